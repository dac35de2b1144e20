/* Host port: the firmware core running in real time on Linux.
 *
 * A 3 kHz tick from clock_nanosleep(TIMER_ABSTIME), the serial framing on a pseudo-terminal
 * (its slave path is printed on stdout as "PTY <path>"), simulated encoder motion turned into
 * quadrature pin changes, and a log of every DAC code (binary records, see log_tick).
 *
 * usage: hostd-fw-host [--ppm N] [--ppm-after SECONDS:N]
 *                      [--motion none|constant:MM_S|metronome|steps:PERIOD_S:MM]
 *                      [--log FILE] [--duration SECONDS] [--glitch-at SECONDS]
 *                      [--jump-at SECONDS:MM] [--clock FILE] [--scenario FILE]
 *
 * --clock writes, for every tick, when it actually ran: 12-byte records LE u32 tick, f64
 * CLOCK_MONOTONIC seconds (so tests can place host events, e.g. a SIGCONT, on the device's
 * tick axis even when the host port itself ran late).
 * --jump-at moves the simulated hand by MM at once at SECONDS (and keeps it there): a real
 * jump (the hand lifted and set down elsewhere), which the host's motion estimate must re-lock
 * to. The encoder still steps through every count in between, within one tick.
 * --scenario FILE writes everything the core was given, as a fw-replay scenario (received
 * bytes "r HEX", timed edges, ticks).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "fw.h"
#include "hal.h"

static int g_master = -1;
static uint64_t g_ticks;           /* device ticks since start */
static double g_device_period_ns;  /* nominal 333,333.3 ns, scaled by the clock error */
static FILE *g_log;
static FILE *g_clock;
static FILE *g_scen; /* --scenario: the core's inputs, replayable by fw-replay and the model */
static int16_t g_last_dac;
static volatile sig_atomic_t g_stop;
static unsigned long g_send_dropped;

/* The device's clock: its own tick count at the nominal rate (it is the clock master). */
uint32_t hal_time_us(void) { return (uint32_t)((g_ticks * 1000000ull) / HP_SAMPLE_RATE_HZ); }

void hal_dac_write(int16_t code) { g_last_dac = code; }

void hal_send(const uint8_t *msg, size_t len) {
    uint8_t fr[FW_FRAME_MAX + 4];
    size_t n = fw_frame(msg, len, fr, sizeof fr);
    if (n == 0 || g_master < 0) {
        return;
    }
    ssize_t w = write(g_master, fr, n);
    if (w != (ssize_t)n) {
        g_send_dropped++; /* host not reading: like a NAKed IN endpoint, drop */
    }
}

static void on_signal(int sig) {
    (void)sig;
    g_stop = 1;
}

static double now_s(const struct timespec *t0) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)(t.tv_sec - t0->tv_sec) + (double)(t.tv_nsec - t0->tv_nsec) * 1e-9;
}

/* Hand motion in mm at real time t (the hand lives in the real world, not on a clock). */
enum { M_NONE, M_CONST, M_METRO, M_STEPS };
static int g_motion = M_NONE;
static double g_speed = 50.0;
static double g_step_period = 0.5, g_step_mm = 0.05;
static double g_jump_at = -1, g_jump_mm = 0;

static double motion_mm(double t);
static double hand_mm(double t) { return motion_mm(t) + (g_jump_at >= 0 && t >= g_jump_at ? g_jump_mm : 0.0); }

static double motion_mm(double t) {
    if (g_motion == M_CONST) {
        return g_speed * t;
    }
    if (g_motion == M_STEPS) { /* latency probe: jumps between 0 and g_step_mm every period */
        return ((long)(t / g_step_period) % 2) ? g_step_mm : 0.0;
    }
    if (g_motion == M_METRO) { /* paper: 40 mm, 1.25 Hz, forward 1 beat, back 2, minimum jerk */
        const double tf = 0.8, tb = 1.6, per = 2.4;
        double p = fmod(t, per);
        double s = p < tf ? p / tf : (p - tf) / tb;
        double x = s * s * s * (10 - 15 * s + 6 * s * s);
        return 40.0 * (p < tf ? x : 1.0 - x);
    }
    return 0.0;
}

static const uint8_t GRAY[4] = {0, 1, 3, 2};
static int64_t g_enc_pos; /* true count of the simulated encoder */

static double g_prev_t, g_prev_mm; /* the hand at the previous tick (real time, mm) */

/* Encoder edges up to the hand at real time t: each at the instant the hand crossed its count
 * boundary (linear between ticks), stamped on the device clock's edge timer (render.c). */
static void step_encoder(fw_t *f, double t, double x_mm) {
    const int64_t target = llround(x_mm * 1e6 / HP_UM_PER_COUNT_NM);
    const double rate = 1e9 / HP_SAMPLE_RATE_HZ / g_device_period_ns; /* device s per real s */
    while (g_enc_pos != target) {
        const int d = target > g_enc_pos ? 1 : -1;
        const double xb = ((double)g_enc_pos + 0.5 * d) * HP_UM_PER_COUNT_NM * 1e-6;
        double a = x_mm != g_prev_mm ? (xb - g_prev_mm) / (x_mm - g_prev_mm) : 1.0;
        a = a < 0.0 ? 0.0 : (a > 1.0 ? 1.0 : a);
        const double te = g_prev_t + a * (t - g_prev_t);
        const double dev_s = (double)g_ticks / HP_SAMPLE_RATE_HZ - (t - te) * rate; /* this tick's instant - */
        g_enc_pos += d;
        const uint32_t t_edge = (uint32_t)(uint64_t)llround(dev_s * HP_RENDER_EDGE_CLOCK_HZ);
        fw_encoder_edge(f, GRAY[(uint64_t)g_enc_pos & 3u], t_edge);
        if (g_scen) fprintf(g_scen, "e %u %u\n", GRAY[(uint64_t)g_enc_pos & 3u], t_edge);
    }
    g_prev_t = t, g_prev_mm = x_mm;
}

/* log record, 12 bytes LE: u32 tick, i16 dac code, u32 encoder count (as decoded),
 * u16 flags (bit 0: the code came from the buffer; bit 1: underrun; bit 2: this tick ran more
 * than 1 ms after its due time: the simulated device itself was held up by the host OS, an
 * artefact of the host port that a real device does not have; bit 3: the device was RUNNING;
 * bit 4: the device was RENDERING itself, protocol v2 device mode; bit 5: it rendered the
 * texture at full gain, no fade: the tick RENDER_STATUS counts in rendered_ticks) */
static void log_tick(uint32_t tick, int16_t code, uint32_t enc, uint16_t flags) {
    if (!g_log) return;
    uint8_t r[12] = {0};
    for (int i = 0; i < 4; i++) r[i] = (uint8_t)(tick >> (8 * i));
    r[4] = (uint8_t)((uint16_t)code & 0xFF);
    r[5] = (uint8_t)((uint16_t)code >> 8);
    for (int i = 0; i < 4; i++) r[6 + i] = (uint8_t)(enc >> (8 * i));
    r[10] = (uint8_t)flags;
    r[11] = (uint8_t)(flags >> 8);
    fwrite(r, 1, sizeof r, g_log);
}

static int open_pty(char *name, size_t cap, int *slave_keep) {
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) != 0 || unlockpt(m) != 0) {
        return -1;
    }
    if (ptsname_r(m, name, cap) != 0) {
        return -1;
    }
    /* raw mode on the slave: no echo, no line editing, no CR/NL translation */
    int s = open(name, O_RDWR | O_NOCTTY);
    if (s < 0) {
        return -1;
    }
    struct termios tio;
    tcgetattr(s, &tio);
    cfmakeraw(&tio);
    tcsetattr(s, TCSANOW, &tio);
    *slave_keep = s; /* kept open so the master never sees a hang-up between host sessions */
    fcntl(m, F_SETFL, fcntl(m, F_GETFL) | O_NONBLOCK);
    return m;
}

int main(int argc, char **argv) {
    double ppm = 0, ppm2 = 0, ppm_after = -1, duration = -1, glitch_at = -1;
    const char *log_path = NULL;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "--ppm") && v) {
            ppm = atof(v), i++;
        } else if (!strcmp(a, "--ppm-after") && v) {
            if (sscanf(v, "%lf:%lf", &ppm_after, &ppm2) != 2) {
                fprintf(stderr, "hostd-fw-host: --ppm-after wants SECONDS:PPM\n");
                return 2;
            }
            i++;
        } else if (!strcmp(a, "--motion") && v) {
            if (!strcmp(v, "none")) g_motion = M_NONE;
            else if (!strcmp(v, "metronome")) g_motion = M_METRO;
            else if (!strncmp(v, "constant:", 9)) g_motion = M_CONST, g_speed = atof(v + 9);
            else if (!strncmp(v, "steps:", 6) && sscanf(v + 6, "%lf:%lf", &g_step_period, &g_step_mm) == 2)
                g_motion = M_STEPS;
            else {
                fprintf(stderr, "hostd-fw-host: --motion none|constant:MM_S|metronome|steps:PERIOD_S:MM\n");
                return 2;
            }
            i++;
        } else if (!strcmp(a, "--scenario") && v) {
            if (!(g_scen = fopen(v, "w"))) {
                fprintf(stderr, "hostd-fw-host: cannot write %s: %s\n", v, strerror(errno));
                return 1;
            }
            i++;
        } else if (!strcmp(a, "--log") && v) {
            log_path = v, i++;
        } else if (!strcmp(a, "--duration") && v) {
            duration = atof(v), i++;
        } else if (!strcmp(a, "--glitch-at") && v) {
            glitch_at = atof(v), i++;
        } else if (!strcmp(a, "--clock") && v) {
            if (!(g_clock = fopen(v, "wb"))) {
                fprintf(stderr, "hostd-fw-host: cannot write %s: %s\n", v, strerror(errno));
                return 1;
            }
            i++;
        } else if (!strcmp(a, "--jump-at") && v) {
            if (sscanf(v, "%lf:%lf", &g_jump_at, &g_jump_mm) != 2 || g_jump_at < 0 || fabs(g_jump_mm) > 1000) {
                fprintf(stderr, "hostd-fw-host: --jump-at wants SECONDS:MM (|MM| <= 1000)\n");
                return 2;
            }
            i++;
        } else {
            fprintf(stderr, "hostd-fw-host: unknown argument %s (see the header of port/host/main.c)\n", a);
            return 2;
        }
    }
    if (fabs(ppm) > 10000 || fabs(ppm2) > 10000) {
        fprintf(stderr, "hostd-fw-host: --ppm must be within +-10000\n");
        return 2;
    }
    if (log_path && !(g_log = fopen(log_path, "wb"))) {
        fprintf(stderr, "hostd-fw-host: cannot write %s: %s\n", log_path, strerror(errno));
        return 1;
    }
    char name[128];
    int slave = -1;
    g_master = open_pty(name, sizeof name, &slave);
    if (g_master < 0) {
        fprintf(stderr, "hostd-fw-host: cannot open a pseudo-terminal: %s\n", strerror(errno));
        return 1;
    }
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    signal(SIGPIPE, SIG_IGN);
    static fw_t f;
    fw_init(&f, 0);
    struct timespec t0, next;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    /* T0: CLOCK_MONOTONIC of tick 0, so tests can map host events to ticks (tick k is due at
     * T0 + k / 3000 s at 0 ppm) */
    printf("PTY %s T0 %.6f\n", name, (double)t0.tv_sec + (double)t0.tv_nsec * 1e-9);
    fflush(stdout);
    next = t0;
    g_device_period_ns = 1e9 / HP_SAMPLE_RATE_HZ / (1.0 + ppm * 1e-6);
    double next_ns = 0; /* since t0 */
    bool glitched = false;
    uint8_t rx[4096];
    while (!g_stop) {
        double t = now_s(&t0);
        if (duration > 0 && t >= duration) break;
        if (ppm_after >= 0 && t >= ppm_after) {
            g_device_period_ns = 1e9 / HP_SAMPLE_RATE_HZ / (1.0 + ppm2 * 1e-6);
            ppm_after = -1;
        }
        next_ns += g_device_period_ns;
        next.tv_sec = t0.tv_sec + (time_t)((t0.tv_nsec + (long long)next_ns) / 1000000000LL);
        next.tv_nsec = (long)((t0.tv_nsec + (long long)next_ns) % 1000000000LL);
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR && !g_stop) {
        }
        bool late = now_s(&t0) - next_ns * 1e-9 > 1e-3;
        for (;;) { /* everything the host has sent so far */
            ssize_t n = read(g_master, rx, sizeof rx);
            if (n <= 0) break;
            fw_deframer_feed(&f, rx, (size_t)n);
            if (g_scen) {
                fputs("r ", g_scen);
                for (ssize_t b = 0; b < n; b++) fprintf(g_scen, "%02x", rx[b]);
                fputc('\n', g_scen);
            }
        }
        /* the hand's time is the tick's due time: when the OS holds the host port up, the
         * simulated hand waits with the device (a real device is never late; a late host port
         * must not turn its own lateness into encoder jitter) */
        double tt = next_ns * 1e-9;
        if (g_clock) {
            struct timespec tn;
            clock_gettime(CLOCK_MONOTONIC, &tn);
            uint32_t k = (uint32_t)(g_ticks + 1);
            double hs = (double)tn.tv_sec + (double)tn.tv_nsec * 1e-9;
            fwrite(&k, sizeof k, 1, g_clock);
            fwrite(&hs, sizeof hs, 1, g_clock);
        }
        step_encoder(&f, tt, hand_mm(tt));
        if (glitch_at >= 0 && !glitched && tt >= glitch_at) { /* one illegal transition */
            fw_encoder_pins(&f, (uint8_t)(GRAY[(uint64_t)g_enc_pos & 3u] ^ 3u));
            fw_encoder_pins(&f, GRAY[(uint64_t)g_enc_pos & 3u]);
            glitched = true;
        }
        fw_tick(&f);
        g_ticks++;
        if (g_scen) fputs("t 1\n", g_scen);
        log_tick((uint32_t)g_ticks, g_last_dac, f.quad.count,
                 (uint16_t)((f.played ? 1u : 0u) | (f.in_underrun ? 2u : 0u) | (late ? 4u : 0u) |
                            (f.state == HP_STATE_RUNNING ? 8u : 0u) |
                            (f.state == HP_STATE_RENDERING ? 16u : 0u) |
                            (f.state == HP_STATE_RENDERING && f.render.env >= 1.0f ? 32u : 0u)));
    }
    if (g_log) fclose(g_log);
    if (g_clock) fclose(g_clock);
    if (g_scen) fclose(g_scen);
    fprintf(stderr, "hostd-fw-host: %llu ticks, %u underruns, %u malformed, %lu sends dropped\n",
            (unsigned long long)g_ticks, f.underruns, f.malformed, g_send_dropped);
    close(slave);
    close(g_master);
    return 0;
}
