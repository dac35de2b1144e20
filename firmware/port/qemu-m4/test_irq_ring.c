/* The core's producer/consumer hand-off under real interrupts on the emulated Cortex-M4F:
 * the main loop delivers SAMPLES messages (the USB interrupt's role: fw_on_message, the
 * ring's producer) while SysTick interrupts run fw_tick (the 3 kHz timer's role: the
 * consumer) every few hundred instructions, at points that drift through the producer's
 * code. Every sample must play exactly once and in order. */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "fw.h"
#include "hal.h"

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define TOTAL (HP_MAX_SAMPLES * 1200) /* 34,800 samples, the ring wraps 136 times */

static fw_t g_f;
static volatile uint32_t g_us, g_ticks, g_played;
static int16_t g_log[TOTAL];

uint32_t hal_time_us(void) { return g_us; }
void hal_dac_write(int16_t code) { (void)code; }
void hal_send(const uint8_t *msg, size_t len) { (void)msg, (void)len; }

static int16_t code_of(uint32_t i) { return (int16_t)((i * 7u) % 2000u) - 1000; }

void SysTick_Handler(void);
void SysTick_Handler(void) {
    g_us += 333;
    fw_tick(&g_f);
    g_ticks++;
    if (g_f.played && g_played < TOTAL) {
        g_log[g_played++] = g_f.out;
    }
}

int qemu_main(void) {
    fw_init(&g_f, 0);
    uint8_t tmo[HP_SET_TIMEOUT_SIZE] = {HP_ID_SET_TIMEOUT, 0xFF, 0xFF}; /* 65 s: ticks outrun messages here */
    fw_on_message(&g_f, tmo, sizeof tmo);
    uint8_t start = HP_ID_START;
    fw_on_message(&g_f, &start, 1);
    uint32_t sent = 0, seq = 0, preempted = 0;
    SYST_RVR = 5;
    SYST_CVR = 0;
    SYST_CSR = 7u; /* processor clock, interrupt, enable */
    while (sent < TOTAL) {
        if (fw_ring_fill(&g_f.ring) + HP_MAX_SAMPLES > HP_BUFFER_CAPACITY) {
            continue;
        }
        uint8_t m[HP_REPORT_SIZE] = {HP_ID_SAMPLES, 0, (uint8_t)seq, (uint8_t)(seq >> 8), HP_MAX_SAMPLES};
        for (uint32_t i = 0; i < HP_MAX_SAMPLES; i++) {
            uint16_t c = (uint16_t)code_of(sent + i);
            m[HP_SAMPLES_SIZE + 2 * i] = (uint8_t)c;
            m[HP_SAMPLES_SIZE + 2 * i + 1] = (uint8_t)(c >> 8);
        }
        uint32_t t0 = g_ticks;
        fw_on_message(&g_f, m, sizeof m);
        preempted += g_ticks != t0;
        sent += HP_MAX_SAMPLES;
        seq++;
        SYST_RVR = 3u + seq % 11u; /* every 120..520 instructions: the tick lands all over */
    }
    for (uint32_t spin = 0; g_played < TOTAL && spin < 50000000u; spin++) {
    }
    SYST_CSR = 0;
    long bad = 0;
    for (uint32_t i = 0; i < g_played; i++) {
        bad += g_log[i] != code_of(i);
    }
    printf("irq hand-off: %lu samples sent, %lu played in order with %ld mismatches; %lu ticks, %lu of %lu "
           "messages interrupted by a tick, %u underruns, %u malformed\n",
           (unsigned long)sent, (unsigned long)g_played, bad, (unsigned long)g_ticks, (unsigned long)preempted,
           (unsigned long)seq, g_f.underruns, g_f.malformed);
    int ok = g_played == TOTAL && bad == 0 && preempted > seq / 2 && g_f.malformed == 0;
    if (!ok) {
        printf("FAIL: the ring lost, repeated or reordered samples under interrupts\n");
    }
    return ok ? 0 : 1;
}
