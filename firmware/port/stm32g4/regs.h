/* STM32G431 register definitions for the peripherals this port uses, written from the
 * reference manual RM0440 (rev 8) and named after it: <PERIPH>_<REGISTER> for registers,
 * <PERIPH>_<REGISTER>_<FIELD> for bits (positions as in the manual's register maps), and
 * the Cortex-M4 core registers from the ARMv7-M Architecture Reference Manual. */
#ifndef HOSTD_STM32G4_REGS_H
#define HOSTD_STM32G4_REGS_H

#include <stdint.h>

#define REG32(a) (*(volatile uint32_t *)(uintptr_t)(a))
#define REG16(a) (*(volatile uint16_t *)(uintptr_t)(a))

/* ---- memory map (RM0440 section 2.2.2) ---- */
#define FLASH_BASE_ADDR 0x08000000u
#define SRAM_BASE_ADDR 0x20000000u
#define APB1_BASE 0x40000000u
#define AHB1_BASE 0x40020000u
#define AHB2_BASE 0x48000000u
#define TIM2_BASE 0x40000000u
#define TIM3_BASE 0x40000400u
#define TIM6_BASE 0x40001000u
#define CRS_BASE 0x40002000u
#define IWDG_BASE 0x40003000u
#define USB_BASE 0x40005C00u
#define USB_PMA_BASE 0x40006000u /* 1 KiB packet memory, 16-bit accesses */
#define PWR_BASE 0x40007000u
#define RCC_BASE 0x40021000u
#define FLASH_R_BASE 0x40022000u
#define GPIOA_BASE 0x48000000u
#define DAC1_BASE 0x50000800u
#define DBGMCU_BASE 0xE0042000u
#define UID_BASE 0x1FFF7590u /* 96-bit unique device ID (section 48.1) */

/* ---- RCC: reset and clock control (chapter 7) ---- */
#define RCC_CR REG32(RCC_BASE + 0x00)
#define RCC_CR_HSION (1u << 8)
#define RCC_CR_HSIRDY (1u << 10)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_CFGR REG32(RCC_BASE + 0x08)
#define RCC_CFGR_SW_Pos 0     /* 01 HSI16, 10 HSE, 11 PLL */
#define RCC_CFGR_SWS_Pos 2
#define RCC_CFGR_HPRE_Pos 4   /* AHB prescaler: 0xxx /1, 1000 /2 */
#define RCC_CFGR_PPRE1_Pos 8  /* APB1 prescaler: 0xx /1 */
#define RCC_CFGR_PPRE2_Pos 11 /* APB2 prescaler: 0xx /1 */
#define RCC_PLLCFGR REG32(RCC_BASE + 0x0C)
#define RCC_PLLCFGR_PLLSRC_Pos 0 /* 10 HSI16, 11 HSE */
#define RCC_PLLCFGR_PLLM_Pos 4   /* division factor M - 1 */
#define RCC_PLLCFGR_PLLN_Pos 8   /* multiplication factor N */
#define RCC_PLLCFGR_PLLREN (1u << 24)
#define RCC_PLLCFGR_PLLR_Pos 25 /* 00 /2, 01 /4, 10 /6, 11 /8 */
#define RCC_AHB2ENR REG32(RCC_BASE + 0x4C)
#define RCC_AHB2ENR_GPIOAEN (1u << 0)
#define RCC_AHB2ENR_DAC1EN (1u << 16)
#define RCC_APB1ENR1 REG32(RCC_BASE + 0x58)
#define RCC_APB1ENR1_TIM2EN (1u << 0)
#define RCC_APB1ENR1_TIM3EN (1u << 1)
#define RCC_APB1ENR1_TIM6EN (1u << 4)
#define RCC_APB1ENR1_CRSEN (1u << 8)
#define RCC_APB1ENR1_USBEN (1u << 23)
#define RCC_APB1ENR1_PWREN (1u << 28)
#define RCC_CCIPR REG32(RCC_BASE + 0x88)
#define RCC_CCIPR_CLK48SEL_Pos 26 /* 00 HSI48 */
#define RCC_CSR REG32(RCC_BASE + 0x94)
#define RCC_CSR_LSION (1u << 0)
#define RCC_CSR_LSIRDY (1u << 1)
#define RCC_CSR_RMVF (1u << 23)
#define RCC_CSR_IWDGRSTF (1u << 29)
#define RCC_CRRCR REG32(RCC_BASE + 0x98)
#define RCC_CRRCR_HSI48ON (1u << 0)
#define RCC_CRRCR_HSI48RDY (1u << 1)

/* ---- PWR (chapter 6): range 1 boost mode for 170 MHz ---- */
#define PWR_CR1 REG32(PWR_BASE + 0x00)
#define PWR_SR2 REG32(PWR_BASE + 0x14)
#define PWR_SR2_VOSF (1u << 10)
#define PWR_CR5 REG32(PWR_BASE + 0x80)
#define PWR_CR5_R1MODE (1u << 8) /* 0: range 1 boost mode */

/* ---- FLASH (chapter 5) ---- */
#define FLASH_ACR REG32(FLASH_R_BASE + 0x00)
#define FLASH_ACR_LATENCY_Pos 0 /* wait states: 4 at 170 MHz in boost mode (table 29) */
#define FLASH_ACR_LATENCY_Msk (0xFu << 0)
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_ACR_DCEN (1u << 10)

/* ---- CRS: clock recovery system (chapter 8), HSI48 trimmed on the USB SOF ---- */
#define CRS_CR REG32(CRS_BASE + 0x00)
#define CRS_CR_CEN (1u << 5)
#define CRS_CR_AUTOTRIMEN (1u << 6)
#define CRS_CFGR REG32(CRS_BASE + 0x04)
#define CRS_CFGR_SYNCSRC_Pos 28 /* 10: USB SOF (the reset value) */

/* ---- GPIO (chapter 9) ---- */
#define GPIOA_MODER REG32(GPIOA_BASE + 0x00) /* 00 input, 01 output, 10 alternate, 11 analog */
#define GPIOA_OSPEEDR REG32(GPIOA_BASE + 0x08)
#define GPIOA_PUPDR REG32(GPIOA_BASE + 0x0C)
#define GPIOA_IDR REG32(GPIOA_BASE + 0x10)
#define GPIOA_AFRL REG32(GPIOA_BASE + 0x20)
#define GPIOA_AFRH REG32(GPIOA_BASE + 0x24)

/* ---- general-purpose timers TIM2 (32-bit) and TIM3 (16-bit), basic timer TIM6 (chapters 29, 31) ---- */
#define TIM_CR1(b) REG32((b) + 0x00)
#define TIM_CR1_CEN (1u << 0)
#define TIM_CR1_URS (1u << 2)
#define TIM_CR1_ARPE (1u << 7)
#define TIM_SMCR(b) REG32((b) + 0x08)
#define TIM_SMCR_SMS_ENC3 3u /* encoder mode 3: counts on both TI1 and TI2 edges (x4) */
#define TIM_DIER(b) REG32((b) + 0x0C)
#define TIM_DIER_UIE (1u << 0)
#define TIM_SR(b) REG32((b) + 0x10)
#define TIM_SR_UIF (1u << 0)
#define TIM_SR_CC1IF (1u << 1)
#define TIM_SR_CC2IF (1u << 2)
#define TIM_SR_CC1OF (1u << 9)
#define TIM_SR_CC2OF (1u << 10)
#define TIM_SR_TERRF (1u << 23) /* encoder transition error: both inputs changed at once */
#define TIM_EGR(b) REG32((b) + 0x14)
#define TIM_EGR_UG (1u << 0)
#define TIM_CCMR1(b) REG32((b) + 0x18)
#define TIM_CCMR1_CC1S_TI1 (1u << 0) /* CC1 is an input mapped on TI1 */
#define TIM_CCMR1_CC2S_TI2 (1u << 8) /* CC2 is an input mapped on TI2 */
#define TIM_CCMR1_IC1F_Pos 4
#define TIM_CCMR1_IC2F_Pos 12
#define TIM_CCER(b) REG32((b) + 0x20)
#define TIM_CCER_CC1E (1u << 0)
#define TIM_CCER_CC1P (1u << 1)
#define TIM_CCER_CC1NP (1u << 3)
#define TIM_CCER_CC2E (1u << 4)
#define TIM_CCER_CC2P (1u << 5)
#define TIM_CCER_CC2NP (1u << 7)
#define TIM_CNT(b) REG32((b) + 0x24)
#define TIM_PSC(b) REG32((b) + 0x28)
#define TIM_ARR(b) REG32((b) + 0x2C)
#define TIM_CCR1(b) REG32((b) + 0x34)
#define TIM_CCR2(b) REG32((b) + 0x38)
#define TIM_ECR(b) REG32((b) + 0x58)

/* ---- DAC1 (chapter 22) ---- */
#define DAC_CR REG32(DAC1_BASE + 0x00)
#define DAC_CR_EN1 (1u << 0)
#define DAC_DHR12R1 REG32(DAC1_BASE + 0x08)
#define DAC_SR REG32(DAC1_BASE + 0x34)
#define DAC_SR_DAC1RDY (1u << 11)
#define DAC_MCR REG32(DAC1_BASE + 0x3C)
#define DAC_MCR_MODE1_Pos 0   /* 000: normal mode, external pin with buffer */
#define DAC_MCR_HFSEL_Pos 14  /* high-frequency interface: 10 for AHB > 160 MHz */

/* ---- IWDG: independent watchdog (chapter 42), on the 32 kHz LSI ---- */
#define IWDG_KR REG32(IWDG_BASE + 0x00)
#define IWDG_KR_START 0xCCCCu
#define IWDG_KR_RELOAD 0xAAAAu
#define IWDG_KR_UNLOCK 0x5555u
#define IWDG_PR REG32(IWDG_BASE + 0x04)
#define IWDG_RLR REG32(IWDG_BASE + 0x08)
#define IWDG_SR REG32(IWDG_BASE + 0x0C)

/* ---- USB full-speed device (chapter 45): 16-bit registers on 32-bit addresses ---- */
#define USB_EPR(n) REG16(USB_BASE + 4u * (n))
#define USB_EP_CTR_RX 0x8000u
#define USB_EP_DTOG_RX 0x4000u
#define USB_EP_STAT_RX 0x3000u
#define USB_EP_SETUP 0x0800u
#define USB_EP_TYPE 0x0600u
#define USB_EP_TYPE_CONTROL 0x0200u
#define USB_EP_TYPE_INTERRUPT 0x0600u
#define USB_EP_KIND 0x0100u
#define USB_EP_CTR_TX 0x0080u
#define USB_EP_DTOG_TX 0x0040u
#define USB_EP_STAT_TX 0x0030u
#define USB_EP_EA 0x000Fu
#define USB_EP_STAT_DISABLED 0u
#define USB_EP_STAT_STALL 1u
#define USB_EP_STAT_NAK 2u
#define USB_EP_STAT_VALID 3u
/* bits kept as read by a write (the toggle bits are written 0 = unchanged) */
#define USB_EP_KEEP (USB_EP_CTR_RX | USB_EP_SETUP | USB_EP_TYPE | USB_EP_KIND | USB_EP_CTR_TX | USB_EP_EA)
#define USB_CNTR REG16(USB_BASE + 0x40)
#define USB_CNTR_FRES 0x0001u
#define USB_CNTR_PDWN 0x0002u
#define USB_CNTR_RESETM 0x0400u
#define USB_CNTR_CTRM 0x8000u
#define USB_ISTR REG16(USB_BASE + 0x44)
#define USB_ISTR_EP_ID 0x000Fu
#define USB_ISTR_DIR 0x0010u
#define USB_ISTR_SOF 0x0200u
#define USB_ISTR_RESET 0x0400u
#define USB_ISTR_SUSP 0x0800u
#define USB_ISTR_WKUP 0x1000u
#define USB_ISTR_ERR 0x2000u
#define USB_ISTR_PMAOVR 0x4000u
#define USB_ISTR_CTR 0x8000u
#define USB_DADDR REG16(USB_BASE + 0x4C)
#define USB_DADDR_EF 0x0080u
#define USB_BTABLE REG16(USB_BASE + 0x50)
#define USB_BCDR REG16(USB_BASE + 0x58)
#define USB_BCDR_DPPU 0x8000u /* D+ pull-up: connect */
#define USB_PMA16(off) REG16(USB_PMA_BASE + (off))
/* buffer descriptor table entry of endpoint n (at BTABLE = 0) */
#define USB_ADDR_TX(n) USB_PMA16(8u * (n) + 0u)
#define USB_COUNT_TX(n) USB_PMA16(8u * (n) + 2u)
#define USB_ADDR_RX(n) USB_PMA16(8u * (n) + 4u)
#define USB_COUNT_RX(n) USB_PMA16(8u * (n) + 6u)
#define USB_COUNT_RX_BL32_2 0x8400u /* BL_SIZE = 1 (32-byte blocks), NUM_BLOCK = 1: 64 bytes */
#define USB_COUNT_RX_COUNT 0x03FFu

/* ---- DBGMCU (chapter 47): stop the watchdog and the tick while the core is halted ---- */
#define DBGMCU_APB1FZR1 REG32(DBGMCU_BASE + 0x08)
#define DBGMCU_APB1FZR1_DBG_TIM6_STOP (1u << 4)
#define DBGMCU_APB1FZR1_DBG_IWDG_STOP (1u << 12)

/* ---- Cortex-M4 core (ARMv7-M ARM, B3) ---- */
#define SCB_VTOR REG32(0xE000ED08u)
#define SCB_CPACR REG32(0xE000ED88u)
#define SCB_AIRCR REG32(0xE000ED0Cu)
#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n))
#define NVIC_IPR8(irq) (*(volatile uint8_t *)(uintptr_t)(0xE000E400u + (irq)))

/* interrupt numbers (RM0440 table 97) */
#define IRQ_USB_LP 20
#define IRQ_TIM6_DAC 54
#define IRQ_COUNT 102

#endif
