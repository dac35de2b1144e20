/* The arithmetic of the board's 3 kHz tick, as pure functions (tests/test_board_tick.c). */
#ifndef HOSTD_STM32G4_TICK_H
#define HOSTD_STM32G4_TICK_H

#include <stdint.h>

/* 170 MHz / 3 kHz = 56666 + 2/3 cycles: the periods cycle through 56666, 56667, 56667. */
#define TICK_PERIOD_SHORT 56666u

typedef struct {
    uint8_t phase;    /* ticks modulo 3 */
    uint32_t time_us; /* ticks x 1000 / 3, rounded down: the host port's device clock */
    uint16_t enc_last;
    uint32_t enc_count; /* the 16-bit encoder count extended to 32 bits */
} tick_state_t;

/* One tick: advance the clock and return the auto-reload value to preload (it takes effect
 * for the period after the current one; any fixed order of the three averages 3 kHz). */
static inline uint32_t tick_advance(tick_state_t *t) {
    t->phase = (uint8_t)(t->phase == 2 ? 0 : t->phase + 1);
    t->time_us += t->phase == 0 ? 334u : 333u; /* 333, 666, 1000, 1333, ... */
    return (t->phase == 0 ? TICK_PERIOD_SHORT : TICK_PERIOD_SHORT + 1u) - 1u;
}

/* Extend the timer's 16-bit encoder count: valid while it moves < 32768 counts per tick. */
static inline uint32_t tick_encoder(tick_state_t *t, uint16_t cnt16) {
    t->enc_count += (uint32_t)(int32_t)(int16_t)(uint16_t)(cnt16 - t->enc_last);
    t->enc_last = cnt16;
    return t->enc_count;
}

#endif
