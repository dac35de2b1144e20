/* Instructions per 3 kHz tick of the portable core on the emulated Cortex-M4F (mps2-an386).
 *
 * QEMU runs with -icount shift=0: its virtual clock advances 1 ns per instruction executed,
 * and SysTick counts that clock (25 MHz on this machine), so SysTick counts INSTRUCTIONS, not
 * cycles (QEMU models no pipeline, wait states or memory timing). The ratio is calibrated
 * here with a loop of known length. A 170 MHz STM32G4 has 56,667 cycles per 333 us tick; the
 * share printed assumes one cycle per instruction, a lower bound (loads, branches and flash
 * wait states cost more cycles). Built with the board's flags (-Os, FPU, -mfloat-abi=hard). */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "fw.h"
#include "render_msgs.h"
#include "hal.h"

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define CYCLES_PER_TICK_170MHZ (170000000.0 / HP_SAMPLE_RATE_HZ)

static volatile uint32_t g_us;
static volatile int16_t g_dac;
static volatile uint8_t g_report[HP_REPORT_SIZE];
static unsigned g_sent;

uint32_t hal_time_us(void) { return g_us; }
void hal_dac_write(int16_t code) { g_dac = code; }
/* like the board's: the message zero-padded into a 64-byte report buffer */
void hal_send(const uint8_t *msg, size_t len) {
    for (size_t i = 0; i < HP_REPORT_SIZE; i++) g_report[i] = i < len ? msg[i] : 0;
    g_sent++;
}

static uint32_t systick_start(void) {
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0;
    SYST_CSR = 5u; /* enable, processor clock, no interrupt */
    return SYST_CVR;
}
static uint32_t elapsed(uint32_t t0, uint32_t t1) { return (t0 - t1) & 0xFFFFFFu; } /* counts down */

static __attribute__((noinline)) void spin(uint32_t n) {
    __asm volatile("1: subs %0, %0, #1\n bne 1b" : "+r"(n) : : "cc"); /* 2 instructions per turn */
}

static __attribute__((noinline)) void empty_tick(fw_t *f) { __asm volatile("" : : "r"(f) : "memory"); }

/* counts for k calls of fn, the clock advanced like the real 3 kHz tick */
static uint32_t block(void (*fn)(fw_t *), fw_t *f, int k) {
    uint32_t t0 = SYST_CVR;
    for (int i = 0; i < k; i++) {
        g_us += 333;
        fn(f);
    }
    return elapsed(t0, SYST_CVR);
}

/* One tick, timed alone: its SysTick counts; *pair keeps the smallest back-to-back read (the
 * timing's own cost, subtracted by the caller). 40-instruction resolution. */
static uint32_t time_tick(fw_t *f, uint32_t *pair) {
    uint32_t a = SYST_CVR;
    fw_tick(f);
    uint32_t b = SYST_CVR;
    uint32_t c = SYST_CVR;
    uint32_t e = elapsed(b, c);
    *pair = e < *pair ? e : *pair;
    return elapsed(a, b);
}

static void samples_msg(uint8_t *m, uint16_t seq, int base) {
    memset(m, 0, HP_REPORT_SIZE);
    m[0] = HP_ID_SAMPLES;
    m[HP_SAMPLES_OFF_SEQ] = (uint8_t)seq;
    m[HP_SAMPLES_OFF_SEQ + 1] = (uint8_t)(seq >> 8);
    m[HP_SAMPLES_OFF_COUNT] = HP_MAX_SAMPLES;
    for (int i = 0; i < HP_MAX_SAMPLES; i++) {
        int16_t c = (int16_t)(((base + i) * 397) % 12000 - 6000); /* within the limits: no clipping */
        m[HP_SAMPLES_SIZE + 2 * i] = (uint8_t)((uint16_t)c & 0xFF);
        m[HP_SAMPLES_SIZE + 2 * i + 1] = (uint8_t)((uint16_t)c >> 8);
    }
}

static void pct(const char *what, double insns) {
    printf("%-44s %8.1f instructions  = %5.2f %% of a 170 MHz core's 3 kHz period (at 1 instr/cycle)\n",
           what, insns, 100.0 * insns / CYCLES_PER_TICK_170MHZ);
}

/* The device renderer's tick, worst case: N' = 512 components, 4 equalizer sections, the hand
 * at 45.6 mm/s (every component below the band's end at 1200 Hz, the upper two thirds of them in
 * the fade, which costs a second phasor each: the most work per tick), then a texture swap (two series per tick
 * during the 50 ms crossfade). Encoder edges (their own interrupt on a board) are fed between
 * the timed ticks. */
static float g_tex[HP_RENDER_MAX_COMPONENTS];
static int bench_render(double ipc) {
    static fw_t f;
    fw_init(&f, 0);
    for (int k = 0; k < HP_RENDER_MAX_COMPONENTS; k++) g_tex[k] = 2.0f / (float)(k + 1);
    rm_set_scale(&f, 400.0f);
    rm_set_band(&f, 1200.0f, 0.333f);
    rm_set_delay(&f, 700);
    for (uint8_t i = 0; i < HP_RENDER_MAX_SECTIONS; i++) {
        rm_set_eq(&f, i, HP_RENDER_MAX_SECTIONS, 0.9f, -0.5f, 0.1f, -0.4f, 0.05f);
    }
    rm_upload(&f, 1, g_tex, HP_RENDER_MAX_COMPONENTS, 20000, 10000000u, CORRUPT_NONE);
    rm_start_render(&f, 1000);
    if (f.state != HP_STATE_RENDERING) {
        printf("FAIL: the renderer did not start (state %u)\n", (unsigned)f.state);
        return 1;
    }
    uint32_t count = 0, t_edge = 0, worst = 0, pair = 0xFFFFFFFFu;
    double sum = 0, sum_x = 0;
    int n = 0, n_x = 0;
    for (int tick = 0; tick < 900; tick++) {
        if (tick == 450) { /* the swap: slot 2, crossfade over the next 150 ticks */
            rm_upload(&f, 2, g_tex, HP_RENDER_MAX_COMPONENTS, 20000, 10000000u, CORRUPT_NONE);
        }
        for (int e = 0; e < 38; e++) { /* 45.6 mm/s = 114 counts per ms */
            count++;
            t_edge += HP_RENDER_EDGE_CLOCK_HZ / HP_SAMPLE_RATE_HZ / 38;
            fw_encoder_edge(&f, (uint8_t)((const uint8_t[]){0, 1, 3, 2})[count & 3u], t_edge);
        }
        g_us += 333;
        uint32_t d = time_tick(&f, &pair);
        if (tick >= 150 && tick < 450) sum += d, n++;
        if (tick >= 452 && tick < 598) sum_x += d, n_x++;
        if (tick >= 150) worst = d > worst ? d : worst;
    }
    if (f.state != HP_STATE_RENDERING) {
        printf("FAIL: the renderer stopped (state %u)\n", (unsigned)f.state);
        return 1;
    }
    pct("device renderer tick, N'=512, 4 sections (mean):", (sum / n - pair) * ipc);
    pct("device renderer tick during a swap (mean):", (sum_x / n_x - pair) * ipc);
    pct("device renderer, slowest tick (+-40):", (double)(worst - pair) * ipc);
    return 0;
}

int qemu_main(void) {
    static fw_t f;
    (void)systick_start();
    /* calibration: instructions per SysTick count, from two loop lengths (overhead cancels) */
    uint32_t t0 = SYST_CVR;
    spin(20000);
    uint32_t c1 = elapsed(t0, SYST_CVR);
    t0 = SYST_CVR;
    spin(220000);
    uint32_t c2 = elapsed(t0, SYST_CVR);
    double ipc = 2.0 * 200000.0 / (double)(c2 - c1);
    printf("calibration: %.3f instructions per SysTick count (-icount shift=0, 25 MHz SysTick: 40 expected)\n", ipc);
    if (ipc < 1.0 || ipc > 1000.0) {
        printf("FAIL: SysTick does not follow the instruction count (is -icount shift=0 set?)\n");
        return 1;
    }

    fw_init(&f, 0);
    uint8_t start = HP_ID_START, m[HP_REPORT_SIZE];
    fw_on_message(&f, &start, 1);
    /* the blocks run 2 x 77 ms without messages in between: a host timeout longer than that */
    uint8_t tmo[HP_SET_TIMEOUT_SIZE] = {HP_ID_SET_TIMEOUT, 1000 & 0xFF, 1000 >> 8};
    fw_on_message(&f, tmo, sizeof tmo);
    const int k = 8 * HP_MAX_SAMPLES; /* 232 ticks per block, the ring holds 8 messages */
    double playout = 0, idle = 0, msg = 0;
    uint32_t seq = 0, nblocks = 13; /* 13 x 232 = 3016 ticks: about one second */
    for (uint32_t b = 0; b < nblocks; b++) {
        uint32_t tm = SYST_CVR;
        for (int j = 0; j < 8; j++) {
            samples_msg(m, (uint16_t)seq, (int)seq * HP_MAX_SAMPLES);
            seq++;
            fw_on_message(&f, m, HP_REPORT_SIZE);
        }
        uint32_t cm = elapsed(tm, SYST_CVR);
        uint32_t played0 = f.samples_played;
        uint32_t ct = block(fw_tick, &f, k);
        uint32_t ce = block(empty_tick, &f, k);
        if (f.samples_played - played0 != (uint32_t)k || f.underruns != 0 || f.state != HP_STATE_RUNNING) {
            printf("FAIL: the playout path did not play every tick from the buffer\n");
            return 1;
        }
        playout += ((double)ct - (double)ce) * ipc / k;
        msg += (double)cm * ipc / 8.0; /* includes building the message: an upper bound */
    }
    playout /= nblocks;
    /* the slowest single tick (the STATUS one), each timed alone: 40-instruction resolution */
    uint32_t worst = 0, pair = 0xFFFFFFFFu;
    for (int j = 0; j < 8; j++) {
        samples_msg(m, (uint16_t)seq, (int)seq * HP_MAX_SAMPLES);
        seq++;
        fw_on_message(&f, m, HP_REPORT_SIZE);
    }
    for (int i = 0; i < 200; i++) {
        g_us += 333;
        uint32_t d = time_tick(&f, &pair);
        worst = d > worst ? d : worst;
    }
    msg /= nblocks;
    /* idle (nothing to play, output at rest) for comparison */
    uint8_t stop = HP_ID_STOP;
    fw_on_message(&f, &stop, 1);
    for (int i = 0; i < 400; i++) fw_tick(&f);
    idle = ((double)block(fw_tick, &f, 300) - (double)block(empty_tick, &f, 300)) * ipc / 300;
    printf("core built with -Os for Cortex-M4F; %u ticks played, %u STATUS reports built\n",
           (unsigned)f.samples_played, g_sent);
    pct("playout tick (mean, STATUS every 3rd tick):", playout);
    pct("slowest playout tick (+-40):", (double)(worst - pair) * ipc);
    pct("idle tick (mean):", idle);
    pct("SAMPLES message of 29 (USB interrupt side):", msg);
    return bench_render(ipc);
}
