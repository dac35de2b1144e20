/* USB descriptors and the endpoint-0 state machine (see usbd.h). USB 2.0 chapter 9 and the
 * HID 1.11 class requests; everything else is refused with a STALL. */
#include "usbd.h"

#include <string.h>

#define LO(x) ((uint8_t)((x) & 0xFFu))
#define HI(x) ((uint8_t)(((x) >> 8) & 0xFFu))
#define BCD_DEVICE HOSTD_USB_BCD_DEVICE

_Static_assert(HP_REPORT_SIZE <= 64 && HP_REPORT_SIZE > 0, "a full-speed interrupt packet holds <= 64 bytes");
_Static_assert((HP_USB_EP_IN & 0x80) && (HP_USB_EP_OUT & 0x80) == 0 && (HP_USB_EP_IN & 0x0F) == 1 &&
                   (HP_USB_EP_OUT & 0x0F) == 1,
               "the STM32 driver serves endpoint 1 (IN 0x81, OUT 0x01)");

const uint8_t usbd_device_desc[18] = {
    18, 1,                            /* bLength, DEVICE */
    0x00, 0x02,                       /* bcdUSB 2.00 */
    0, 0, 0,                          /* class in the interface */
    USBD_EP0_SIZE,                    /* bMaxPacketSize0 */
    LO(HP_USB_VID), HI(HP_USB_VID),   /* idVendor */
    LO(HP_USB_PID), HI(HP_USB_PID),   /* idProduct */
    LO(BCD_DEVICE), HI(BCD_DEVICE),   /* bcdDevice: firmware version */
    1, 2, 3,                          /* iManufacturer, iProduct, iSerialNumber */
    1,                                /* bNumConfigurations */
};

/* The HID report descriptor and the strings: hostd_usb.h, shared with the Linux gadget port. */
const uint8_t usbd_hid_report_desc[] = HOSTD_USB_HID_REPORT_DESC;
const uint16_t usbd_hid_report_desc_len = sizeof usbd_hid_report_desc;
#define REPORT_DESC_LEN HOSTD_USB_HID_REPORT_DESC_LEN
_Static_assert(sizeof usbd_hid_report_desc == REPORT_DESC_LEN, "keep REPORT_DESC_LEN in step");

const uint8_t usbd_config_desc[USBD_CONFIG_DESC_LEN] = {
    9, 2, LO(USBD_CONFIG_DESC_LEN), HI(USBD_CONFIG_DESC_LEN), /* CONFIGURATION, wTotalLength */
    1, 1, 0,                          /* bNumInterfaces, bConfigurationValue, iConfiguration */
    0x80, HOSTD_USB_MAX_POWER_MA / 2,  /* bus powered */
    9, 4, 0, 0, 2, 3, HOSTD_USB_HID_SUBCLASS, HOSTD_USB_HID_PROTOCOL, 0, /* INTERFACE 0, 2 endpoints, HID */
    9, 0x21, 0x11, 0x01, 0, 1, 0x22, LO(REPORT_DESC_LEN), HI(REPORT_DESC_LEN), /* HID 1.11 */
    7, 5, HP_USB_EP_IN, 3, LO(HP_REPORT_SIZE), HI(HP_REPORT_SIZE), HOSTD_USB_INTERVAL_MS, /* interrupt IN */
    7, 5, HP_USB_EP_OUT, 3, LO(HP_REPORT_SIZE), HI(HP_REPORT_SIZE), HOSTD_USB_INTERVAL_MS, /* interrupt OUT */
};
#define HID_DESC_OFFSET 18u

static const uint8_t lang_desc[4] = {4, 3, 0x09, 0x04}; /* English (United States) */
static const char *const strings[] = {HOSTD_USB_MANUFACTURER, HOSTD_USB_PRODUCT};

static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

void usbd_init(usbd_t *u, const usbd_hw_t *hw, const uint32_t uid[USBD_UID_WORDS]) {
    memset(u, 0, sizeof *u);
    u->hw = hw;
    static const char hex[] = "0123456789ABCDEF";
    u->serial_desc[0] = sizeof u->serial_desc;
    u->serial_desc[1] = 3;
    for (unsigned i = 0; i < USBD_SERIAL_CHARS; i++) {
        uint32_t w = uid[i / 8];
        u->serial_desc[2 + 2 * i] = (uint8_t)hex[(w >> (28 - 4 * (i % 8))) & 0xF];
    }
}

void usbd_bus_reset(usbd_t *u) {
    u->state = USBD_DEFAULT;
    u->stage = USBD_IDLE;
    u->config = 0;
    u->halted_in = u->halted_out = false;
    u->hw->configure(u->hw->ctx, 0);
}

static void stall(usbd_t *u) {
    u->stage = USBD_IDLE;
    u->stalls++;
    u->hw->ep0_stall(u->hw->ctx);
}

static void send_next(usbd_t *u) {
    uint16_t n = u->tx_left < USBD_EP0_SIZE ? u->tx_left : USBD_EP0_SIZE;
    if (n == 0 && !u->tx_zlp) {
        /* data stage done: the host's zero-length OUT is the status stage */
        u->stage = USBD_STATUS_OUT;
        u->hw->ep0_recv(u->hw->ctx);
        return;
    }
    if (n == 0) {
        u->tx_zlp = false;
    }
    u->hw->ep0_send(u->hw->ctx, u->tx, n);
    u->tx += n;
    u->tx_left = (uint16_t)(u->tx_left - n);
    if (n < USBD_EP0_SIZE) {
        u->tx_zlp = false; /* a short packet ends the data stage */
    }
    if (u->tx_left == 0 && !u->tx_zlp) {
        u->stage = USBD_STATUS_OUT; /* the host may send its status OUT right away */
        u->hw->ep0_recv(u->hw->ctx);
    } else {
        u->stage = USBD_DATA_IN;
    }
}

static void reply(usbd_t *u, const uint8_t *p, uint16_t len) {
    uint16_t want = rd16(u->setup + 6);
    u->tx = p;
    u->tx_left = len < want ? len : want;
    u->tx_zlp = u->tx_left < want && u->tx_left % USBD_EP0_SIZE == 0;
    send_next(u);
}

static void status_in(usbd_t *u) {
    u->stage = USBD_STATUS_IN;
    u->hw->ep0_send(u->hw->ctx, NULL, 0);
}

static void string_desc(usbd_t *u, uint8_t index) {
    if (index == 0) {
        reply(u, lang_desc, sizeof lang_desc);
    } else if (index == 3) {
        reply(u, u->serial_desc, sizeof u->serial_desc);
    } else if (index <= sizeof strings / sizeof strings[0]) {
        const char *s = strings[index - 1];
        size_t n = strlen(s);
        if (2 + 2 * n > sizeof u->buf) {
            stall(u);
            return;
        }
        u->buf[0] = (uint8_t)(2 + 2 * n);
        u->buf[1] = 3;
        for (size_t i = 0; i < n; i++) {
            u->buf[2 + 2 * i] = (uint8_t)s[i];
            u->buf[3 + 2 * i] = 0;
        }
        reply(u, u->buf, u->buf[0]);
    } else {
        stall(u);
    }
}

static void get_descriptor(usbd_t *u, uint8_t type, uint8_t index, bool iface) {
    if (iface) { /* HID class descriptors, asked of the interface */
        if (type == 0x21) {
            reply(u, usbd_config_desc + HID_DESC_OFFSET, 9);
        } else if (type == 0x22) {
            reply(u, usbd_hid_report_desc, usbd_hid_report_desc_len);
        } else {
            stall(u);
        }
        return;
    }
    switch (type) {
    case 1: reply(u, usbd_device_desc, sizeof usbd_device_desc); break;
    case 2:
        if (index == 0) {
            reply(u, usbd_config_desc, sizeof usbd_config_desc);
        } else {
            stall(u);
        }
        break;
    case 3: string_desc(u, index); break;
    default: stall(u); break; /* device qualifier (6) etc.: a full-speed-only device stalls */
    }
}

static bool ep_known(uint8_t ep) { return ep == 0x00 || ep == 0x80 || ep == HP_USB_EP_IN || ep == HP_USB_EP_OUT; }

void usbd_setup(usbd_t *u, const uint8_t pkt[8]) {
    memcpy(u->setup, pkt, 8);
    const uint8_t rt = pkt[0], req = pkt[1];
    const uint16_t value = rd16(pkt + 2), index = rd16(pkt + 4), length = rd16(pkt + 6);
    const uint8_t type = rt & 0x60u, recip = rt & 0x1Fu;
    const bool in = (rt & 0x80u) != 0;
    u->stage = USBD_IDLE;
    u->tx_left = 0;
    u->tx_zlp = false;

    if (type == 0x00 && recip == 0) { /* standard, device */
        switch (req) {
        case 0x00: /* GET_STATUS: bus powered, no remote wake-up */
            if (!in || value != 0 || index != 0 || length != 2) break;
            u->buf[0] = u->buf[1] = 0;
            reply(u, u->buf, 2);
            return;
        case 0x05: /* SET_ADDRESS: takes effect after the status stage */
            if (in || value > 127 || index != 0 || length != 0 || u->state == USBD_CONFIGURED) break;
            u->new_address = (uint8_t)value;
            status_in(u);
            return;
        case 0x06: /* GET_DESCRIPTOR */
            if (!in) break;
            get_descriptor(u, (uint8_t)(value >> 8), (uint8_t)value, false);
            return;
        case 0x08: /* GET_CONFIGURATION */
            if (!in || length != 1 || u->state == USBD_DEFAULT) break;
            u->buf[0] = u->config;
            reply(u, u->buf, 1);
            return;
        case 0x09: /* SET_CONFIGURATION */
            if (in || value > 1 || length != 0 || u->state == USBD_DEFAULT) break;
            u->config = (uint8_t)value;
            u->state = value ? USBD_CONFIGURED : USBD_ADDRESS;
            u->halted_in = u->halted_out = false;
            u->hw->configure(u->hw->ctx, u->config);
            status_in(u);
            return;
        default: break; /* SET/CLEAR_FEATURE (no remote wake-up, no test modes), SET_DESCRIPTOR... */
        }
    } else if (type == 0x00 && recip == 1 && (index & 0xFF) == 0) { /* standard, interface 0 */
        switch (req) {
        case 0x00: /* GET_STATUS */
            if (!in || length != 2 || u->state != USBD_CONFIGURED) break;
            u->buf[0] = u->buf[1] = 0;
            reply(u, u->buf, 2);
            return;
        case 0x06: /* GET_DESCRIPTOR: HID or report descriptor */
            if (!in) break;
            get_descriptor(u, (uint8_t)(value >> 8), (uint8_t)value, true);
            return;
        case 0x0A: /* GET_INTERFACE */
            if (!in || length != 1 || u->state != USBD_CONFIGURED) break;
            u->buf[0] = 0;
            reply(u, u->buf, 1);
            return;
        case 0x0B: /* SET_INTERFACE: only alternate setting 0 */
            if (in || value != 0 || u->state != USBD_CONFIGURED) break;
            status_in(u);
            return;
        default: break;
        }
    } else if (type == 0x00 && recip == 2 && ep_known((uint8_t)index)) { /* standard, endpoint */
        const uint8_t ep = (uint8_t)index;
        const bool data_ep = (ep & 0x0F) != 0;
        if (data_ep && u->state != USBD_CONFIGURED) {
            stall(u);
            return;
        }
        bool *halted = ep == HP_USB_EP_IN ? &u->halted_in : &u->halted_out;
        switch (req) {
        case 0x00: /* GET_STATUS: the halt bit */
            if (!in || length != 2) break;
            u->buf[0] = data_ep && *halted;
            u->buf[1] = 0;
            reply(u, u->buf, 2);
            return;
        case 0x01: /* CLEAR_FEATURE(ENDPOINT_HALT) */
        case 0x03: /* SET_FEATURE(ENDPOINT_HALT) */
            if (in || value != 0 || length != 0) break;
            if (data_ep) {
                *halted = req == 0x03;
                u->hw->ep_halt(u->hw->ctx, ep, *halted);
            }
            status_in(u);
            return;
        default: break;
        }
    } else if (type == 0x20 && recip == 1 && (index & 0xFF) == 0) { /* HID class, interface 0 */
        switch (req) {
        case 0x01: /* GET_REPORT: Input, no report ID */
            if (!in || value != 0x0100) break;
            reply(u, u->buf, u->hw->get_report(u->hw->ctx, u->buf));
            return;
        case 0x02: /* GET_IDLE */
            if (!in || length != 1) break;
            u->buf[0] = u->idle_rate;
            reply(u, u->buf, 1);
            return;
        case 0x09: /* SET_REPORT: Output, no report ID, data stage follows */
            if (in || value != 0x0200 || length == 0 || length > sizeof u->buf) break;
            u->rx_len = 0;
            u->rx_want = length;
            u->stage = USBD_DATA_OUT;
            u->hw->ep0_recv(u->hw->ctx);
            return;
        case 0x0A: /* SET_IDLE: reports go out every tick anyway; remembered for GET_IDLE */
            if (in || length != 0) break;
            u->idle_rate = (uint8_t)(value >> 8);
            status_in(u);
            return;
        default: break; /* GET/SET_PROTOCOL: not a boot device */
        }
    }
    stall(u);
}

void usbd_ep0_in_done(usbd_t *u) {
    switch (u->stage) {
    case USBD_DATA_IN: send_next(u); break;
    case USBD_STATUS_IN:
        u->stage = USBD_IDLE;
        if (u->setup[1] == 0x05 && (u->setup[0] & 0x7F) == 0) { /* SET_ADDRESS completed */
            u->hw->set_address(u->hw->ctx, u->new_address);
            u->state = u->new_address ? USBD_ADDRESS : USBD_DEFAULT;
        }
        break;
    default: break; /* nothing was in flight: ignore */
    }
}

void usbd_ep0_out(usbd_t *u, const uint8_t *p, uint16_t n) {
    switch (u->stage) {
    case USBD_STATUS_OUT: /* the host's zero-length status packet, possibly before all data */
        u->stage = USBD_IDLE;
        break;
    case USBD_DATA_OUT:
        if (u->rx_len + n > u->rx_want) {
            stall(u);
            return;
        }
        memcpy(u->buf + u->rx_len, p, n);
        u->rx_len = (uint16_t)(u->rx_len + n);
        if (u->rx_len == u->rx_want || n < USBD_EP0_SIZE) {
            u->hw->set_report(u->hw->ctx, u->buf, u->rx_len);
            status_in(u);
        } else {
            u->hw->ep0_recv(u->hw->ctx);
        }
        break;
    default:
        stall(u); /* an OUT packet nobody asked for */
        break;
    }
}
