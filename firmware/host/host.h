/* The host build's shared state: the pseudo-terminal, the analog front-end's frames and its faults. */
#ifndef CSTOMO_HOST_H
#define CSTOMO_HOST_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

typedef struct {
    /* the analog front-end */
    const float *frames;   /* n_frames rows of 208 volts at 8 mA, in the file's pattern order */
    size_t n_frames;
    uint8_t file_layers;   /* the pattern the file's rows are in */
    double noise_v;        /* added white noise, volts rms */
    double full_scale_v;   /* the channel's full scale: beyond it a value is clipped and flagged */
    /* faults, as cstomo board-sim's (probabilities per frame) */
    double drop, bit_flip, truncate, garbage;
    int garbage_bytes;
    int dead_electrode;    /* -1: none */
    int saturate_channel;  /* -1: none */
    uint64_t seed;
} frontend_config_t;

void host_frontend_init(const frontend_config_t *c);
/* the link: the pseudo-terminal's master (non-blocking) */
void host_link_init(int master_fd);
/* bytes waiting in the transmit queue */
size_t host_link_pending(void);
/* counts of injected faults */
typedef struct {
    unsigned long drop, bit_flip, truncate, garbage, link_full, rows_played;
} host_counts_t;
const host_counts_t *host_counts(void);

#endif
