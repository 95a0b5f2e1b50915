#define _POSIX_C_SOURCE 200809L
/* The HAL on a POSIX host: the link is a pseudo-terminal, the clock CLOCK_MONOTONIC, and the analog
 * front-end answers from a frames file (docs/formats.md#frames-file) with noise and board-sim's faults.
 * The front-end plays the file's next row each time a sweep starts again at drive pair (1,2), and
 * finds each value's column by its electrodes, so a frame in the other SET_PATTERN order reads the
 * values the file has for those electrodes (noise only where it has none). */
#include <errno.h>
#include <math.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "../core/cstomo_protocol.h"
#include "../core/hal.h"
#include "../core/schedule.h"
#include "host.h"

#define TX_RING 32768u /* a pty holds ~16 kB more in the kernel */

static frontend_config_t fe;
static host_counts_t counts;
static int16_t column[16][16][16][16]; /* [source][sink][pos][neg] -> column of the file, -1: none */
static size_t row;
static bool row_started;
static uint8_t drive_src, drive_sink, meas_pos, meas_neg;
static float current_a = CSTOMO_DRIVE_CURRENT_A;
static bool current_on;
static uint64_t rng_state;

/* xorshift64* and Box-Muller: the noise */
static uint64_t rng_next(void) {
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return rng_state * 2685821657736338717ull;
}
static double uniform(void) { return ((double)(rng_next() >> 11) + 0.5) * (1.0 / 9007199254740992.0); }
static double gauss(void) { return sqrt(-2.0 * log(uniform())) * cos(6.283185307179586 * uniform()); }

void host_frontend_init(const frontend_config_t *c) {
    fe = *c;
    rng_state = c->seed * 0x9E3779B97F4A7C15ull + 0x2545F4914F6CDD1Dull;
    if (!rng_state)
        rng_state = 1;
    memset(column, 0xFF, sizeof column);
    schedule_t s;
    schedule_build(&s, c->file_layers);
    for (unsigned d = 0; d < CSTOMO_N_PAIRS; d++)
        for (unsigned j = 0; j < CSTOMO_N_MEASURE; j++) {
            const uint8_t *a = s.pair[d], *m = s.pair[s.measure[d][j]];
            column[a[0]][a[1]][m[0]][m[1]] = (int16_t)schedule_index(d, j);
        }
}

const host_counts_t *host_counts(void) { return &counts; }

void hal_select_drive(uint8_t source, uint8_t sink) {
    drive_src = source & 15;
    drive_sink = sink & 15;
    if (drive_src == 0 && drive_sink == 1) { /* a sweep starts: the next row */
        if (row_started)
            row = (row + 1) % (fe.n_frames ? fe.n_frames : 1);
        row_started = true;
        counts.rows_played++;
    }
}

void hal_select_measure(uint8_t pos, uint8_t neg) {
    meas_pos = pos & 15;
    meas_neg = neg & 15;
}

void hal_settle(bool drive_changed) { (void)drive_changed; }

static bool touches_dead(void) {
    int e = fe.dead_electrode;
    return e >= 0 && (drive_src == e || drive_sink == e || meas_pos == e || meas_neg == e);
}

float hal_read_sample(bool *saturated) {
    int col = column[drive_src][drive_sink][meas_pos][meas_neg];
    double v = 0.0;
    if (touches_dead()) {
        v = 1e-3 * gauss(); /* an open electrode reads noise */
    } else {
        if (col >= 0 && fe.n_frames)
            v = fe.frames[row * CSTOMO_N_VALUES + (size_t)col] * (current_a / CSTOMO_DRIVE_CURRENT_A);
        if (!current_on)
            v = 0.0;
        if (fe.noise_v > 0)
            v += fe.noise_v * gauss();
    }
    bool sat = false;
    if (col >= 0 && col == fe.saturate_channel) {
        v = v >= 0 ? fe.full_scale_v : -fe.full_scale_v;
        sat = true;
    } else if (fabs(v) >= fe.full_scale_v) {
        v = v >= 0 ? fe.full_scale_v : -fe.full_scale_v;
        sat = true;
    }
    *saturated = sat;
    return (float)v;
}

void hal_current_on(bool on) { current_on = on; }

bool hal_current_set(float amps) {
    current_a = amps;
    return true;
}

bool hal_contact_ok(uint8_t electrode) { return (int)electrode != fe.dead_electrode; }

uint64_t hal_micros(void) {
    static struct timespec start;
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    if (!start.tv_sec && !start.tv_nsec)
        start = now;
    return (uint64_t)(now.tv_sec - start.tv_sec) * 1000000u + (uint64_t)((now.tv_nsec - start.tv_nsec) / 1000);
}

/* --- link ----------------------------------------------------------------------------------- */
static int master = -1;
static uint8_t ring[TX_RING];
static size_t head, tail; /* bytes [tail, head) queued (mod TX_RING); head - tail <= TX_RING */

void host_link_init(int fd) { master = fd; }
size_t host_link_pending(void) { return head - tail; }

size_t hal_link_read(uint8_t *buf, size_t cap) {
    ssize_t n = read(master, buf, cap);
    return n > 0 ? (size_t)n : 0;
}

size_t hal_link_tx_room(void) {
    size_t room = TX_RING - (head - tail);
    return room;
}

static void push(const uint8_t *p, size_t n) {
    for (size_t i = 0; i < n && head - tail < TX_RING; i++)
        ring[head++ % TX_RING] = p[i];
}

size_t hal_link_write(const uint8_t *buf, size_t n) {
    if (n > hal_link_tx_room())
        return 0;
    if (n < CSTOMO_DATA_PACKET) { /* an answer: never harmed */
        push(buf, n);
        return n;
    }
    /* a frame: board-sim's faults, each drawn once per frame */
    if (uniform() < fe.drop) { /* measured, not sent: the host sees a seq gap */
        counts.drop++;
        return n;
    }
    if (uniform() < fe.garbage) {
        counts.garbage++;
        for (int i = 0; i < fe.garbage_bytes; i++) {
            uint8_t b = (uint8_t)rng_next();
            push(&b, 1);
        }
    }
    size_t len = n;
    if (uniform() < fe.truncate) {
        counts.truncate++;
        len = 2 + (size_t)(uniform() * (double)(n - 4));
    }
    if (uniform() < fe.bit_flip) {
        counts.bit_flip++;
        size_t at = 1 + (size_t)(uniform() * (double)(len - 2));
        size_t start = head;
        push(buf, len);
        ring[(start + at) % TX_RING] ^= (uint8_t)(1u << (rng_next() % 8));
        return n;
    }
    push(buf, len);
    return n;
}

void hal_link_poll(void) {
    while (head != tail) {
        size_t at = tail % TX_RING;
        size_t chunk = head - tail;
        if (chunk > TX_RING - at)
            chunk = TX_RING - at;
        ssize_t w = write(master, ring + at, chunk);
        if (w <= 0) {
            if (w < 0 && errno != EAGAIN && errno != EINTR)
                tail = head; /* the link is gone: what was queued is lost */
            return;
        }
        tail += (size_t)w;
    }
}

bool hal_link_reconnected(void) { return false; }
