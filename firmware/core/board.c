/* The protocol engine: docs/protocol.md version 1 over the HAL of hal.h. See board.h. */
#include "board.h"

#include <string.h>

#include "cstomo_protocol.h"
#include "hal.h"
#include "schedule.h"
#include "wire.h"

/* a text line: 208 values of at most 16 characters ("-9999999999e-9,") and the newline */
#define TEXT_LINE_MAX (CSTOMO_N_VALUES * 16 + 2)
#define MIN_RATE_HZ 0.01f  /* a period of 100 s at most: the schedule's arithmetic stays in range */

static board_config_t cfg;
static board_stats_t st;
static schedule_t sched;

static uint8_t rx[CSTOMO_MAX_ENCODED];  /* one piece between 0x00 delimiters; decoded in place */
static size_t rx_len;
static bool rx_skip;                    /* the piece overflowed: skip to the next delimiter */
static uint8_t pkt[CSTOMO_MAX_PACKET];  /* the packet being sent */
static union {
    uint8_t wire[CSTOMO_MAX_ENCODED];
    char text[TEXT_LINE_MAX];
} out;

static bool streaming;
static float rate_hz;
static uint64_t t0_us;        /* the schedule's origin: frame k is due at t0 + k / rate */
static uint64_t period_q16;   /* the frame period in 2^-16 microseconds */
static uint32_t k_next;       /* the next frame slot */
static uint32_t seq;          /* the next frame's sequence number */

/* --- small text builder (no printf: it costs kilobytes of flash) ---------------------------- */
typedef struct {
    char *p;
    size_t n, cap;
} text_t;

static void t_str(text_t *t, const char *s) {
    while (*s && t->n < t->cap)
        t->p[t->n++] = *s++;
}

static void t_uint(text_t *t, uint64_t v) {
    char d[21];
    int i = 0;
    do {
        d[i++] = (char)('0' + v % 10);
        v /= 10;
    } while (v);
    while (i && t->n < t->cap)
        t->p[t->n++] = d[--i];
}

static void t_int(text_t *t, int64_t v) {
    if (v < 0) {
        t_str(t, "-");
        t_uint(t, (uint64_t)0 - (uint64_t)v);
    } else {
        t_uint(t, (uint64_t)v);
    }
}

static void t_hex8(text_t *t, uint8_t v) {
    static const char hex[] = "0123456789abcdef";
    char s[5] = {'0', 'x', hex[v >> 4], hex[v & 15], 0};
    t_str(t, s);
}

static bool finite_f32(float f) { return (f32_bits(f) & 0x7F800000u) != 0x7F800000u; }

/* a float for a message: integer part and three decimals ("nan", "inf", ">1e9" when it is one) */
static void t_float(text_t *t, float f) {
    if (!finite_f32(f)) {
        t_str(t, f != f ? "nan" : f > 0 ? "inf" : "-inf");
        return;
    }
    if (f < 0) {
        t_str(t, "-");
        f = -f;
    }
    if (f >= 1e9f) {
        t_str(t, ">1e9");
        return;
    }
    uint64_t milli = (uint64_t)(f * 1000.0f + 0.5f);
    t_uint(t, milli / 1000);
    uint32_t frac = (uint32_t)(milli % 1000);
    if (frac) {
        char d[5] = {'.', (char)('0' + frac / 100), (char)('0' + frac / 10 % 10), (char)('0' + frac % 10), 0};
        for (int i = 3; i > 1 && d[i] == '0'; i--)
            d[i] = 0;
        t_str(t, d);
    }
}

/* --- sending -------------------------------------------------------------------------------- */
/* Queue pkt (payload of `len` bytes already at pkt + 4) as a packet of `type`; false: no room. */
static bool send_packet(uint8_t type, uint16_t len) {
    size_t n = packet_finish(pkt, type, len);
    size_t w = packet_to_wire(pkt, n, out.wire);
    if (hal_link_tx_room() < w)
        return false;
    hal_link_write(out.wire, w);
    return true;
}

static void answer(uint8_t type, uint16_t len) {
    st.commands++;
    if (!send_packet(type, len))
        st.answers_lost++;
}

static void ack(uint8_t command) {
    pkt[CSTOMO_HEADER_LEN] = command;
    answer(CSTOMO_MSG_ACK, 1);
}

/* ERROR for `command` with `code`; the text is built by the caller into a text_t from error_text() */
static text_t error_text(void) {
    text_t t = {(char *)pkt + CSTOMO_HEADER_LEN + 2, 0, CSTOMO_MAX_ERROR_TEXT};
    return t;
}

static void refuse(uint8_t command, uint8_t code, const text_t *t) {
    pkt[CSTOMO_HEADER_LEN] = command;
    pkt[CSTOMO_HEADER_LEN + 1] = code;
    st.refused++;
    answer(CSTOMO_MSG_ERROR, (uint16_t)(2 + t->n));
}

static void refuse_length(uint8_t command, size_t got, size_t want) {
    text_t t = error_text();
    t_str(&t, "payload of ");
    t_uint(&t, got);
    t_str(&t, " bytes for command ");
    t_hex8(&t, command);
    t_str(&t, "; expected ");
    t_uint(&t, want);
    refuse(command, CSTOMO_ERR_BAD_ARGUMENT, &t);
}

/* --- streaming ------------------------------------------------------------------------------ */
static void start_schedule(void) {
    /* 2^16 * 1e6 / rate in double once per START: the per-frame arithmetic is integer */
    period_q16 = (uint64_t)(65536.0e6 / (double)rate_hz + 0.5);
    if (period_q16 == 0)
        period_q16 = 1;
    t0_us = hal_micros();
    k_next = 0;
    streaming = true;
    hal_current_on(true);
}

static uint64_t due_us(uint32_t k) { return t0_us + (((uint64_t)k * period_q16) >> 16); }

/* Measure one frame into pkt's DATA payload (and the float values into `values`). */
static void measure(uint64_t now, float *values) {
    uint8_t *p = pkt + CSTOMO_HEADER_LEN;
    put_u32(p, seq);
    put_u64(p + 4, now);
    seq++;
    st.measured++;
    uint8_t *sat = p + CSTOMO_DATA_HEAD_LEN;
    uint8_t *val = sat + CSTOMO_SAT_BYTES;
    memset(sat, 0, CSTOMO_SAT_BYTES);
    unsigned i = 0;
    for (unsigned d = 0; d < CSTOMO_N_PAIRS; d++) {
        hal_select_drive(sched.pair[d][0], sched.pair[d][1]);
        for (unsigned j = 0; j < CSTOMO_N_MEASURE; j++, i++) {
            const uint8_t *m = sched.pair[sched.measure[d][j]];
            hal_select_measure(m[0], m[1]);
            hal_settle(j == 0);
            bool s = false;
            float v = hal_read_sample(&s);
            if (!finite_f32(v)) { /* a receiver drops a frame holding NaN: never send one */
                v = 0.0f;
                s = true;
            }
            if (s)
                sat[i >> 3] |= (uint8_t)(1u << (i & 7));
            values[i] = v;
            put_u32(val + 4 * i, f32_bits(v));
        }
        hal_link_poll(); /* keep the line busy while measuring */
    }
    uint16_t contact = 0;
    for (unsigned e = 0; e < CSTOMO_N_ELECTRODES; e++)
        if (hal_contact_ok((uint8_t)e))
            contact |= (uint16_t)(1u << e);
    put_u16(p + 12, contact);
}

/* One text line: the values as integer nanovolts ("-153296140e-9"), which Python's float() reads. */
static size_t text_line(const float *values) {
    text_t t = {out.text, 0, TEXT_LINE_MAX};
    for (unsigned i = 0; i < CSTOMO_N_VALUES; i++) {
        double nv = (double)values[i] * 1e9; /* exact to the nanovolt (soft double on an M4F: text mode only) */
        if (nv > 9.0e18)
            nv = 9.0e18;
        if (nv < -9.0e18)
            nv = -9.0e18;
        int64_t q = (int64_t)(nv < 0 ? nv - 0.5 : nv + 0.5);
        if (i)
            t_str(&t, ",");
        t_int(&t, q);
        t_str(&t, "e-9");
    }
    t_str(&t, "\n");
    return t.n;
}

static void frame(uint64_t now) {
    static float values[CSTOMO_N_VALUES];
    measure(now, values);
    uint64_t measured = hal_micros();
    size_t w;
    if (cfg.text_mode) {
        w = text_line(values);
    } else {
        size_t n = packet_finish(pkt, CSTOMO_MSG_DATA, CSTOMO_DATA_LEN);
        w = packet_to_wire(pkt, n, out.wire);
    }
    if (hal_link_tx_room() >= w) { /* else measured but not sent: its seq is used, the host sees a gap */
        hal_link_write(out.wire, w);
        st.sent++;
    } else {
        st.no_room++;
    }
    uint64_t done = hal_micros(), took = done - now;
    if (done - measured > st.max_encode_us)
        st.max_encode_us = (uint32_t)(done - measured);
    if (took > st.max_frame_us)
        st.max_frame_us = took > 0xFFFFFFFFu ? 0xFFFFFFFFu : (uint32_t)took;
}

/* --- commands ------------------------------------------------------------------------------- */
static void command(uint8_t type, const uint8_t *payload, size_t len) {
    text_t t = error_text();
    switch (type) {
    case CSTOMO_MSG_IDENTIFY: {
        if (len != 0)
            return refuse_length(type, len, 0);
        uint8_t *p = pkt + CSTOMO_HEADER_LEN;
        put_u16(p, CSTOMO_PROTOCOL_VERSION);
        p[2] = CSTOMO_N_ELECTRODES;
        put_u16(p + 3, CSTOMO_N_VALUES);
        size_t n = 0;
        while (cfg.firmware[n] && n < CSTOMO_MAX_FIRMWARE_TEXT) {
            p[CSTOMO_IDENTITY_HEAD_LEN + n] = (uint8_t)cfg.firmware[n];
            n++;
        }
        return answer(CSTOMO_MSG_IDENTITY, (uint16_t)(CSTOMO_IDENTITY_HEAD_LEN + n));
    }
    case CSTOMO_MSG_START: {
        if (len != 4)
            return refuse_length(type, len, 4);
        float r = f32_from_bits(get_u32(payload));
        if (!(r == 0.0f || (r >= MIN_RATE_HZ && r <= cfg.max_rate_hz))) { /* NaN fails both */
            t_str(&t, "rate ");
            t_float(&t, r);
            t_str(&t, " Hz not in 0.01..");
            t_float(&t, cfg.max_rate_hz);
            t_str(&t, " (0: the default rate)");
            return refuse(type, CSTOMO_ERR_BAD_ARGUMENT, &t);
        }
        rate_hz = r > 0.0f ? r : cfg.default_rate_hz;
        ack(type); /* before the first frame */
        start_schedule();
        return;
    }
    case CSTOMO_MSG_STOP:
        if (len != 0)
            return refuse_length(type, len, 0);
        streaming = false;
        hal_current_on(false);
        return ack(type);
    case CSTOMO_MSG_SET_CURRENT: {
        if (len != 4)
            return refuse_length(type, len, 4);
        float a = f32_from_bits(get_u32(payload));
        if (!(a > 0.0f && a <= cfg.max_current_a)) {
            t_str(&t, "current ");
            t_float(&t, a * 1000.0f);
            t_str(&t, " mA not in (0, ");
            t_float(&t, cfg.max_current_a * 1000.0f);
            t_str(&t, "] mA");
            return refuse(type, CSTOMO_ERR_BAD_ARGUMENT, &t);
        }
        if (!hal_current_set(a)) {
            t_str(&t, "the current source cannot give ");
            t_float(&t, a * 1000.0f);
            t_str(&t, " mA");
            return refuse(type, CSTOMO_ERR_NOT_SUPPORTED, &t);
        }
        return ack(type);
    }
    case CSTOMO_MSG_SET_PATTERN: {
        if (len != 1)
            return refuse_length(type, len, 1);
        uint8_t p = payload[0];
        if (p != CSTOMO_PATTERN_ONE_RING && p != CSTOMO_PATTERN_TWO_RINGS) {
            t_str(&t, "pattern ");
            t_uint(&t, p);
            t_str(&t, ": expected 1 (one ring) or 2 (two rings)");
            return refuse(type, CSTOMO_ERR_BAD_ARGUMENT, &t);
        }
        if (!(cfg.patterns & (1u << p))) {
            t_str(&t, "pattern ");
            t_uint(&t, p);
            t_str(&t, " rings: this board's multiplexers cannot switch it");
            return refuse(type, CSTOMO_ERR_NOT_SUPPORTED, &t);
        }
        schedule_build(&sched, p); /* the next frame measures in the new order */
        return ack(type);
    }
    default:
        t_str(&t, "not a command: type ");
        t_hex8(&t, type);
        return refuse(type, CSTOMO_ERR_UNKNOWN_COMMAND, &t);
    }
}

/* One piece between delimiters: decode, check, answer. */
static void piece(size_t n) {
    long m = cobs_decode(rx, n, rx);
    if (m < CSTOMO_HEADER_LEN + CSTOMO_CRC_LEN || m > CSTOMO_MAX_PACKET) {
        st.dropped++;
        return;
    }
    size_t body = (size_t)m - CSTOMO_CRC_LEN;
    if (crc32_update(0, rx, body) != get_u32(rx + body)) {
        st.dropped++; /* nothing in it can be trusted, not even its type: ignored */
        return;
    }
    uint8_t version = rx[0], type = rx[1];
    size_t len = body - CSTOMO_HEADER_LEN;
    text_t t = error_text();
    if (version != CSTOMO_PROTOCOL_VERSION) {
        t_str(&t, "protocol version ");
        t_uint(&t, version);
        t_str(&t, "; this board speaks 1");
        return refuse(type, CSTOMO_ERR_BAD_VERSION, &t);
    }
    if (get_u16(rx + 2) != len) {
        t_str(&t, "length field ");
        t_uint(&t, get_u16(rx + 2));
        t_str(&t, " but a payload of ");
        t_uint(&t, len);
        t_str(&t, " bytes");
        return refuse(type, CSTOMO_ERR_BAD_ARGUMENT, &t);
    }
    command(type, rx + CSTOMO_HEADER_LEN, len);
}

void board_feed(const uint8_t *data, unsigned long n) {
    if (cfg.text_mode)
        return; /* text boards are deaf */
    for (unsigned long i = 0; i < n; i++) {
        uint8_t b = data[i];
        if (b == 0) {
            if (rx_len && !rx_skip)
                piece(rx_len);
            rx_len = 0;
            rx_skip = false;
        } else if (rx_skip) {
            continue;
        } else if (rx_len < sizeof rx) {
            rx[rx_len++] = b;
        } else {
            st.dropped++;
            rx_skip = true;
            rx_len = 0;
        }
    }
}

/* --- the loop ------------------------------------------------------------------------------- */
void board_init(const board_config_t *c) {
    cfg = *c;
    memset(&st, 0, sizeof st);
    if (!schedule_build(&sched, cfg.layers))
        schedule_build(&sched, CSTOMO_PATTERN_TWO_RINGS);
    rx_len = 0;
    rx_skip = false;
    seq = 0;
    streaming = false;
    rate_hz = cfg.default_rate_hz;
    hal_current_set(CSTOMO_DRIVE_CURRENT_A);
    if (cfg.text_mode)
        start_schedule();
}

void board_poll(void) {
    static uint8_t buf[256];
    size_t n;
    if (hal_link_reconnected() && !cfg.text_mode) { /* a new host: idle until START */
        streaming = false;
        rx_len = 0;
        rx_skip = false;
        hal_current_on(false);
    }
    for (int i = 0; i < 4 && (n = hal_link_read(buf, sizeof buf)) > 0; i++) /* a flood of input never */
        board_feed(buf, n);                                                 /* starves the schedule */
    hal_link_poll();
    if (!streaming)
        return;
    uint64_t now = hal_micros();
    uint64_t due = due_us(k_next);
    if (now < due)
        return;
    if (now - due > cfg.resync_us) { /* fell behind (a stalled line, a debugger): skip, do not burst */
        uint64_t k = ((((now - t0_us) << 16) + period_q16 - 1) / period_q16);
        st.skipped += (uint32_t)(k - k_next);
        t0_us += (k >> 16) * period_q16; /* rebase (below) */
        k_next = (uint32_t)(k & 0xFFFFu);
        return;
    }
    frame(now);
    if (++k_next == 0x10000u) { /* rebase every 2^16 slots, exactly (due_us(2^16) = t0 + period_q16): */
        t0_us += period_q16;    /* k_next never wraps, whatever the uptime */
        k_next = 0;
    }
    hal_link_poll();
}

const board_stats_t *board_get_stats(void) { return &st; }

bool board_streaming(void) { return streaming; }

uint64_t board_next_due_us(void) { return streaming ? due_us(k_next) : UINT64_MAX; }
