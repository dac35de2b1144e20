/* fw-replay: runs the firmware core on a scenario and prints every DAC code (and, with
 * --time, the wall time of each fw_tick in ns). Shared by the Python model's comparison test
 * (tests/test_device_render.py) and `hostd bench accuracy` (render_at = device).
 *
 * Scenario lines (stdin):
 *   m HEX        a message from the host (fw_on_message)
 *   r HEX        raw serial bytes from the host (fw_deframer_feed; the host port's --scenario)
 *   e AB T       an encoder pin state AB (0..3) at edge-clock time T (fw_encoder_edge)
 *   t N          N ticks; tick k (counting from 1) is at (k - 1) / 3000 s on the device clock,
 *                and messages after it arrive at k / 3000 s
 * Output: one line per tick, "CODE NS" (NS: wall time of that fw_tick, CLOCK_MONOTONIC). */
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "fw.h"
#include "hal.h"

static uint32_t g_us;
static int16_t g_dac;
uint32_t hal_time_us(void) { return g_us; }
void hal_dac_write(int16_t code) { g_dac = code; }
void hal_send(const uint8_t *msg, size_t len) { (void)msg, (void)len; }

static long long now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (long long)t.tv_sec * 1000000000LL + t.tv_nsec;
}

int main(int argc, char **argv) {
    int timed = argc > 1 && !strcmp(argv[1], "--time");
    if (argc > 1 && !timed) {
        fprintf(stderr, "usage: fw-replay [--time] < SCENARIO\n");
        return 2;
    }
    static fw_t f;
    static char line[16384];
    fw_init(&f, 0);
    while (fgets(line, sizeof line, stdin)) {
        if (line[0] == 'm') {
            uint8_t m[HP_REPORT_SIZE];
            size_t n = 0;
            const char *h = line + 2;
            unsigned v;
            while (n < sizeof m && sscanf(h, "%2x", &v) == 1) {
                m[n++] = (uint8_t)v;
                h += 2;
            }
            fw_on_message(&f, m, n);
        } else if (line[0] == 'r') {
            static uint8_t raw[sizeof line / 2];
            size_t n = 0;
            const char *h = line + 2;
            unsigned v;
            while (n < sizeof raw && sscanf(h, "%2x", &v) == 1) {
                raw[n++] = (uint8_t)v;
                h += 2;
            }
            fw_deframer_feed(&f, raw, n);
        } else if (line[0] == 'e') {
            unsigned ab;
            unsigned long t;
            if (sscanf(line + 2, "%u %lu", &ab, &t) != 2) return 2;
            fw_encoder_edge(&f, (uint8_t)ab, (uint32_t)t);
        } else if (line[0] == 't') {
            long n = atol(line + 2);
            for (long i = 0; i < n; i++) {
                g_us = (uint32_t)((uint64_t)f.ticks * 1000000u / HP_SAMPLE_RATE_HZ);
                long long t0 = timed ? now_ns() : 0;
                fw_tick(&f);
                long long dt = timed ? now_ns() - t0 : 0;
                printf("%d %lld\n", g_dac, dt);
                /* messages until the next tick arrive at its instant (the simulated display's clock) */
                g_us = (uint32_t)((uint64_t)f.ticks * 1000000u / HP_SAMPLE_RATE_HZ);
            }
        }
    }
    return 0;
}
