/* The value to write to a USB endpoint register (EPnR, RM0440 45.6.2) so that only the
 * intended bits change. EPnR mixes three kinds of bits:
 *   toggle (STAT_RX, DTOG_RX, STAT_TX, DTOG_TX): writing 1 flips the bit, 0 leaves it;
 *   CTR_RX, CTR_TX: writing 0 clears, 1 leaves (the hardware sets them);
 *   the rest (EP_TYPE, EP_KIND, EA) plain read/write; SETUP read-only.
 * Pure functions, so the host tests check them against a model of the register. */
#ifndef HOSTD_USB_EPR_H
#define HOSTD_USB_EPR_H

#include <stdint.h>

#include "regs.h"

#define USB_EP_TOGGLES (USB_EP_STAT_RX | USB_EP_DTOG_RX | USB_EP_STAT_TX | USB_EP_DTOG_TX)

/* Set the toggle bits selected by `which` to their value in `want`, keep every other bit,
 * clear the CTR flags in `clear_ctr` (and no other: a flag the hardware sets between the
 * read and the write survives, since its bit is written as 1). */
static inline uint16_t usb_epr_value(uint16_t cur, uint16_t which, uint16_t want, uint16_t clear_ctr) {
    uint16_t v = (uint16_t)((cur & USB_EP_KEEP) | USB_EP_CTR_RX | USB_EP_CTR_TX);
    v = (uint16_t)(v & ~clear_ctr);
    return (uint16_t)(v | ((cur ^ want) & which & USB_EP_TOGGLES));
}

/* (Re)open an endpoint: type and address, both data toggles 0, the given STAT_RX / STAT_TX
 * (USB_EP_STAT_* values); CTR flags left alone. */
static inline uint16_t usb_epr_open(uint16_t cur, uint16_t type, uint16_t addr, uint16_t stat_rx, uint16_t stat_tx) {
    uint16_t want = (uint16_t)((stat_rx << 12) | (stat_tx << 4));
    return (uint16_t)(type | (addr & USB_EP_EA) | USB_EP_CTR_RX | USB_EP_CTR_TX | ((cur ^ want) & USB_EP_TOGGLES));
}

#endif
