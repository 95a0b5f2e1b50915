/* cstomo-fw-host: the reference firmware's core on a POSIX host, serving a pseudo-terminal.
 *
 *   cstomo-fw-host --frames FILE [--layers 2] [--noise V] [--rate HZ] [--link PATH]
 *                  [--protocol binary|text] [--duration S] [--seed N] [faults...]
 *
 * Prints "device: /dev/pts/N" (the path a host opens) first, then serves until SIGINT/SIGTERM or
 * --duration; at the end one line of counts on stderr. */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "../core/board.h"
#include "../core/cstomo_protocol.h"
#include "../core/hal.h"
#include "../core/wire.h"
#include "host.h"

#define FIRMWARE_HOST "cstomo-fw 1.0 (host)"

static volatile sig_atomic_t stop;
static void on_signal(int sig) { (void)sig; stop = 1; }

static void usage(const char *why) {
    fprintf(stderr,
            "cstomo-fw-host: %s\n"
            "usage: cstomo-fw-host --frames FILE [--layers 1|2] [--noise V] [--rate HZ] [--max-rate HZ]\n"
            "       [--link PATH] [--protocol binary|text] [--duration S] [--seed N] [--full-scale V]\n"
            "       [--drop P] [--bit-flip P] [--truncate P] [--garbage P] [--garbage-bytes N]\n"
            "       [--dead-electrode E] [--saturate-channel I] [--patterns MASK]\n",
            why);
    exit(2);
}

/* A frames file (docs/formats.md#frames-file): rows of 208 comma-separated volts, '#' comments. */
static float *read_frames(const char *path, size_t *n_out) {
    FILE *f = fopen(path, "r");
    if (!f) {
        fprintf(stderr, "cstomo-fw-host: --frames %s: %s\n", path, strerror(errno));
        exit(2);
    }
    size_t cap = 16, n = 0;
    float *rows = malloc(cap * CSTOMO_N_VALUES * sizeof *rows); /* the host's front-end, not the core */
    char *line = NULL;
    size_t line_cap = 0;
    unsigned long lineno = 0;
    while (getline(&line, &line_cap, f) > 0) {
        lineno++;
        char *p = line;
        while (*p == ' ' || *p == '\t')
            p++;
        if (*p == '#' || *p == '\n' || *p == '\r' || !*p)
            continue;
        if (n == cap) {
            cap *= 2;
            rows = realloc(rows, cap * CSTOMO_N_VALUES * sizeof *rows);
        }
        for (int i = 0; i < CSTOMO_N_VALUES; i++) {
            char *end;
            double v = strtod(p, &end);
            if (end == p || v != v || v > 1e30 || v < -1e30) {
                fprintf(stderr, "cstomo-fw-host: --frames %s line %lu: value %d is not a finite number\n", path,
                        lineno, i + 1);
                exit(2);
            }
            rows[n * CSTOMO_N_VALUES + i] = (float)v;
            while (*end == ' ' || *end == '\t')
                end++;
            if (i < CSTOMO_N_VALUES - 1 && *end != ',') {
                fprintf(stderr, "cstomo-fw-host: --frames %s line %lu: %d values; expected %d\n", path, lineno,
                        i + 1, CSTOMO_N_VALUES);
                exit(2);
            }
            p = end + 1;
        }
        n++;
    }
    free(line);
    fclose(f);
    if (!n) {
        fprintf(stderr, "cstomo-fw-host: --frames %s: no frame in it\n", path);
        exit(2);
    }
    *n_out = n;
    return rows;
}

static double number(const char *opt, const char *s, double lo, double hi) {
    char *end;
    double v = strtod(s, &end);
    if (end == s || *end || !(v >= lo && v <= hi)) {
        char why[160];
        snprintf(why, sizeof why, "%s %s: expected a number in %g..%g", opt, s, lo, hi);
        usage(why);
    }
    return v;
}

static int open_pty(const char *link, char *name, size_t cap) {
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) || unlockpt(m) || !ptsname(m)) {
        perror("cstomo-fw-host: pty");
        exit(1);
    }
    snprintf(name, cap, "%s", ptsname(m));
    /* hold the slave open (raw): a host may close and reopen it without the master seeing a hangup */
    int s = open(name, O_RDWR | O_NOCTTY);
    struct termios t;
    if (s < 0 || tcgetattr(s, &t)) {
        perror("cstomo-fw-host: pty slave");
        exit(1);
    }
    cfmakeraw(&t);
    tcsetattr(s, TCSANOW, &t);
    fcntl(m, F_SETFL, fcntl(m, F_GETFL) | O_NONBLOCK);
    if (link) {
        char tmp[4096];
        snprintf(tmp, sizeof tmp, "%s.%d.tmp", link, (int)getpid());
        unlink(tmp);
        if (symlink(name, tmp) || rename(tmp, link)) {
            fprintf(stderr, "cstomo-fw-host: --link %s: %s\n", link, strerror(errno));
            exit(2);
        }
    }
    return m;
}

static void hex(const char *label, const uint8_t *p, size_t n) {
    printf("%s", label);
    for (size_t i = 0; i < n; i++)
        printf(" %02x", p[i]);
    printf("\n");
}

/* --selftest: the framing's results for the examples of docs/protocol.md (a test compares them). */
static int selftest(void) {
    static uint8_t pkt[CSTOMO_MAX_PACKET], wire[CSTOMO_MAX_ENCODED];
    printf("crc32 123456789 %08x\n", crc32_update(0, (const uint8_t *)"123456789", 9));
    static const uint8_t zero[] = {0x00}, ex[] = {0x11, 0x22, 0x00, 0x33};
    hex("cobs 00", wire, cobs_encode(zero, sizeof zero, wire));
    hex("cobs 11 22 00 33", wire, cobs_encode(ex, sizeof ex, wire));
    uint8_t run[600];
    for (size_t i = 0; i < sizeof run; i++)
        run[i] = (uint8_t)(i % 255 + 1);
    size_t n = cobs_encode(run, sizeof run, wire);
    long back = cobs_decode(wire, n, pkt);
    printf("cobs 600 non-zero bytes: %zu encoded, round trip %s\n", n,
           back == (long)sizeof run && !memcmp(pkt, run, sizeof run) ? "ok" : "FAILED");
    hex("IDENTIFY", wire, packet_to_wire(pkt, packet_finish(pkt, CSTOMO_MSG_IDENTIFY, 0), wire));
    put_u32(pkt + CSTOMO_HEADER_LEN, f32_bits(200.0f));
    hex("START 200 Hz", wire, packet_to_wire(pkt, packet_finish(pkt, CSTOMO_MSG_START, 4), wire));
    pkt[CSTOMO_HEADER_LEN] = CSTOMO_MSG_START;
    hex("ACK of START", wire, packet_to_wire(pkt, packet_finish(pkt, CSTOMO_MSG_ACK, 1), wire));
    return 0;
}

int main(int argc, char **argv) {
    if (argc == 2 && !strcmp(argv[1], "--selftest"))
        return selftest();
    const char *frames_path = NULL, *link = NULL;
    double duration = 0;
    frontend_config_t fe = {.file_layers = 2, .full_scale_v = 2.5, .garbage_bytes = 48, .dead_electrode = -1,
                            .saturate_channel = -1};
    board_config_t cfg = {.firmware = FIRMWARE_HOST, .default_rate_hz = 200.0f, .max_rate_hz = 10000.0f,
                          .max_current_a = 0.05f, .patterns = (1u << 1) | (1u << 2), .layers = 2,
                          .resync_us = 100000};
    static const struct option opts[] = {
        {"frames", 1, 0, 'f'}, {"layers", 1, 0, 'l'}, {"noise", 1, 0, 'n'}, {"rate", 1, 0, 'r'},
        {"max-rate", 1, 0, 'M'}, {"link", 1, 0, 'L'}, {"protocol", 1, 0, 'p'}, {"duration", 1, 0, 'd'},
        {"seed", 1, 0, 's'}, {"full-scale", 1, 0, 'F'}, {"drop", 1, 0, 'D'}, {"bit-flip", 1, 0, 'B'},
        {"truncate", 1, 0, 'T'}, {"garbage", 1, 0, 'G'}, {"garbage-bytes", 1, 0, 'g'},
        {"dead-electrode", 1, 0, 'E'}, {"saturate-channel", 1, 0, 'S'}, {"patterns", 1, 0, 'P'},
        {"help", 0, 0, 'h'}, {0, 0, 0, 0}};
    int c;
    while ((c = getopt_long(argc, argv, "", opts, NULL)) != -1) {
        switch (c) {
        case 'f': frames_path = optarg; break;
        case 'l': fe.file_layers = cfg.layers = (uint8_t)number("--layers", optarg, 1, 2); break;
        case 'n': fe.noise_v = number("--noise", optarg, 0, 10); break;
        case 'r': cfg.default_rate_hz = (float)number("--rate", optarg, 0.01, 10000); break;
        case 'M': cfg.max_rate_hz = (float)number("--max-rate", optarg, 0.01, 100000); break;
        case 'L': link = optarg; break;
        case 'p':
            if (strcmp(optarg, "binary") && strcmp(optarg, "text"))
                usage("--protocol: expected binary or text");
            cfg.text_mode = !strcmp(optarg, "text");
            break;
        case 'd': duration = number("--duration", optarg, 0, 1e9); break;
        case 's': fe.seed = (uint64_t)number("--seed", optarg, 0, 1e18); break;
        case 'F': fe.full_scale_v = number("--full-scale", optarg, 1e-6, 1e3); break;
        case 'D': fe.drop = number("--drop", optarg, 0, 1); break;
        case 'B': fe.bit_flip = number("--bit-flip", optarg, 0, 1); break;
        case 'T': fe.truncate = number("--truncate", optarg, 0, 1); break;
        case 'G': fe.garbage = number("--garbage", optarg, 0, 1); break;
        case 'g': fe.garbage_bytes = (int)number("--garbage-bytes", optarg, 0, 4096); break;
        case 'E': fe.dead_electrode = (int)number("--dead-electrode", optarg, 0, 15); break;
        case 'S': fe.saturate_channel = (int)number("--saturate-channel", optarg, 0, 207); break;
        case 'P': cfg.patterns = (uint8_t)(((int)number("--patterns", optarg, 1, 3)) << 1); break;
        case 'h': usage("the board's reference firmware on a pseudo-terminal"); break;
        default: usage("unknown option");
        }
    }
    if (!frames_path)
        usage("--frames FILE is required (docs/formats.md#frames-file)");
    fe.frames = read_frames(frames_path, &fe.n_frames);
    host_frontend_init(&fe);
    char name[256];
    int m = open_pty(link, name, sizeof name);
    host_link_init(m);
    struct sigaction sa = {0};
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
    printf("device: %s\n", link ? link : name);
    fflush(stdout);
    uint64_t end_us = duration > 0 ? hal_micros() + (uint64_t)(duration * 1e6) : UINT64_MAX;
    board_init(&cfg);
    while (!stop && hal_micros() < end_us) {
        board_poll();
        uint64_t now = hal_micros(), due = board_next_due_us();
        uint64_t wait = due > now ? due - now : 0;
        if (wait > 20000)
            wait = 20000;
        if (wait == 0 && due != UINT64_MAX)
            continue;
        struct pollfd p = {m, POLLIN | (host_link_pending() ? POLLOUT : 0), 0};
        struct timespec ts = {0, (long)wait * 1000};
        ppoll(&p, 1, &ts, NULL);
    }
    const board_stats_t *st = board_get_stats();
    const host_counts_t *hc = host_counts();
    fprintf(stderr,
            "cstomo-fw-host: measured %u frames, sent %u, not sent for want of room %u, slots skipped %u, "
            "commands %u (refused %u), packets ignored %u, longest frame %u us; injected: drop %lu, "
            "bit_flip %lu, truncate %lu, garbage %lu\n",
            st->measured, st->sent, st->no_room, st->skipped, st->commands, st->refused, st->dropped,
            st->max_frame_us, hc->drop, hc->bit_flip, hc->truncate, hc->garbage);
    if (link)
        unlink(link);
    return 0;
}
