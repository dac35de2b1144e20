/* The STM32G4 USB full-speed device peripheral (RM0440 chapter 45) behind usbd_hw_t, and
 * the interrupt endpoint 1 carrying protocol messages: OUT reports go to fw_on_message, the
 * core's hal_send goes out as IN reports.
 *
 * Packet memory (16-bit accesses, BTABLE at 0): EP0 TX 0x40, EP0 RX 0x80, EP1 TX 0xC0,
 * EP1 RX 0x100, 64 bytes each. EPnR bits are toggle (STAT, DTOG), clear-by-writing-0 (CTR)
 * or plain: every write goes through ep_write so that no bit changes by accident.
 *
 * Concurrency: this file runs in the USB interrupt, except usb_fs_send, which the tick (a
 * higher priority) calls for STATUS. Endpoint 1's register and IN buffer are touched by both,
 * so the USB-interrupt side does so with interrupts masked (a few dozen cycles). */
#include <stdbool.h>
#include <string.h>

#include "board.h"
#include "regs.h"
#include "usb_epr.h"
#include "usbd.h"

#define PMA_EP0_TX 0x40u
#define PMA_EP0_RX 0x80u
#define PMA_EP1_TX 0xC0u
#define PMA_EP1_RX 0x100u

static usbd_t g_usbd;
static fw_t *g_fw;
static volatile bool g_configured;
/* replies (IDENT, CAPS, render ACKs) waiting for the IN endpoint, oldest first: a v2 IDENTIFY
 * is answered with two messages at once, and an upload's ACKs may follow each other */
#define PENDING_MAX 4u
static uint8_t g_pending[PENDING_MAX][HP_REPORT_SIZE];
static uint8_t g_pending_len[PENDING_MAX];
static volatile uint8_t g_pending_head, g_pending_count;
static volatile uint32_t g_reply_dropped; /* replies dropped with the queue full */
static volatile uint32_t g_in_dropped; /* STATUS reports dropped while the host had not polled */

#ifdef USB_FS_SIM
#include "usb_fs_sim.h" /* tests/: a model of the peripheral in place of the registers */
#else
static uint32_t irq_save(void) {
    uint32_t p;
    __asm volatile("mrs %0, primask\n cpsid i" : "=r"(p)::"memory");
    return p;
}
static void irq_restore(uint32_t p) { __asm volatile("msr primask, %0" ::"r"(p) : "memory"); }
/* EPnR and ISTR writes have side effects (toggle, clear-on-0): they go through these */
static uint16_t epr_get(unsigned ep) { return USB_EPR(ep); }
static void epr_set(unsigned ep, uint16_t v) { USB_EPR(ep) = v; }
static void istr_write(uint16_t v) { USB_ISTR = v; }
#endif

static void pma_write(uint32_t off, const uint8_t *p, uint32_t n, uint32_t pad_to) {
    for (uint32_t i = 0; i < pad_to; i += 2) {
        uint32_t lo = i < n ? p[i] : 0u, hi = i + 1 < n ? p[i + 1] : 0u;
        USB_PMA16(off + i) = (uint16_t)(lo | (hi << 8));
    }
}
static void pma_read(uint32_t off, uint8_t *p, uint32_t n) {
    for (uint32_t i = 0; i < n; i += 2) {
        uint16_t w = USB_PMA16(off + i);
        p[i] = (uint8_t)w;
        if (i + 1 < n) {
            p[i + 1] = (uint8_t)(w >> 8);
        }
    }
}

static void ep_write(unsigned ep, uint16_t which, uint16_t want, uint16_t clear_ctr) {
    epr_set(ep, usb_epr_value(epr_get(ep), which, want, clear_ctr));
}
#define STAT_RX(s) ((uint16_t)((s) << 12))
#define STAT_TX(s) ((uint16_t)((s) << 4))

static void ep_open(unsigned ep, uint16_t type, uint16_t stat_rx, uint16_t stat_tx) {
    epr_set(ep, usb_epr_open(epr_get(ep), type, (uint16_t)ep, stat_rx, stat_tx));
}

/* ---- usbd_hw_t ---- */
static void hw_ep0_send(void *ctx, const uint8_t *p, uint16_t n) {
    (void)ctx;
    pma_write(PMA_EP0_TX, p, n, n);
    USB_COUNT_TX(0) = n;
    ep_write(0, USB_EP_STAT_TX, STAT_TX(USB_EP_STAT_VALID), 0);
}
static void hw_ep0_recv(void *ctx) {
    (void)ctx;
    ep_write(0, USB_EP_STAT_RX, STAT_RX(USB_EP_STAT_VALID), 0);
}
static void hw_ep0_stall(void *ctx) {
    (void)ctx;
    ep_write(0, USB_EP_STAT_RX | USB_EP_STAT_TX, STAT_RX(USB_EP_STAT_STALL) | STAT_TX(USB_EP_STAT_STALL), 0);
}
static void hw_set_address(void *ctx, uint8_t addr) {
    (void)ctx;
    USB_DADDR = (uint16_t)(USB_DADDR_EF | addr);
}
static void hw_configure(void *ctx, uint8_t config) {
    (void)ctx;
    uint32_t m = irq_save();
    USB_ADDR_TX(1) = PMA_EP1_TX;
    USB_COUNT_TX(1) = 0;
    USB_ADDR_RX(1) = PMA_EP1_RX;
    USB_COUNT_RX(1) = USB_COUNT_RX_BL32_2;
    if (config) {
        ep_open(1, USB_EP_TYPE_INTERRUPT, USB_EP_STAT_VALID, USB_EP_STAT_NAK);
    } else {
        ep_open(1, USB_EP_TYPE_INTERRUPT, USB_EP_STAT_DISABLED, USB_EP_STAT_DISABLED);
    }
    g_configured = config != 0;
    g_pending_head = g_pending_count = 0;
    irq_restore(m);
}
static void hw_ep_halt(void *ctx, uint8_t ep, bool halt) {
    (void)ctx;
    uint32_t m = irq_save();
    if (ep & 0x80) {
        ep_write(1, USB_EP_STAT_TX | USB_EP_DTOG_TX, STAT_TX(halt ? USB_EP_STAT_STALL : USB_EP_STAT_NAK), 0);
    } else {
        ep_write(1, USB_EP_STAT_RX | USB_EP_DTOG_RX, STAT_RX(halt ? USB_EP_STAT_STALL : USB_EP_STAT_VALID), 0);
    }
    irq_restore(m);
}
static uint16_t hw_get_report(void *ctx, uint8_t *buf) {
    (void)ctx;
    memset(buf, 0, HP_REPORT_SIZE);
    (void)fw_build_status(g_fw, buf); /* a snapshot of the device's state */
    return HP_REPORT_SIZE;
}
static void hw_set_report(void *ctx, const uint8_t *p, uint16_t n) {
    (void)ctx;
    fw_on_message(g_fw, p, n);
}

static const usbd_hw_t HW = {NULL, hw_ep0_send, hw_ep0_recv, hw_ep0_stall, hw_set_address, hw_configure,
                             hw_ep_halt, hw_get_report, hw_set_report};

/* ---- endpoint 1 IN: one report in flight; STATUS is dropped when the host has not taken the
 * last one yet (a newer one follows within 1 ms), any other reply waits in g_pending ---- */
static bool ep1_in_busy(void) { return ((epr_get(1) & USB_EP_STAT_TX) >> 4) == USB_EP_STAT_VALID; }
static void ep1_in_load(const uint8_t *msg, size_t len) {
    pma_write(PMA_EP1_TX, msg, (uint32_t)len, HP_REPORT_SIZE);
    USB_COUNT_TX(1) = HP_REPORT_SIZE;
    ep_write(1, USB_EP_STAT_TX, STAT_TX(USB_EP_STAT_VALID), 0);
}

void usb_fs_send(const uint8_t *msg, size_t len) {
    if (len == 0 || len > HP_REPORT_SIZE) {
        return;
    }
    uint32_t m = irq_save();
    if (!g_configured) {
        /* no host: nothing to do */
    } else if (!ep1_in_busy()) {
        ep1_in_load(msg, len);
    } else if (msg[0] != HP_ID_STATUS) {
        if (g_pending_count < PENDING_MAX) {
            uint8_t i = (uint8_t)((g_pending_head + g_pending_count) % PENDING_MAX);
            memcpy(g_pending[i], msg, len);
            g_pending_len[i] = (uint8_t)len;
            g_pending_count++;
        } else {
            g_reply_dropped++;
        }
    } else {
        g_in_dropped++;
    }
    irq_restore(m);
}

static void usb_reset(void) {
    USB_BTABLE = 0;
    USB_ADDR_TX(0) = PMA_EP0_TX;
    USB_COUNT_TX(0) = 0;
    USB_ADDR_RX(0) = PMA_EP0_RX;
    USB_COUNT_RX(0) = USB_COUNT_RX_BL32_2;
    ep_open(0, USB_EP_TYPE_CONTROL, USB_EP_STAT_VALID, USB_EP_STAT_NAK);
    USB_DADDR = USB_DADDR_EF; /* address 0 */
    usbd_bus_reset(&g_usbd);
}

void USB_LP_IRQHandler(void) {
    uint16_t istr = USB_ISTR;
    if (istr & USB_ISTR_RESET) {
        istr_write((uint16_t)~USB_ISTR_RESET);
        usb_reset();
    }
    while ((istr = USB_ISTR) & USB_ISTR_CTR) {
        unsigned ep = istr & USB_ISTR_EP_ID;
        uint16_t r = epr_get(ep);
        uint8_t buf[64];
        if (ep == 0) {
            if (r & USB_EP_CTR_TX) {
                ep_write(0, 0, 0, USB_EP_CTR_TX);
                usbd_ep0_in_done(&g_usbd);
            }
            if (r & USB_EP_CTR_RX) {
                uint16_t n = USB_COUNT_RX(0) & USB_COUNT_RX_COUNT;
                n = n > sizeof buf ? (uint16_t)sizeof buf : n;
                pma_read(PMA_EP0_RX, buf, n);
                ep_write(0, 0, 0, USB_EP_CTR_RX);
                if (r & USB_EP_SETUP) {
                    if (n == 8) {
                        usbd_setup(&g_usbd, buf);
                    }
                } else {
                    usbd_ep0_out(&g_usbd, buf, n);
                }
            }
        } else if (ep == 1) {
            if (r & USB_EP_CTR_RX) {
                uint16_t n = USB_COUNT_RX(1) & USB_COUNT_RX_COUNT;
                n = n > sizeof buf ? (uint16_t)sizeof buf : n;
                pma_read(PMA_EP1_RX, buf, n);
                uint32_t m = irq_save();
                ep_write(1, 0, 0, USB_EP_CTR_RX);
                irq_restore(m);
                fw_on_message(g_fw, buf, n); /* the producer side of the core's ring */
                m = irq_save();
                ep_write(1, USB_EP_STAT_RX, STAT_RX(USB_EP_STAT_VALID), 0);
                irq_restore(m);
            }
            if (r & USB_EP_CTR_TX) {
                uint32_t m = irq_save();
                ep_write(1, 0, 0, USB_EP_CTR_TX);
                if (g_pending_count) {
                    ep1_in_load(g_pending[g_pending_head], g_pending_len[g_pending_head]);
                    g_pending_head = (uint8_t)((g_pending_head + 1u) % PENDING_MAX);
                    g_pending_count--;
                }
                irq_restore(m);
            }
        } else {
            ep_write(ep, 0, 0, USB_EP_CTR_RX | USB_EP_CTR_TX); /* not ours */
        }
    }
    /* suspend, wake-up, errors, SOF: acknowledged, nothing to do (the device is bus powered
     * and keeps running; the host timeout ramps the output down when the host goes away) */
    istr_write((uint16_t)~(USB_ISTR_SUSP | USB_ISTR_WKUP | USB_ISTR_ERR | USB_ISTR_PMAOVR | USB_ISTR_SOF));
}

void usb_fs_init(fw_t *f, const uint32_t uid[3]) {
    g_fw = f;
    usbd_init(&g_usbd, &HW, uid);
    RCC_APB1ENR1 |= RCC_APB1ENR1_USBEN;
    (void)RCC_APB1ENR1;
    USB_CNTR = USB_CNTR_FRES; /* power up (PDWN = 0), held in reset */
    for (volatile int i = 0; i < 200; i++) { /* t_STARTUP: 1 us */
    }
    USB_CNTR = 0;
    istr_write(0);
    USB_BTABLE = 0;
    USB_CNTR = USB_CNTR_CTRM | USB_CNTR_RESETM;
    USB_BCDR |= USB_BCDR_DPPU; /* D+ pull-up: the host sees a full-speed device */
}
