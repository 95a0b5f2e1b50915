/* The STM32F4 firmware: the portable core (core/board.c) on hal_stm32.c, and the table front-end the
 * emulated build (QEMU) measures: the frames of frames_table.c, row after row, plus noise. */
#include <stdint.h>

#include "../core/board.h"
#include "../core/cstomo_protocol.h"
#include "../core/hal.h"
#include "../core/schedule.h"
#include "stm32_board.h"

#define FIRMWARE_STM32 "cstomo-fw 1.0 (stm32f4, table front-end)"

static schedule_t table_order; /* the order of the table's rows */
static uint32_t row, sweeps;
static int drive_index = -1;
static uint32_t rng = 0x12345678u;

static uint32_t xorshift32(void) {
    rng ^= rng << 13;
    rng ^= rng >> 17;
    rng ^= rng << 5;
    return rng;
}

/* approximately normal, unit variance: the sum of four uniforms (variance 4 / 12) times sqrt(3) */
static float noise(void) {
    float s = 0.0f;
    for (int i = 0; i < 4; i++)
        s += (float)(xorshift32() >> 8) * (1.0f / 16777216.0f);
    return (s - 2.0f) * 1.7320508f;
}

void frontend_sweep(uint8_t source, uint8_t sink) {
    drive_index = -1;
    for (int d = 0; d < CSTOMO_N_PAIRS; d++)
        if (table_order.pair[d][0] == source && table_order.pair[d][1] == sink)
            drive_index = d;
    if (source == 0 && sink == 1) { /* a sweep starts again at drive (1,2): the table's next row */
        if (sweeps++)
            row = (row + 1) % cstomo_n_frames;
    }
}

float frontend_value(uint8_t source, uint8_t sink, uint8_t pos, uint8_t neg) {
    (void)source;
    (void)sink;
    float v = 0.0f;
    if (drive_index >= 0)
        for (int j = 0; j < CSTOMO_N_MEASURE; j++) {
            const uint8_t *m = table_order.pair[table_order.measure[drive_index][j]];
            if (m[0] == pos && m[1] == neg)
                v = cstomo_frames[row][schedule_index((unsigned)drive_index, (unsigned)j)];
        }
    return v + cstomo_noise_v * noise();
}

static char *fmt_u32(char *p, const char *label, uint32_t v) {
    while (*label)
        *p++ = *label++;
    char d[10];
    int i = 0;
    do {
        d[i++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    while (i)
        *p++ = d[--i];
    return p;
}

int main(void) {
    stm32_init();
    schedule_build(&table_order, cstomo_frames_layers);
    static const board_config_t cfg = {
        .firmware = FIRMWARE_STM32,
        .default_rate_hz = 100.0f,  /* what a 921600-baud UART carries (docs/protocol.md 1.9) */
        .max_rate_hz = 1000.0f,     /* the analog chain's limit (docs/firmware.md, timing budget) */
        .max_current_a = 0.02f,
        .patterns = (1u << 1) | (1u << 2),
        .layers = 2,
        .text_mode = false,
        .resync_us = 100000,
    };
    board_init(&cfg);
    debug_write("cstomo-fw stm32: up\r\n");
    uint64_t next_report = hal_micros() + 100000u;
    for (;;) {
        board_poll();
        if (hal_micros() >= next_report) { /* ten times a second on the debug console */
            next_report += 100000u;
            const board_stats_t *st = board_get_stats();
            char line[160], *p = line;
            p = fmt_u32(p, "measured ", st->measured);
            p = fmt_u32(p, " sent ", st->sent);
            p = fmt_u32(p, " no_room ", st->no_room);
            p = fmt_u32(p, " skipped ", st->skipped);
            p = fmt_u32(p, " commands ", st->commands);
            p = fmt_u32(p, " ignored ", st->dropped);
            p = fmt_u32(p, " max_frame_us ", st->max_frame_us);
            p = fmt_u32(p, " max_encode_us ", st->max_encode_us);
            *p++ = '\r';
            *p++ = '\n';
            *p = 0;
            debug_write(line);
        }
    }
}
