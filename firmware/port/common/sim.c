/* The firmware's Linux ports' shared part: tick, simulated hand, DAC log (see sim.h). */
#define _GNU_SOURCE
#include "sim.h"

#include <errno.h>
#include <math.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "hal.h"

static uint64_t g_ticks;           /* device ticks since start */
static double g_device_period_ns;  /* nominal 333,333.3 ns, scaled by the clock error */
static FILE *g_log;
static FILE *g_clock;
static FILE *g_scen; /* --scenario: the core's inputs, replayable by fw-replay and the model */
static int16_t g_last_dac;
static volatile sig_atomic_t g_stop;
static double g_ppm, g_ppm2, g_ppm_after = -1, g_duration = -1, g_glitch_at = -1;

/* The device's clock: its own tick count at the nominal rate (it is the clock master). */
uint32_t hal_time_us(void) { return (uint32_t)((g_ticks * 1000000ull) / HP_SAMPLE_RATE_HZ); }

void hal_dac_write(int16_t code) { g_last_dac = code; }

static void on_signal(int sig) {
    (void)sig;
    g_stop = 1;
}

bool sim_stopping(void) { return g_stop != 0; }

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
 * artefact of the Linux ports that a real device does not have; bit 3: the device was RUNNING;
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

static FILE *open_out(const sim_port_t *port, const char *path) {
    FILE *fp = fopen(path, "wb");
    if (!fp) fprintf(stderr, "%s: cannot write %s: %s\n", port->prog, path, strerror(errno));
    return fp;
}

int sim_parse(const sim_port_t *port, int argc, char **argv) {
    const char *log_path = NULL;
    const char *P = port->prog;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "--ppm") && v) {
            g_ppm = atof(v), i++;
        } else if (!strcmp(a, "--ppm-after") && v) {
            if (sscanf(v, "%lf:%lf", &g_ppm_after, &g_ppm2) != 2) {
                fprintf(stderr, "%s: --ppm-after wants SECONDS:PPM\n", P);
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
                fprintf(stderr, "%s: --motion none|constant:MM_S|metronome|steps:PERIOD_S:MM\n", P);
                return 2;
            }
            i++;
        } else if (!strcmp(a, "--scenario") && v) {
            if (!(g_scen = open_out(port, v))) return 1;
            i++;
        } else if (!strcmp(a, "--log") && v) {
            log_path = v, i++;
        } else if (!strcmp(a, "--duration") && v) {
            g_duration = atof(v), i++;
        } else if (!strcmp(a, "--glitch-at") && v) {
            g_glitch_at = atof(v), i++;
        } else if (!strcmp(a, "--clock") && v) {
            if (!(g_clock = open_out(port, v))) return 1;
            i++;
        } else if (!strcmp(a, "--jump-at") && v) {
            if (sscanf(v, "%lf:%lf", &g_jump_at, &g_jump_mm) != 2 || g_jump_at < 0 || fabs(g_jump_mm) > 1000) {
                fprintf(stderr, "%s: --jump-at wants SECONDS:MM (|MM| <= 1000)\n", P);
                return 2;
            }
            i++;
        } else {
            int r = port->option ? port->option(a, v) : 0;
            if (r < 0) return 2;
            if (r == 0) {
                fprintf(stderr, "%s: unknown argument %s (see the header of its main.c)\n", P, a);
                return 2;
            }
            i += r - 1;
        }
    }
    if (fabs(g_ppm) > 10000 || fabs(g_ppm2) > 10000) {
        fprintf(stderr, "%s: --ppm must be within +-10000\n", P);
        return 2;
    }
    if (log_path && !(g_log = open_out(port, log_path))) return 1;
    return 0;
}

struct timespec sim_start(void) {
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    signal(SIGPIPE, SIG_IGN);
    /* The simulated device keeps real time where the OS lets it: SCHED_FIFO when permitted (root,
     * or RLIMIT_RTPRIO), as a device's timer interrupt is never held up by the host's other work.
     * A loaded machine otherwise holds the port up for milliseconds, and it then runs the missed
     * ticks at once and empties its own buffer (DAC log flag 4): the rig's underruns, not the
     * link's. It sleeps between ticks (a few % of a core); SCHED_RESET_ON_FORK keeps its children
     * ordinary. Not permitted: it runs as before, and its late ticks are flagged. */
    struct sched_param sp = {.sched_priority = 10};
    (void)sched_setscheduler(0, SCHED_FIFO | SCHED_RESET_ON_FORK, &sp);
    struct timespec t0;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    return t0;
}

void sim_scenario_rx(const uint8_t *bytes, size_t n) {
    if (!g_scen) return;
    fputs("r ", g_scen);
    for (size_t b = 0; b < n; b++) fprintf(g_scen, "%02x", bytes[b]);
    fputc('\n', g_scen);
}

void sim_run(fw_t *f, const sim_port_t *port, struct timespec t0) {
    struct timespec next = t0;
    g_device_period_ns = 1e9 / HP_SAMPLE_RATE_HZ / (1.0 + g_ppm * 1e-6);
    double next_ns = 0; /* since t0 */
    bool glitched = false;
    long ramp_ticks = -1; /* after a signal with ramp_on_stop: ticks left for the STOP ramp */
    for (;;) {
        if (g_stop) {
            if (!port->ramp_on_stop) break;
            if (ramp_ticks < 0) { /* the core's own STOP: ramp to zero (50 ms), clear, idle */
                const uint8_t stop[1] = {HP_ID_STOP};
                fw_on_message(f, stop, sizeof stop);
                ramp_ticks = HP_SAMPLE_RATE_HZ / 5; /* 200 ms at most */
            }
            if (ramp_ticks-- == 0 || (f->state == HP_STATE_IDLE && f->out == 0)) break;
        }
        double t = now_s(&t0);
        if (g_duration > 0 && t >= g_duration) break;
        if (g_ppm_after >= 0 && t >= g_ppm_after) {
            g_device_period_ns = 1e9 / HP_SAMPLE_RATE_HZ / (1.0 + g_ppm2 * 1e-6);
            g_ppm_after = -1;
        }
        next_ns += g_device_period_ns;
        next.tv_sec = t0.tv_sec + (time_t)((t0.tv_nsec + (long long)next_ns) / 1000000000LL);
        next.tv_nsec = (long)((t0.tv_nsec + (long long)next_ns) % 1000000000LL);
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR && !g_stop) {
        }
        bool late = now_s(&t0) - next_ns * 1e-9 > 1e-3;
        port->poll(f, now_s(&t0)); /* everything the host has sent so far */
        /* the hand's time is the tick's due time: when the OS holds the port up, the simulated
         * hand waits with the device (a real device is never late; a late port must not turn
         * its own lateness into encoder jitter) */
        double tt = next_ns * 1e-9;
        if (g_clock) {
            struct timespec tn;
            clock_gettime(CLOCK_MONOTONIC, &tn);
            uint32_t k = (uint32_t)(g_ticks + 1);
            double hs = (double)tn.tv_sec + (double)tn.tv_nsec * 1e-9;
            fwrite(&k, sizeof k, 1, g_clock);
            fwrite(&hs, sizeof hs, 1, g_clock);
            if (k % 30 == 0) fflush(g_clock); /* every 10 ms: tests wait on the device's clock */
        }
        step_encoder(f, tt, hand_mm(tt));
        if (g_glitch_at >= 0 && !glitched && tt >= g_glitch_at) { /* one illegal transition */
            fw_encoder_pins(f, (uint8_t)(GRAY[(uint64_t)g_enc_pos & 3u] ^ 3u));
            fw_encoder_pins(f, GRAY[(uint64_t)g_enc_pos & 3u]);
            glitched = true;
        }
        fw_tick(f);
        g_ticks++;
        if (g_scen) fputs("t 1\n", g_scen);
        log_tick((uint32_t)g_ticks, g_last_dac, f->quad.count,
                 (uint16_t)((f->played ? 1u : 0u) | (f->in_underrun ? 2u : 0u) | (late ? 4u : 0u) |
                            (f->state == HP_STATE_RUNNING ? 8u : 0u) |
                            (f->state == HP_STATE_RENDERING ? 16u : 0u) |
                            (f->state == HP_STATE_RENDERING && f->render.env >= 1.0f ? 32u : 0u)));
    }
}

void sim_finish(const fw_t *f, const sim_port_t *port, unsigned long sends_dropped) {
    if (g_log) fclose(g_log);
    if (g_clock) fclose(g_clock);
    if (g_scen) fclose(g_scen);
    g_log = g_clock = g_scen = NULL;
    fprintf(stderr, "%s: %llu ticks, %u underruns, %u malformed, %lu sends dropped\n", port->prog,
            (unsigned long long)g_ticks, f->underruns, f->malformed, sends_dropped);
}
