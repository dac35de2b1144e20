/* The hardware seam: what a board port implements. The core never touches registers. */
#ifndef HOSTD_HAL_H
#define HOSTD_HAL_H

#include <stddef.h>
#include <stdint.h>

/* Write one signed DAC code (already limited by the core's safety stage). */
void hal_dac_write(int16_t code);

/* Free-running microsecond clock of the device (wraps at 2^32). */
uint32_t hal_time_us(void);

/* Send one protocol message to the host. The port frames it for its transport: a
 * zero-padded 64-byte report on USB, COBS + CRC-16 + 0x00 on a serial bridge
 * (fw_frame). Must not block the 3 kHz tick: drop when the transport is busy. */
void hal_send(const uint8_t *msg, size_t len);

/* Received bytes and encoder edges are pushed into the core by the port:
 *   fw_on_message()      one complete message (a USB report, or a deframed serial frame)
 *   fw_deframer_feed()   raw serial bytes
 *   fw_encoder_pins()    the encoder's A/B pin state on every pin change (or polled fast)
 *   fw_tick()            from a 3 kHz timer interrupt */

#endif
