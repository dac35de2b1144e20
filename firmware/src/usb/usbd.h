/* A minimal USB full-speed HID device for the display: descriptors and the endpoint-0
 * control-request state machine. Portable C11: the peripheral sits behind usbd_hw_t (the
 * STM32G4 driver in port/stm32g4/usb_fs.c; a simulated endpoint 0 in port/stm32g4/tests/test_usbd.c).
 * The stack every board shares (TinyUSB's usbd/dcd cut): a new board brings its usbd_hw_t only.
 *
 * One HID interface, no report IDs, one interrupt IN (HP_USB_EP_IN) and one interrupt OUT
 * (HP_USB_EP_OUT) endpoint, 1 ms interval, HP_REPORT_SIZE-byte reports: one protocol message
 * per report (docs/protocol.md). VID/PID/endpoints/report size come from hostd_proto.h. */
#ifndef HOSTD_USBD_H
#define HOSTD_USBD_H

#include <stdbool.h>
#include <stdint.h>

#include "hostd_proto.h"
#include "hostd_usb.h"

#define USBD_EP0_SIZE 64u
#define USBD_CONFIG_DESC_LEN 41u
#define USBD_UID_WORDS 3u
#define USBD_SERIAL_CHARS (8u * USBD_UID_WORDS) /* 96-bit unique ID as 24 hex digits */
_Static_assert(USBD_SERIAL_CHARS == HOSTD_USB_SERIAL_CHARS, "hostd_usb.h: the serial is the 96-bit UID");

extern const uint8_t usbd_device_desc[18];
extern const uint8_t usbd_config_desc[USBD_CONFIG_DESC_LEN];
extern const uint8_t usbd_hid_report_desc[];
extern const uint16_t usbd_hid_report_desc_len;

/* What the state machine asks of the peripheral. All calls come from the USB interrupt. */
typedef struct {
    void *ctx;
    void (*ep0_send)(void *ctx, const uint8_t *p, uint16_t n); /* one IN packet, n <= 64 (0: ZLP) */
    void (*ep0_recv)(void *ctx);                              /* accept one OUT packet */
    void (*ep0_stall)(void *ctx);                             /* STALL until the next SETUP */
    void (*set_address)(void *ctx, uint8_t addr);             /* after the status stage */
    void (*configure)(void *ctx, uint8_t config);             /* 1: open the interrupt EPs, 0: close */
    void (*ep_halt)(void *ctx, uint8_t ep, bool halt);        /* clear also resets the data toggle */
    uint16_t (*get_report)(void *ctx, uint8_t *buf);          /* HID GET_REPORT(Input): <= 64 bytes */
    void (*set_report)(void *ctx, const uint8_t *p, uint16_t n); /* HID SET_REPORT(Output) on EP0 */
} usbd_hw_t;

enum { USBD_DEFAULT, USBD_ADDRESS, USBD_CONFIGURED };
enum { USBD_IDLE, USBD_DATA_IN, USBD_STATUS_OUT, USBD_DATA_OUT, USBD_STATUS_IN };

typedef struct {
    const usbd_hw_t *hw;
    uint8_t state, stage, config, idle_rate, new_address;
    bool halted_in, halted_out;
    const uint8_t *tx;
    uint16_t tx_left;
    bool tx_zlp; /* a zero-length packet ends a reply shorter than asked that fills its last packet */
    uint8_t setup[8];
    uint8_t buf[USBD_EP0_SIZE]; /* GET_REPORT / GET_STATUS replies and SET_REPORT data */
    uint16_t rx_len, rx_want;
    uint8_t serial_desc[2 + 2 * USBD_SERIAL_CHARS];
    uint32_t stalls; /* requests refused (for tests and logs) */
} usbd_t;

void usbd_init(usbd_t *u, const usbd_hw_t *hw, const uint32_t uid[USBD_UID_WORDS]);
void usbd_bus_reset(usbd_t *u);                                /* USB RESET seen */
void usbd_setup(usbd_t *u, const uint8_t pkt[8]);              /* SETUP packet on EP0 */
void usbd_ep0_in_done(usbd_t *u);                              /* an EP0 IN packet was ACKed */
void usbd_ep0_out(usbd_t *u, const uint8_t *p, uint16_t n);    /* an EP0 OUT packet arrived */

#endif
