/* The USB control-request state machine (usbd.c) against a simulated endpoint 0: the setup
 * packets a Linux host sends at enumeration (usb_new_device / hid-generic), short lengths,
 * SET_ADDRESS after its status stage, HID class requests, and STALLs for what the device does
 * not support. `test_usbd --dump` prints the descriptors for tests/test_board_usb.py. */
#include <stdio.h>
#include <string.h>

#include "check.h"
#include "usb_epr.h"
#include "usbd.h"

int g_checks, g_failures;

/* ---- the simulated endpoint 0 (what usb_fs.c does with the STM32 registers) ---- */
static struct {
    uint8_t tx[64];
    int tx_len; /* -1: no IN packet armed */
    int rx_armed, stalled, address, config, halt_calls;
    uint8_t halt_ep;
    int halt_on;
    uint8_t report_out[64];
    int report_out_len;
    int order; /* set_address must come after the status IN was ACKed */
} sim;

static void ep0_send(void *ctx, const uint8_t *p, uint16_t n) {
    (void)ctx;
    CHECK(n <= 64);
    CHECK(sim.tx_len < 0); /* never two IN packets in flight */
    if (n) memcpy(sim.tx, p, n);
    sim.tx_len = n;
}
static void ep0_recv(void *ctx) { (void)ctx, sim.rx_armed = 1; }
static void ep0_stall(void *ctx) { (void)ctx, sim.stalled = 1; }
static void set_address(void *ctx, uint8_t a) { (void)ctx, sim.address = a, sim.order++; }
static void configure(void *ctx, uint8_t c) { (void)ctx, sim.config = c; }
static void ep_halt(void *ctx, uint8_t ep, bool on) { (void)ctx, sim.halt_ep = ep, sim.halt_on = on, sim.halt_calls++; }
static uint16_t get_report(void *ctx, uint8_t *buf) {
    (void)ctx;
    for (int i = 0; i < HP_REPORT_SIZE; i++) buf[i] = (uint8_t)(0x81 + i);
    return HP_REPORT_SIZE;
}
static void set_report(void *ctx, const uint8_t *p, uint16_t n) {
    (void)ctx;
    memcpy(sim.report_out, p, n);
    sim.report_out_len = n;
}
static const usbd_hw_t HW = {NULL, ep0_send, ep0_recv, ep0_stall, set_address, configure, ep_halt,
                             get_report, set_report};

static void setup(usbd_t *u, uint8_t rt, uint8_t req, uint16_t value, uint16_t index, uint16_t length) {
    uint8_t p[8] = {rt, req, (uint8_t)value, (uint8_t)(value >> 8), (uint8_t)index, (uint8_t)(index >> 8),
                    (uint8_t)length, (uint8_t)(length >> 8)};
    sim.tx_len = -1, sim.rx_armed = 0, sim.stalled = 0; /* a SETUP clears the STALL */
    usbd_setup(u, p);
}

/* A control read as the host does it: IN packets until a short one or wLength, then a
 * zero-length OUT status. Returns the bytes read, or -1 on STALL. */
static int control_in(usbd_t *u, uint8_t rt, uint8_t req, uint16_t value, uint16_t index,
                      uint16_t length, uint8_t *out) {
    setup(u, rt, req, value, index, length);
    int got = 0;
    for (;;) {
        if (sim.stalled) return -1;
        CHECK(sim.tx_len >= 0);
        if (sim.tx_len < 0) return -2;
        int n = sim.tx_len;
        memcpy(out + got, sim.tx, (size_t)n);
        got += n;
        sim.tx_len = -1;
        usbd_ep0_in_done(u);
        if (n < 64 || got >= length) break;
    }
    CHECK(sim.tx_len < 0); /* nothing more after the data stage */
    CHECK(sim.rx_armed);   /* ready for the status OUT */
    usbd_ep0_out(u, NULL, 0);
    CHECK(!sim.stalled);
    CHECK_EQ(u->stage, USBD_IDLE);
    return got;
}

/* A control write without data: the device answers with a zero-length IN (or STALLs). */
static int control_nodata(usbd_t *u, uint8_t rt, uint8_t req, uint16_t value, uint16_t index) {
    setup(u, rt, req, value, index, 0);
    if (sim.stalled) return -1;
    CHECK_EQ(sim.tx_len, 0);
    sim.tx_len = -1;
    usbd_ep0_in_done(u);
    CHECK_EQ(u->stage, USBD_IDLE);
    return 0;
}

static const uint32_t UID[3] = {0x00390021u, 0x4D4B5011u, 0x20343634u};

static void test_linux_enumeration(void) {
    static usbd_t u;
    uint8_t b[512];
    memset(&sim, 0, sizeof sim);
    usbd_init(&u, &HW, UID);
    usbd_bus_reset(&u);
    CHECK_EQ(sim.config, 0);
    /* 1. GET_DESCRIPTOR(device) with wLength 64: one short packet of 18 bytes */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0100, 0, 64, b), 18);
    CHECK(memcmp(b, usbd_device_desc, 18) == 0);
    CHECK_EQ(b[7], 64);
    CHECK_EQ(b[8] | (b[9] << 8), HP_USB_VID);
    CHECK_EQ(b[10] | (b[11] << 8), HP_USB_PID);
    /* 2. a second bus reset, then SET_ADDRESS: applied only after the status stage */
    usbd_bus_reset(&u);
    setup(&u, 0x00, 5, 23, 0, 0);
    CHECK_EQ(sim.tx_len, 0);
    CHECK_EQ(sim.order, 0);
    CHECK_EQ(sim.address, 0);
    sim.tx_len = -1;
    usbd_ep0_in_done(&u);
    CHECK_EQ(sim.order, 1);
    CHECK_EQ(sim.address, 23);
    CHECK_EQ(u.state, USBD_ADDRESS);
    /* 3. GET_DESCRIPTOR(device) with wLength 18, and an 8-byte one (older hosts) */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0100, 0, 18, b), 18);
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0100, 0, 8, b), 8);
    CHECK(memcmp(b, usbd_device_desc, 8) == 0);
    /* 4. configuration: 9 bytes first, then wTotalLength, then 255 as some hosts ask */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0200, 0, 9, b), 9);
    uint16_t total = (uint16_t)(b[2] | (b[3] << 8));
    CHECK_EQ(total, USBD_CONFIG_DESC_LEN);
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0200, 0, total, b), total);
    CHECK(memcmp(b, usbd_config_desc, total) == 0);
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0200, 0, 255, b), total);
    /* 5. strings: languages, product, manufacturer, serial number from the unique ID */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0300, 0, 255, b), 4);
    CHECK(b[2] == 0x09 && b[3] == 0x04);
    int n = control_in(&u, 0x80, 6, 0x0302, 0x0409, 255, b);
    CHECK_EQ(n, 2 + 2 * (int)strlen("hostd vibrotactile display"));
    CHECK(b[0] == n && b[1] == 3 && b[2] == 'h' && b[3] == 0);
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0301, 0x0409, 255, b), 2 + 2 * 5);
    n = control_in(&u, 0x80, 6, 0x0303, 0x0409, 255, b);
    CHECK_EQ(n, 2 + 2 * 24);
    const char *want = "003900214D4B501120343634";
    for (int i = 0; i < 24; i++) CHECK(b[2 + 2 * i] == want[i] && b[3 + 2 * i] == 0);
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0303, 0x0409, 2, b), 2); /* length probe */
    CHECK_EQ(b[0], 50);
    /* 6. SET_CONFIGURATION(1): the interrupt endpoints open */
    CHECK_EQ(control_nodata(&u, 0x00, 9, 1, 0), 0);
    CHECK_EQ(sim.config, 1);
    CHECK_EQ(u.state, USBD_CONFIGURED);
    CHECK_EQ(control_in(&u, 0x80, 8, 0, 0, 1, b), 1);
    CHECK_EQ(b[0], 1);
    /* 7. hid-generic: SET_IDLE(0), then the report descriptor from the interface */
    CHECK_EQ(control_nodata(&u, 0x21, 0x0A, 0, 0), 0);
    CHECK_EQ(control_in(&u, 0xA1, 0x02, 0, 0, 1, b), 1); /* GET_IDLE */
    CHECK_EQ(b[0], 0);
    CHECK_EQ(control_in(&u, 0x81, 6, 0x2200, 0, (uint16_t)(usbd_hid_report_desc_len + 64), b),
             usbd_hid_report_desc_len);
    CHECK(memcmp(b, usbd_hid_report_desc, usbd_hid_report_desc_len) == 0);
    CHECK_EQ(control_in(&u, 0x81, 6, 0x2100, 0, 9, b), 9); /* the HID descriptor */
    CHECK_EQ(b[1], 0x21);
    CHECK_EQ(b[7] | (b[8] << 8), usbd_hid_report_desc_len);
    /* 8. GET_REPORT(Input): 64 bytes; asked for more, a zero-length packet ends it */
    CHECK_EQ(control_in(&u, 0xA1, 0x01, 0x0100, 0, 64, b), 64);
    CHECK_EQ(b[0], 0x81);
    CHECK_EQ(control_in(&u, 0xA1, 0x01, 0x0100, 0, 255, b), 64);
    CHECK_EQ(b[63], (uint8_t)(0x81 + 63));
    /* 9. GET_STATUS of device, interface, endpoint */
    CHECK_EQ(control_in(&u, 0x80, 0, 0, 0, 2, b), 2);
    CHECK_EQ(control_in(&u, 0x81, 0, 0, 0, 2, b), 2);
    CHECK_EQ(control_in(&u, 0x82, 0, 0, HP_USB_EP_IN, 2, b), 2);
    CHECK_EQ(b[0], 0);
}

static void test_stalls_and_features(void) {
    static usbd_t u;
    uint8_t b[256];
    memset(&sim, 0, sizeof sim);
    usbd_init(&u, &HW, UID);
    usbd_bus_reset(&u);
    /* before an address: no SET_CONFIGURATION, no GET_CONFIGURATION */
    CHECK_EQ(control_nodata(&u, 0x00, 9, 1, 0), -1);
    CHECK_EQ(control_in(&u, 0x80, 8, 0, 0, 1, b), -1);
    CHECK_EQ(control_nodata(&u, 0x00, 5, 7, 0), 0);
    CHECK_EQ(sim.address, 7);
    unsigned before = u.stalls;
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0600, 0, 10, b), -1);  /* device qualifier: full speed only */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0700, 0, 9, b), -1);   /* other-speed configuration */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0201, 0, 9, b), -1);   /* configuration index 1 */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0304, 0x0409, 255, b), -1); /* no string 4 */
    CHECK_EQ(control_in(&u, 0xC0, 0x33, 0, 0, 8, b), -1);     /* vendor request */
    CHECK_EQ(control_nodata(&u, 0x00, 9, 2, 0), -1);          /* no configuration 2 */
    CHECK_EQ(control_nodata(&u, 0x00, 3, 1, 0), -1);          /* SET_FEATURE(remote wake-up) */
    CHECK_EQ(control_nodata(&u, 0x21, 0x0B, 0, 0), -1);       /* SET_PROTOCOL: not a boot device */
    CHECK_EQ(control_in(&u, 0xA1, 0x03, 0, 0, 1, b), -1);     /* GET_PROTOCOL */
    CHECK_EQ(control_in(&u, 0xA1, 0x01, 0x0300, 0, 64, b), -1); /* GET_REPORT(Feature) */
    CHECK_EQ(control_in(&u, 0x81, 6, 0x2200, 1, 64, b), -1);  /* interface 1 does not exist */
    CHECK_EQ(control_in(&u, 0x82, 0, 0, 0x82, 2, b), -1);     /* endpoint 0x82 does not exist */
    CHECK_EQ(control_in(&u, 0x82, 0, 0, HP_USB_EP_IN, 2, b), -1); /* data endpoint before configuration */
    CHECK_EQ(u.stalls - before, 13);
    /* a stalled request does not wedge endpoint 0: the next SETUP works */
    CHECK_EQ(control_in(&u, 0x80, 6, 0x0100, 0, 18, b), 18);
    CHECK_EQ(control_nodata(&u, 0x00, 9, 1, 0), 0);
    /* endpoint halt: SET_FEATURE / GET_STATUS / CLEAR_FEATURE (resets the data toggle) */
    CHECK_EQ(control_nodata(&u, 0x02, 3, 0, HP_USB_EP_IN), 0);
    CHECK(sim.halt_ep == HP_USB_EP_IN && sim.halt_on);
    CHECK_EQ(control_in(&u, 0x82, 0, 0, HP_USB_EP_IN, 2, b), 2);
    CHECK_EQ(b[0], 1);
    CHECK_EQ(control_nodata(&u, 0x02, 1, 0, HP_USB_EP_IN), 0);
    CHECK(sim.halt_ep == HP_USB_EP_IN && !sim.halt_on);
    CHECK_EQ(control_in(&u, 0x82, 0, 0, HP_USB_EP_IN, 2, b), 2);
    CHECK_EQ(b[0], 0);
    CHECK_EQ(control_nodata(&u, 0x02, 1, 0, HP_USB_EP_OUT), 0);
    CHECK_EQ(sim.halt_ep, HP_USB_EP_OUT);
    /* SET_REPORT(Output) on endpoint 0: the data stage is handed over, then the status IN */
    uint8_t msg[64] = {HP_ID_START};
    setup(&u, 0x21, 0x09, 0x0200, 0, 64);
    CHECK(sim.rx_armed && !sim.stalled);
    usbd_ep0_out(&u, msg, 64);
    CHECK_EQ(sim.report_out_len, 64);
    CHECK_EQ(sim.report_out[0], HP_ID_START);
    CHECK_EQ(sim.tx_len, 0);
    sim.tx_len = -1;
    usbd_ep0_in_done(&u);
    /* an OUT packet nobody asked for is refused */
    usbd_ep0_out(&u, msg, 8);
    CHECK(sim.stalled);
    /* SET_REPORT longer than the data announced: refused */
    setup(&u, 0x21, 0x09, 0x0200, 0, 8);
    usbd_ep0_out(&u, msg, 64);
    CHECK(sim.stalled);
    /* a bus reset closes the endpoints and forgets the configuration */
    usbd_bus_reset(&u);
    CHECK_EQ(sim.config, 0);
    CHECK_EQ(u.state, USBD_DEFAULT);
    /* SET_CONFIGURATION(0) goes back to the address state */
    CHECK_EQ(control_nodata(&u, 0x00, 5, 9, 0), 0);
    CHECK_EQ(control_nodata(&u, 0x00, 9, 1, 0), 0);
    CHECK_EQ(control_nodata(&u, 0x00, 9, 0, 0), 0);
    CHECK_EQ(sim.config, 0);
    CHECK_EQ(u.state, USBD_ADDRESS);
}

/* A model of an EPnR write (RM0440 45.6.2): toggle bits flip where 1 is written, CTR flags
 * clear where 0 is written (and may be set by the hardware between the driver's read and
 * its write), EP_TYPE / EP_KIND / EA take the written value, SETUP is read-only. */
static uint16_t epr_model_write(uint16_t cur, uint16_t w, uint16_t set_by_hw) {
    const uint16_t ctr = USB_EP_CTR_RX | USB_EP_CTR_TX, plain = USB_EP_TYPE | USB_EP_KIND | USB_EP_EA;
    uint16_t toggles = (uint16_t)((cur ^ w) & USB_EP_TOGGLES);
    uint16_t flags = (uint16_t)((cur | set_by_hw) & (w | (uint16_t)~ctr) & ctr);
    return (uint16_t)(toggles | flags | (w & plain) | (cur & USB_EP_SETUP));
}

static void test_endpoint_register_writes(void) {
    uint32_t x = 12345;
    long bad = 0;
    for (int i = 0; i < 200000; i++) {
        x = x * 1664525u + 1013904223u;
        uint16_t cur = (uint16_t)(x >> 16);
        x = x * 1664525u + 1013904223u;
        uint16_t which = (uint16_t)((x >> 16) & USB_EP_TOGGLES), want = (uint16_t)(x & USB_EP_TOGGLES);
        x = x * 1664525u + 1013904223u;
        /* the driver clears only a flag it read as set */
        uint16_t clear = (uint16_t)((x >> 16) & cur & (USB_EP_CTR_RX | USB_EP_CTR_TX));
        uint16_t hw = (uint16_t)(x & (USB_EP_CTR_RX | USB_EP_CTR_TX));
        uint16_t after = epr_model_write(cur, usb_epr_value(cur, which, want, clear), hw);
        /* the selected toggles reach `want`, the others stay */
        if ((after & USB_EP_TOGGLES) != (uint16_t)((want & which) | (cur & USB_EP_TOGGLES & ~which))) bad++;
        /* only the flags asked for are cleared; one the hardware set meanwhile survives */
        uint16_t ctr = USB_EP_CTR_RX | USB_EP_CTR_TX;
        if ((after & ctr) != (uint16_t)(((cur | hw) & ctr) & ~clear)) bad++;
        if ((after & (USB_EP_TYPE | USB_EP_KIND | USB_EP_EA | USB_EP_SETUP)) !=
            (cur & (USB_EP_TYPE | USB_EP_KIND | USB_EP_EA | USB_EP_SETUP)))
            bad++;
        /* opening: type, address, stats, toggles 0, flags untouched */
        uint16_t srx = (uint16_t)(x >> 30), stx = (uint16_t)((x >> 28) & 3u);
        uint16_t opened = epr_model_write(cur, usb_epr_open(cur, USB_EP_TYPE_INTERRUPT, 1, srx, stx), 0);
        if ((opened & (USB_EP_TYPE | USB_EP_EA)) != (USB_EP_TYPE_INTERRUPT | 1u)) bad++;
        if ((opened & USB_EP_TOGGLES) != (uint16_t)((srx << 12) | (stx << 4))) bad++;
        if ((opened & ctr) != (cur & ctr)) bad++;
    }
    CHECK_EQ(bad, 0);
    /* and the model is not trivially satisfied: writing back what was read flips toggles */
    uint16_t cur = (uint16_t)(USB_EP_STAT_TX | USB_EP_CTR_RX);
    CHECK(epr_model_write(cur, cur, 0) != cur);
}

static void hex(const char *name, const uint8_t *p, size_t n) {
    printf("%s ", name);
    for (size_t i = 0; i < n; i++) printf("%02x", p[i]);
    printf("\n");
}

int main(int argc, char **argv) {
    if (argc > 1 && !strcmp(argv[1], "--dump")) {
        static usbd_t u;
        usbd_init(&u, &HW, UID);
        hex("device", usbd_device_desc, sizeof usbd_device_desc);
        hex("config", usbd_config_desc, sizeof usbd_config_desc);
        hex("report", usbd_hid_report_desc, usbd_hid_report_desc_len);
        hex("serial", u.serial_desc, sizeof u.serial_desc);
        return 0;
    }
    test_linux_enumeration();
    test_stalls_and_features();
    test_endpoint_register_writes();
    printf("usb control requests: %d checks, %d failures\n", g_checks, g_failures);
    return g_failures ? 1 : 0;
}
