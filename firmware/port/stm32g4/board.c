/* STM32G431 board port: clocks, the 3 kHz tick writing the DAC, the encoder, the watchdog,
 * and the hal.h functions of the portable core.
 *
 * Interrupts: the tick (TIM6) has the highest priority and pre-empts the USB interrupt, which
 * delivers messages to the core (fw_on_message); the two share the core through its SPSC ring
 * and atomic fields (fw.h). The main loop only sleeps.
 *
 * Pins (STM32G431KB, LQFP32 / the NUCLEO-G431KB): PA4 DAC1_OUT1 (piezo amplifier input),
 * PA6 TIM3_CH1 = encoder A, PA7 TIM3_CH2 = encoder B (counting), PA0 TIM2_CH1 = encoder A,
 * PA1 TIM2_CH2 = encoder B (edge times), PA11 USB D-, PA12 USB D+, PA13 SWDIO, PA14 SWCLK. */
#include <stdbool.h>

#include "board.h"
#include "hal.h"
#include "regs.h"
#include "tick.h"

static fw_t g_fw;
static board_encoder_t g_enc;
static tick_state_t g_tick; /* the device clock (tick count x 1000 / 3 us) and the encoder */

/* ---- hal.h ---- */
uint32_t hal_time_us(void) { return g_tick.time_us; }

/* The core's codes are signed 16-bit, |code| <= HP_LIMIT_CODE; the 12-bit DAC is offset
 * binary around mid-scale (2048 = rest): code / 8 + 2048, clamped to the DAC's range. */
void hal_dac_write(int16_t code) {
    int32_t v = ((int32_t)code + 16384) >> 3;
    DAC_DHR12R1 = (uint32_t)(v < 0 ? 0 : v > 4095 ? 4095 : v);
}

void hal_send(const uint8_t *msg, size_t len) { usb_fs_send(msg, len); }

__attribute__((weak)) void board_render_tick(fw_t *f, const board_encoder_t *enc) {
    (void)f;
    (void)enc;
}

/* ---- clocks: HSI16 (or HSE) -> PLL 170 MHz; HSI48 trimmed by the CRS on USB SOF ---- */
static void clock_init(void) {
    RCC_APB1ENR1 |= RCC_APB1ENR1_PWREN;
    (void)RCC_APB1ENR1;
    PWR_CR5 &= ~PWR_CR5_R1MODE; /* range 1 boost: needed above 150 MHz (RM0440 6.1.5) */
    while (PWR_SR2 & PWR_SR2_VOSF) {
    }
    FLASH_ACR = (FLASH_ACR & ~FLASH_ACR_LATENCY_Msk) | (4u << FLASH_ACR_LATENCY_Pos) | FLASH_ACR_PRFTEN |
                FLASH_ACR_ICEN | FLASH_ACR_DCEN;
    while ((FLASH_ACR & FLASH_ACR_LATENCY_Msk) != 4u) {
    }
#ifdef BOARD_HSE_HZ /* a crystal: VCO input 4 MHz = HSE / M */
    RCC_CR |= RCC_CR_HSEON;
    while (!(RCC_CR & RCC_CR_HSERDY)) {
    }
    RCC_PLLCFGR = (3u << RCC_PLLCFGR_PLLSRC_Pos) | ((BOARD_HSE_HZ / 4000000u - 1u) << RCC_PLLCFGR_PLLM_Pos) |
                  (85u << RCC_PLLCFGR_PLLN_Pos) | (0u << RCC_PLLCFGR_PLLR_Pos) | RCC_PLLCFGR_PLLREN;
#else /* HSI16 / 4 = 4 MHz, x 85 = 340 MHz VCO, / 2 = 170 MHz */
    RCC_CR |= RCC_CR_HSION;
    while (!(RCC_CR & RCC_CR_HSIRDY)) {
    }
    RCC_PLLCFGR = (2u << RCC_PLLCFGR_PLLSRC_Pos) | (3u << RCC_PLLCFGR_PLLM_Pos) | (85u << RCC_PLLCFGR_PLLN_Pos) |
                  (0u << RCC_PLLCFGR_PLLR_Pos) | RCC_PLLCFGR_PLLREN;
#endif
    RCC_CR |= RCC_CR_PLLON;
    while (!(RCC_CR & RCC_CR_PLLRDY)) {
    }
    /* above 80 MHz: switch with AHB / 2 first, wait 1 us, then AHB / 1 (RM0440 7.2.7) */
    RCC_CFGR = (RCC_CFGR & ~(0xFu << RCC_CFGR_HPRE_Pos)) | (8u << RCC_CFGR_HPRE_Pos);
    RCC_CFGR = (RCC_CFGR & ~(3u << RCC_CFGR_SW_Pos)) | (3u << RCC_CFGR_SW_Pos);
    while (((RCC_CFGR >> RCC_CFGR_SWS_Pos) & 3u) != 3u) {
    }
    for (volatile int i = 0; i < 200; i++) {
    }
    RCC_CFGR &= ~((0xFu << RCC_CFGR_HPRE_Pos) | (7u << RCC_CFGR_PPRE1_Pos) | (7u << RCC_CFGR_PPRE2_Pos));
    /* 48 MHz for USB from HSI48, kept on frequency by the CRS against the host's 1 ms SOF */
    RCC_CRRCR |= RCC_CRRCR_HSI48ON;
    while (!(RCC_CRRCR & RCC_CRRCR_HSI48RDY)) {
    }
    RCC_CCIPR &= ~(3u << RCC_CCIPR_CLK48SEL_Pos); /* 00: HSI48 */
    RCC_APB1ENR1 |= RCC_APB1ENR1_CRSEN;
    (void)RCC_APB1ENR1;
    CRS_CFGR = (CRS_CFGR & ~(3u << CRS_CFGR_SYNCSRC_Pos)) | (2u << CRS_CFGR_SYNCSRC_Pos);
    CRS_CR |= CRS_CR_AUTOTRIMEN | CRS_CR_CEN;
}

static void gpio_af(unsigned pin, unsigned af) {
    GPIOA_MODER = (GPIOA_MODER & ~(3u << (2 * pin))) | (2u << (2 * pin));
    volatile uint32_t *afr = pin < 8 ? &GPIOA_AFRL : &GPIOA_AFRH;
    unsigned sh = 4 * (pin % 8);
    *afr = (*afr & ~(0xFu << sh)) | (af << sh);
}

static void io_init(void) {
    RCC_AHB2ENR |= RCC_AHB2ENR_GPIOAEN | RCC_AHB2ENR_DAC1EN;
    RCC_APB1ENR1 |= RCC_APB1ENR1_TIM2EN | RCC_APB1ENR1_TIM3EN | RCC_APB1ENR1_TIM6EN;
    (void)RCC_APB1ENR1;
    /* PA13 / PA14 (SWD) keep their reset configuration */
    GPIOA_MODER |= 3u << (2 * 4); /* PA4 analog: DAC1_OUT1 */
    gpio_af(0, 1);                /* PA0 TIM2_CH1 */
    gpio_af(1, 1);                /* PA1 TIM2_CH2 */
    gpio_af(6, 2);                /* PA6 TIM3_CH1 */
    gpio_af(7, 2);                /* PA7 TIM3_CH2 */

    /* DAC1 channel 1, buffered, to the pin; mid-scale (rest) before it is switched on */
    DAC_MCR = (2u << DAC_MCR_HFSEL_Pos) | (0u << DAC_MCR_MODE1_Pos); /* AHB > 160 MHz */
    DAC_DHR12R1 = 2048u;
    DAC_CR = DAC_CR_EN1;
    while (!(DAC_SR & DAC_SR_DAC1RDY)) {
    }

    /* TIM3: x4 quadrature counting of A/B, 8-sample input filter (47 ns) */
    TIM_SMCR(TIM3_BASE) = TIM_SMCR_SMS_ENC3;
    TIM_CCMR1(TIM3_BASE) = TIM_CCMR1_CC1S_TI1 | TIM_CCMR1_CC2S_TI2 | (3u << TIM_CCMR1_IC1F_Pos) |
                           (3u << TIM_CCMR1_IC2F_Pos);
    TIM_CCER(TIM3_BASE) = 0; /* both inputs non-inverted */
    TIM_ARR(TIM3_BASE) = 0xFFFFu;
    TIM_CR1(TIM3_BASE) = TIM_CR1_CEN;
    g_tick.enc_last = (uint16_t)TIM_CNT(TIM3_BASE);

    /* TIM2: free-running 32-bit at 170 MHz; CC1 / CC2 capture both edges of A / B */
    TIM_PSC(TIM2_BASE) = 0;
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_CCMR1(TIM2_BASE) = TIM_CCMR1_CC1S_TI1 | TIM_CCMR1_CC2S_TI2 | (3u << TIM_CCMR1_IC1F_Pos) |
                           (3u << TIM_CCMR1_IC2F_Pos);
    TIM_CCER(TIM2_BASE) = TIM_CCER_CC1E | TIM_CCER_CC1P | TIM_CCER_CC1NP | TIM_CCER_CC2E | TIM_CCER_CC2P |
                          TIM_CCER_CC2NP;
    TIM_EGR(TIM2_BASE) = TIM_EGR_UG;
    TIM_CR1(TIM2_BASE) = TIM_CR1_CEN;

    /* TIM6: the 3 kHz tick. 170 MHz / 3 kHz = 56666.67 cycles: periods of 56666, 56667,
     * 56667 (ARR preloaded, so the ISR sets the one after next) average exactly 3 kHz. */
    TIM_PSC(TIM6_BASE) = 0;
    TIM_ARR(TIM6_BASE) = 56666u - 1u;
    TIM_CR1(TIM6_BASE) = TIM_CR1_ARPE | TIM_CR1_URS;
    TIM_EGR(TIM6_BASE) = TIM_EGR_UG;
    TIM_SR(TIM6_BASE) = 0;
    TIM_DIER(TIM6_BASE) = TIM_DIER_UIE;
}

_Static_assert(BOARD_SYSCLK_HZ / HP_SAMPLE_RATE_HZ == TICK_PERIOD_SHORT && (BOARD_SYSCLK_HZ % HP_SAMPLE_RATE_HZ) * 3u == 2u * HP_SAMPLE_RATE_HZ,
               "the tick's period pattern assumes 170 MHz / 3 kHz = 56666 + 2/3");

/* The watchdog: LSI 32 kHz / 4 = 8 kHz, 80 counts = 10 ms; refreshed by every tick. */
static void watchdog_init(void) {
    DBGMCU_APB1FZR1 |= DBGMCU_APB1FZR1_DBG_IWDG_STOP | DBGMCU_APB1FZR1_DBG_TIM6_STOP;
    IWDG_KR = IWDG_KR_START;
    IWDG_KR = IWDG_KR_UNLOCK;
    IWDG_PR = 0;
    IWDG_RLR = 80u - 1u;
    while (IWDG_SR != 0) {
    }
    IWDG_KR = IWDG_KR_RELOAD;
}

void TIM6_DAC_IRQHandler(void) {
    TIM_SR(TIM6_BASE) = ~TIM_SR_UIF;
    TIM_ARR(TIM6_BASE) = tick_advance(&g_tick);
    g_enc.count = tick_encoder(&g_tick, (uint16_t)TIM_CNT(TIM3_BASE));
    g_enc.tick_cycles = TIM_CNT(TIM2_BASE);
    g_enc.edge_a_cycles = TIM_CCR1(TIM2_BASE);
    g_enc.edge_b_cycles = TIM_CCR2(TIM2_BASE);
    if (TIM_SR(TIM3_BASE) & TIM_SR_TERRF) { /* both inputs changed at once: a lost edge */
        TIM_SR(TIM3_BASE) = ~TIM_SR_TERRF;
        g_enc.transition_errors++;
        g_fw.quad.errors++;
        g_fw.faults |= HP_FAULT_ENCODER;
    }
    g_fw.quad.count = g_enc.count;

    board_render_tick(&g_fw, &g_enc);
    fw_tick(&g_fw);
    IWDG_KR = IWDG_KR_RELOAD;
}

static void read_uid(uint32_t uid[3]) {
    for (unsigned i = 0; i < 3; i++) {
        uid[i] = REG32(UID_BASE + 4u * i);
    }
}

int main(void) {
    clock_init();
    io_init();
    fw_init(&g_fw, 0);
    uint32_t uid[3];
    read_uid(uid);
    usb_fs_init(&g_fw, uid);
    watchdog_init();
    /* priorities (4 bits, upper nibble): the tick above USB */
    NVIC_IPR8(IRQ_TIM6_DAC) = 0x00;
    NVIC_IPR8(IRQ_USB_LP) = 0x40;
    NVIC_ISER(IRQ_TIM6_DAC / 32) = 1u << (IRQ_TIM6_DAC % 32);
    NVIC_ISER(IRQ_USB_LP / 32) = 1u << (IRQ_USB_LP % 32);
    TIM_CR1(TIM6_BASE) |= TIM_CR1_CEN;
    for (;;) {
        __asm volatile("wfi");
    }
}
