/* The board tick's arithmetic (tick.h): the device clock, the timer periods, the encoder. */
#include <stdio.h>

#include "check.h"
#include "hostd_proto.h"
#include "tick.h"

int g_checks, g_failures;

int main(void) {
    tick_state_t t = {0};
    uint64_t cycles = 0;
    long clock_bad = 0;
    for (uint64_t n = 1; n <= 3000000; n++) { /* 1000 s of ticks */
        cycles += tick_advance(&t) + 1u;
        if (t.time_us != (uint32_t)(n * 1000000u / HP_SAMPLE_RATE_HZ)) clock_bad++; /* the host port's clock */
    }
    CHECK_EQ(clock_bad, 0);
    CHECK_EQ(cycles, 170000000ull * 1000u); /* exactly 3 kHz from 170 MHz */
    /* the encoder: wraps of the 16-bit timer both ways, and the 32-bit count's own wrap */
    tick_state_t e = {0};
    e.enc_last = 65000;
    uint16_t hw = 65000;
    int64_t truth = 0;
    long enc_bad = 0;
    uint32_t x = 1;
    for (int i = 0; i < 400000; i++) {
        x = x * 1103515245u + 12345u;
        int32_t step = (int32_t)((x >> 8) % 65535u) - 32767; /* -32767 .. +32767 counts per tick */
        if (i > 100000) step = (int32_t)((x >> 8) % 32001u); /* drift forward */
        hw = (uint16_t)(hw + step);
        truth += step;
        if (tick_encoder(&e, hw) != (uint32_t)truth) enc_bad++;
    }
    CHECK_EQ(enc_bad, 0);
    CHECK(truth > 4294967296LL || truth < 0); /* the 32-bit count wrapped or went negative */
    printf("board tick: %d checks, %d failures\n", g_checks, g_failures);
    return g_failures ? 1 : 0;
}
