/* The board's protocol engine (docs/protocol.md, version 1): answers commands, measures frames on an
 * absolute schedule (t0 + k / rate) through the HAL and streams them. One static instance: no heap,
 * no OS; call board_init once, then board_poll as often as possible from the main loop. */
#ifndef CSTOMO_BOARD_H
#define CSTOMO_BOARD_H

#include <stdbool.h>
#include <stdint.h>

typedef struct {
    const char *firmware;   /* IDENTITY text (0..64 bytes of UTF-8) */
    float default_rate_hz;  /* START with rate 0, and text mode's rate */
    float max_rate_hz;      /* START above this: ERROR bad argument */
    float max_current_a;    /* SET_CURRENT outside (0, max]: ERROR bad argument */
    uint8_t patterns;       /* bit p set: SET_PATTERN p can be switched (p = 1, 2) */
    uint8_t layers;         /* pattern at power-up */
    bool text_mode;         /* stream text lines from power-up, deaf to commands */
    uint32_t resync_us;     /* a frame later than this is skipped with the ones missed (not measured) */
} board_config_t;

typedef struct {
    uint32_t measured;      /* frames measured (each used a seq) */
    uint32_t sent;          /* frames queued whole on the link */
    uint32_t no_room;       /* frames measured but not sent: the link's queue was full (a seq gap) */
    uint32_t skipped;       /* frame slots skipped after falling behind by more than resync_us */
    uint32_t commands;      /* commands answered (ACK, IDENTITY or ERROR) */
    uint32_t refused;       /* of which ERROR */
    uint32_t dropped;       /* packets ignored: bad COBS, length or CRC, or too long */
    uint32_t answers_lost;  /* answers not queued: no room on the link */
    uint32_t max_frame_us;  /* the longest measurement + encoding of one frame */
    uint32_t max_encode_us; /* the longest encoding of one frame (packing, CRC, COBS, queueing) */
} board_stats_t;

void board_init(const board_config_t *cfg);
/* One step: take the link's bytes, answer what they complete, measure and send a frame when due. */
void board_poll(void);
const board_stats_t *board_get_stats(void);
/* The time (hal_micros) the next frame is due; UINT64_MAX while idle (a main loop may sleep until then). */
uint64_t board_next_due_us(void);
/* true while streaming (after START, or always in text mode) */
bool board_streaming(void);

/* Feed received bytes directly (board_poll does this with hal_link_read; tests and fuzzers call it). */
void board_feed(const uint8_t *data, unsigned long n);

#endif
