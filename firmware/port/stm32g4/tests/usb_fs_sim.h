/* Included by usb_fs.c when built with -DUSB_FS_SIM (tests/test_usb_fs.c): the USB
 * peripheral's registers and packet memory become a model in host memory. EPnR and ISTR
 * writes go to functions that apply the hardware's write semantics. */
#ifndef HOSTD_USB_FS_SIM_H
#define HOSTD_USB_FS_SIM_H

#include <stdint.h>

typedef struct {
    uint16_t epr[8];
    uint16_t istr_flags; /* RESET, SUSP, ... (CTR, EP_ID and DIR are computed from epr) */
    uint16_t cntr, daddr, btable, bcdr;
    uint16_t pma[512]; /* 1 KiB, 16-bit words */
    uint32_t rcc_apb1enr1;
    int irq_masked;
} usb_sim_t;

extern usb_sim_t g_sim;
void sim_epr_write(unsigned ep, uint16_t v);
void sim_istr_write(uint16_t v);
uint16_t sim_istr_read(void);

static inline uint32_t irq_save(void) {
    uint32_t p = (uint32_t)g_sim.irq_masked;
    g_sim.irq_masked = 1;
    return p;
}
static inline void irq_restore(uint32_t p) { g_sim.irq_masked = (int)p; }
static inline uint16_t epr_get(unsigned ep) { return g_sim.epr[ep]; }
static inline void epr_set(unsigned ep, uint16_t v) { sim_epr_write(ep, v); }
static inline void istr_write(uint16_t v) { sim_istr_write(v); }

#undef USB_ISTR
#define USB_ISTR (sim_istr_read())
#undef USB_CNTR
#define USB_CNTR (g_sim.cntr)
#undef USB_DADDR
#define USB_DADDR (g_sim.daddr)
#undef USB_BTABLE
#define USB_BTABLE (g_sim.btable)
#undef USB_BCDR
#define USB_BCDR (g_sim.bcdr)
#undef USB_PMA16
#define USB_PMA16(off) (g_sim.pma[(off) / 2u])
#undef RCC_APB1ENR1
#define RCC_APB1ENR1 (g_sim.rcc_apb1enr1)

#endif
