/* The STM32 USB driver (usb_fs.c) on the host, against a model of the peripheral
 * (usb_fs_sim.h): buffer table and packet memory, EPnR write semantics, the interrupt's
 * dispatch, and the path from endpoint 1 to the firmware core and back. A simulated host
 * enumerates it, then streams protocol messages. */
#include <stdio.h>
#include <string.h>

#include "board.h"
#include "check.h"
#include "hal.h"
#include "regs.h"
#include "usb_fs_sim.h"
#include "usbd.h"

int g_checks, g_failures;
usb_sim_t g_sim;
void USB_LP_IRQHandler(void);

/* ---- the model of the hardware ---- */
void sim_epr_write(unsigned ep, uint16_t w) {
    CHECK(ep < 8);
    uint16_t cur = g_sim.epr[ep];
    const uint16_t tog = USB_EP_STAT_RX | USB_EP_DTOG_RX | USB_EP_STAT_TX | USB_EP_DTOG_TX;
    const uint16_t ctr = USB_EP_CTR_RX | USB_EP_CTR_TX, plain = USB_EP_TYPE | USB_EP_KIND | USB_EP_EA;
    g_sim.epr[ep] = (uint16_t)(((cur ^ w) & tog) | (cur & w & ctr) | (w & plain) | (cur & USB_EP_SETUP));
}
void sim_istr_write(uint16_t v) { g_sim.istr_flags &= (uint16_t)(v & 0x7F00u); }
uint16_t sim_istr_read(void) {
    uint16_t r = g_sim.istr_flags;
    for (unsigned ep = 0; ep < 8; ep++) {
        if (g_sim.epr[ep] & (USB_EP_CTR_RX | USB_EP_CTR_TX)) {
            r |= (uint16_t)(USB_ISTR_CTR | ep | ((g_sim.epr[ep] & USB_EP_CTR_RX) ? USB_ISTR_DIR : 0));
            break;
        }
    }
    return r;
}

/* ---- the HAL of the core for this test ---- */
static uint32_t fake_us;
uint32_t hal_time_us(void) { return fake_us; }
void hal_dac_write(int16_t code) { (void)code; }
void hal_send(const uint8_t *msg, size_t len) { usb_fs_send(msg, len); }

/* ---- the serial interface engine and the host ---- */
static unsigned stat_rx(unsigned ep) { return (g_sim.epr[ep] >> 12) & 3u; }
static unsigned stat_tx(unsigned ep) { return (g_sim.epr[ep] >> 4) & 3u; }
static void hw_stat(unsigned ep, unsigned rx, unsigned tx) {
    g_sim.epr[ep] = (uint16_t)((g_sim.epr[ep] & ~(USB_EP_STAT_RX | USB_EP_STAT_TX)) | (rx << 12) | (tx << 4));
}
static uint16_t bt(unsigned ep, unsigned word) { return g_sim.pma[(g_sim.btable + 8u * ep) / 2u + word]; }
static int rx_capacity(unsigned ep) {
    uint16_t c = bt(ep, 3);
    return (c & 0x8000u) ? 32 * (((c >> 10) & 0x1F) + 1) : 2 * ((c >> 10) & 0x1F);
}
static void to_pma(uint16_t addr, const uint8_t *p, int n) {
    for (int i = 0; i < n; i += 2) {
        g_sim.pma[(addr + i) / 2] = (uint16_t)(p[i] | ((i + 1 < n ? p[i + 1] : 0) << 8));
    }
}
static void rx_done(unsigned ep, const uint8_t *p, int n, int setup) {
    CHECK(n <= rx_capacity(ep));
    to_pma(bt(ep, 2), p, n);
    g_sim.pma[(g_sim.btable + 8u * ep) / 2u + 3] = (uint16_t)((bt(ep, 3) & 0xFC00u) | (uint16_t)n);
    g_sim.epr[ep] = (uint16_t)((g_sim.epr[ep] & ~USB_EP_SETUP) | USB_EP_CTR_RX | (setup ? USB_EP_SETUP : 0));
    hw_stat(ep, USB_EP_STAT_NAK, setup ? USB_EP_STAT_NAK : stat_tx(ep));
    USB_LP_IRQHandler();
}
static void sie_setup(const uint8_t pkt[8]) {
    CHECK((g_sim.epr[0] & USB_EP_TYPE) == USB_EP_TYPE_CONTROL && (g_sim.epr[0] & USB_EP_EA) == 0);
    rx_done(0, pkt, 8, 1); /* a SETUP is taken whatever STAT_RX says */
}
/* IN token: bytes sent, or -1 NAK, -2 STALL, -3 disabled */
static int sie_in(unsigned ep, uint8_t *out) {
    unsigned s = stat_tx(ep);
    if (s != USB_EP_STAT_VALID) return s == USB_EP_STAT_NAK ? -1 : s == USB_EP_STAT_STALL ? -2 : -3;
    int n = bt(ep, 1) & 0x3FF;
    uint16_t a = bt(ep, 0);
    for (int i = 0; i < n; i++) out[i] = (uint8_t)(g_sim.pma[(a + i) / 2] >> (8 * ((a + i) & 1)));
    g_sim.epr[ep] |= USB_EP_CTR_TX;
    hw_stat(ep, stat_rx(ep), USB_EP_STAT_NAK);
    USB_LP_IRQHandler();
    return n;
}
/* OUT token: 0, or -1 NAK, -2 STALL, -3 disabled */
static int sie_out(unsigned ep, const uint8_t *p, int n) {
    unsigned s = stat_rx(ep);
    if (s != USB_EP_STAT_VALID) return s == USB_EP_STAT_NAK ? -1 : s == USB_EP_STAT_STALL ? -2 : -3;
    rx_done(ep, p, n, 0);
    return 0;
}

static int control_in(uint8_t rt, uint8_t req, uint16_t value, uint16_t index, uint16_t length, uint8_t *out) {
    uint8_t p[8] = {rt, req, (uint8_t)value, (uint8_t)(value >> 8), (uint8_t)index, (uint8_t)(index >> 8),
                    (uint8_t)length, (uint8_t)(length >> 8)};
    sie_setup(p);
    int got = 0;
    for (;;) {
        int n = sie_in(0, out + got);
        if (n == -2) return -1;
        CHECK(n >= 0);
        if (n < 0) return -9;
        got += n;
        if (n < 64 || got >= length) break;
    }
    CHECK_EQ(sie_out(0, NULL, 0), 0); /* status stage */
    return got;
}
static int control_nodata(uint8_t rt, uint8_t req, uint16_t value, uint16_t index) {
    uint8_t p[8] = {rt, req, (uint8_t)value, (uint8_t)(value >> 8), (uint8_t)index, (uint8_t)(index >> 8), 0, 0};
    sie_setup(p);
    uint8_t b[64];
    int n = sie_in(0, b);
    return n == -2 ? -1 : n;
}

static void bus_reset(void) {
    g_sim.istr_flags |= USB_ISTR_RESET;
    USB_LP_IRQHandler();
    CHECK_EQ(g_sim.istr_flags & USB_ISTR_RESET, 0);
}

static void test_driver(void) {
    static fw_t f;
    memset(&g_sim, 0, sizeof g_sim);
    g_sim.epr[1] = USB_EP_DTOG_TX | USB_EP_DTOG_RX | (USB_EP_STAT_STALL << 4); /* junk before reset */
    fw_init(&f, 0);
    const uint32_t uid[3] = {1, 2, 3};
    usb_fs_init(&f, uid);
    CHECK(g_sim.rcc_apb1enr1 & RCC_APB1ENR1_USBEN);
    CHECK(g_sim.bcdr & USB_BCDR_DPPU);
    CHECK((g_sim.cntr & (USB_CNTR_CTRM | USB_CNTR_RESETM)) == (USB_CNTR_CTRM | USB_CNTR_RESETM));
    CHECK_EQ(g_sim.cntr & (USB_CNTR_PDWN | USB_CNTR_FRES), 0);
    bus_reset();
    CHECK_EQ(g_sim.daddr, USB_DADDR_EF);
    CHECK_EQ(stat_rx(0), USB_EP_STAT_VALID);
    CHECK_EQ(stat_tx(0), USB_EP_STAT_NAK);
    CHECK_EQ(stat_rx(1), USB_EP_STAT_DISABLED);
    CHECK_EQ(rx_capacity(0), 64);
    /* buffers: within the 1 KiB, clear of the table and of each other */
    uint16_t a[4] = {bt(0, 0), bt(0, 2), bt(1, 0), bt(1, 2)};
    for (int i = 0; i < 4; i++) {
        CHECK(a[i] >= 16 && a[i] + 64 <= 1024 && a[i] % 2 == 0);
        for (int j = 0; j < i; j++) CHECK(a[i] >= a[j] + 64 || a[j] >= a[i] + 64);
    }
    uint8_t b[256];
    CHECK_EQ(control_in(0x80, 6, 0x0100, 0, 64, b), 18);
    CHECK(memcmp(b, usbd_device_desc, 18) == 0);
    bus_reset();
    CHECK_EQ(control_nodata(0x00, 5, 42, 0), 0);
    CHECK_EQ(g_sim.daddr, USB_DADDR_EF | 42);
    CHECK_EQ(control_in(0x80, 6, 0x0200, 0, 255, b), USBD_CONFIG_DESC_LEN);
    CHECK(memcmp(b, usbd_config_desc, USBD_CONFIG_DESC_LEN) == 0);
    CHECK_EQ(control_in(0x80, 6, 0x0303, 0x0409, 255, b), 50);
    CHECK(b[2] == '0' && b[16] == '1' && b[49 - 1] == '3');
    CHECK_EQ(control_in(0x80, 6, 0x0600, 0, 10, b), -1); /* STALL on both directions */
    CHECK_EQ(stat_rx(0), USB_EP_STAT_STALL);
    CHECK_EQ(control_nodata(0x00, 9, 1, 0), 0); /* the next SETUP still works */
    /* endpoint 1 open: interrupt, address 1, OUT valid, IN NAK, toggles 0, 64-byte buffer */
    CHECK_EQ(g_sim.epr[1] & (USB_EP_TYPE | USB_EP_EA), USB_EP_TYPE_INTERRUPT | 1);
    CHECK_EQ(stat_rx(1), USB_EP_STAT_VALID);
    CHECK_EQ(stat_tx(1), USB_EP_STAT_NAK);
    CHECK_EQ(g_sim.epr[1] & (USB_EP_DTOG_RX | USB_EP_DTOG_TX), 0);
    CHECK_EQ(rx_capacity(1), HP_REPORT_SIZE);
    CHECK_EQ(control_nodata(0x21, 0x0A, 0, 0), 0); /* SET_IDLE */

    /* messages over endpoint 1: IDENTIFY -> IDENT on the IN endpoint */
    uint8_t m[64] = {HP_ID_IDENTIFY};
    CHECK_EQ(sie_out(1, m, 64), 0);
    CHECK_EQ(stat_rx(1), USB_EP_STAT_VALID); /* re-armed */
    CHECK_EQ(sie_in(1, b), HP_REPORT_SIZE);
    CHECK_EQ(b[0], HP_ID_IDENT);
    CHECK_EQ(b[HP_IDENT_OFF_MAX_SAMPLES], HP_MAX_SAMPLES);
    CHECK_EQ(sie_in(1, b), HP_REPORT_SIZE); /* protocol v2: the render capabilities follow */
    CHECK_EQ(b[0], HP_ID_CAPS);
    CHECK_EQ(sie_in(1, b), -1); /* nothing more: NAK */
    /* START and samples, then the ticks' STATUS reports */
    m[0] = HP_ID_START;
    CHECK_EQ(sie_out(1, m, 64), 0);
    memset(m, 0, sizeof m);
    m[0] = HP_ID_SAMPLES, m[2] = 7, m[4] = 3, m[5] = 10, m[7] = 20, m[9] = 30;
    CHECK_EQ(sie_out(1, m, 64), 0);
    CHECK_EQ(fw_ring_fill(&f.ring), 3);
    CHECK_EQ(f.state, HP_STATE_RUNNING);
    for (int i = 0; i < 3; i++) fake_us += 333, fw_tick(&f);
    CHECK_EQ(sie_in(1, b), HP_REPORT_SIZE);
    CHECK_EQ(b[0], HP_ID_STATUS);
    CHECK_EQ(b[HP_STATUS_OFF_SAMPLES_PLAYED], 3);
    CHECK_EQ(b[HP_STATUS_OFF_LAST_SEQ], 7);
    CHECK_EQ(b[HP_STATUS_SIZE], 0); /* zero padded */
    /* the host does not poll for 2 ms: one STATUS waits, the newer one is dropped, and an
     * IDENT asked for meanwhile goes out right after the waiting STATUS */
    for (int i = 0; i < 6; i++) fake_us += 333, fw_tick(&f);
    m[0] = HP_ID_IDENTIFY;
    memset(m + 1, 0, 63);
    CHECK_EQ(sie_out(1, m, 64), 0);
    CHECK_EQ(sie_in(1, b), HP_REPORT_SIZE);
    CHECK_EQ(b[0], HP_ID_STATUS);
    CHECK_EQ(sie_in(1, b), HP_REPORT_SIZE);
    CHECK_EQ(b[0], HP_ID_IDENT);
    CHECK_EQ(sie_in(1, b), HP_REPORT_SIZE);
    CHECK_EQ(b[0], HP_ID_CAPS);
    CHECK_EQ(sie_in(1, b), -1);
    /* a SET_REPORT on endpoint 0 reaches the core as well */
    uint8_t p[8] = {0x21, 0x09, 0x00, 0x02, 0, 0, 64, 0};
    sie_setup(p);
    m[0] = HP_ID_STOP;
    CHECK_EQ(sie_out(0, m, 64), 0);
    CHECK_EQ(sie_in(0, b), 0); /* status */
    CHECK_EQ(f.state, HP_STATE_RAMP_DOWN);
    /* ENDPOINT_HALT on the IN endpoint, then cleared: the data toggle restarts at 0 */
    CHECK_EQ(control_nodata(0x02, 3, 0, HP_USB_EP_IN), 0);
    CHECK_EQ(stat_tx(1), USB_EP_STAT_STALL);
    CHECK_EQ(sie_in(1, b), -2);
    g_sim.epr[1] |= USB_EP_DTOG_TX; /* as after some transfers */
    CHECK_EQ(control_nodata(0x02, 1, 0, HP_USB_EP_IN), 0);
    CHECK_EQ(stat_tx(1), USB_EP_STAT_NAK);
    CHECK_EQ(g_sim.epr[1] & USB_EP_DTOG_TX, 0);
    CHECK_EQ(g_sim.irq_masked, 0); /* every masked section was left */
    /* a bus reset closes endpoint 1 and drops the address */
    bus_reset();
    CHECK_EQ(stat_rx(1), USB_EP_STAT_DISABLED);
    CHECK_EQ(sie_out(1, m, 64), -3);
    CHECK_EQ(g_sim.daddr, USB_DADDR_EF);
}

int main(void) {
    test_driver();
    printf("usb driver on a model of the peripheral: %d checks, %d failures\n", g_checks, g_failures);
    return g_failures ? 1 : 0;
}
