/* The STM32G4 board port: what its parts share. */
#ifndef HOSTD_STM32G4_BOARD_H
#define HOSTD_STM32G4_BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "fw.h"

#define BOARD_SYSCLK_HZ 170000000u

/* The encoder as the tick sees it: the count (TIM3 in encoder mode, extended from 16 to 32
 * bits every tick) and the time of the last edge on A and on B (TIM2 input capture, in
 * 170 MHz cycles of the free-running 32-bit TIM2), with TIM2's count at the tick. */
typedef struct {
    uint32_t count;
    uint32_t edge_a_cycles, edge_b_cycles;
    uint32_t tick_cycles;
    uint32_t transition_errors;
} board_encoder_t;

/* THE DEVICE RENDERER HOOK (issue 12): called at every 3 kHz tick, right before fw_tick(),
 * with the encoder state. Weak and empty here; the renderer defines it and feeds the core
 * the code to play (through the core's own device-mode interface, then the safety stage). */
void board_render_tick(fw_t *f, const board_encoder_t *enc);

/* usb_fs.c */
void usb_fs_init(fw_t *f, const uint32_t uid[3]);
void usb_fs_send(const uint8_t *msg, size_t len);

#endif
