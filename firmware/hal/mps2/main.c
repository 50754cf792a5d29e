/* The firmware on a Cortex-M MPS2 board as QEMU emulates it (mps2-an500: a Cortex-M7 at 25 MHz), hosting
 * the chamber library (FW_HOSTED). UART0 is the CMSDK APB UART at 0x40004000 (QEMU's -serial), polled;
 * SysTick is the core's tick (FW_TICK_US); the sensors read a fixed pressure (FW_FIXED_PA, Pa: this board
 * has no plant), the pump and valve outputs are kept in variables, and the NVM is RAM (the defaults at
 * every boot). Its own start-up: the vector table with SysTick, the FPU on, .data copied and .bss
 * cleared. Built by `make -C firmware mps2 LIB=DIR` with arm-none-eabi-gcc and the library's linker
 * script; run with qemu-system-arm -M mps2-an500 -nographic -serial pty (or stdio). */
#include <stdint.h>
#include <string.h>

#include "fw.h"
#include "hal.h"

#ifndef FW_CPU_HZ
#define FW_CPU_HZ 25000000u /* the MPS2 boards' SysTick and APB clock */
#endif
#ifndef FW_BAUD
#define FW_BAUD 115200u
#endif
#ifndef FW_TICK_US
#define FW_TICK_US 100u
#endif
#ifndef FW_PERIOD_TICKS
#define FW_PERIOD_TICKS 100u
#endif
#ifndef FW_FIXED_PA
#define FW_FIXED_PA 10000 /* what every sensor reads, Pa */
#endif

typedef struct {
    volatile uint32_t data, state, ctrl, intstatus, bauddiv;
} cmsdk_uart_t;
#define UART0 ((cmsdk_uart_t *)0x40004000u)
#define UART_TX_FULL 1u
#define UART_RX_FULL 2u
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define CPACR (*(volatile uint32_t *)0xE000ED88u)

static fw_t fw;
static uint16_t pump_out[FW_MAX_N];
static uint8_t valve_out[FW_MAX_N][2];
static uint8_t nvm[64 * FW_NVM_BYTES_PER_CH];
static uint32_t crit_depth;

void hal_crit_enter(void) {
    __asm__ volatile("cpsid i" ::: "memory");
    crit_depth++;
}

void hal_crit_exit(void) {
    if (--crit_depth == 0) __asm__ volatile("cpsie i" ::: "memory");
}

uint16_t hal_uart_write(const char *buf, uint16_t len) {
    for (uint16_t i = 0; i < len; i++) {
        while (UART0->state & UART_TX_FULL) {
        }
        UART0->data = (uint8_t)buf[i];
    }
    return len;
}

void hal_pump(uint8_t ch, uint16_t permille) { pump_out[ch] = permille; }
void hal_valve(uint8_t ch, uint8_t which, uint8_t open) { valve_out[ch][which] = open; }

uint16_t hal_adc(uint8_t ch) {
    (void)ch;
    return (uint16_t)(FW_CAL_ZERO + (int32_t)FW_FIXED_PA * 1000 / FW_CAL_GAIN);
}

void hal_nvm_read(uint16_t addr, void *buf, uint16_t len) {
    if ((uint32_t)addr + len <= sizeof nvm) memcpy(buf, nvm + addr, len);
}

void hal_nvm_write(uint16_t addr, const void *buf, uint16_t len) {
    if ((uint32_t)addr + len <= sizeof nvm) memcpy(nvm + addr, buf, len);
}

/* ---- start-up ---------------------------------------------------------------------------------- */

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
void Reset_Handler(void);
void Fault_Handler(void);
void SysTick_Handler(void);
int main(void);

/* the table's first word is the initial stack pointer, the others handlers */
typedef union {
    void *sp;
    void (*handler)(void);
} vector_t;
#define H(f) {.handler = f}
__attribute__((section(".isr_vector"), used)) const vector_t vectors[16] = {
    {.sp = &_estack}, H(Reset_Handler), H(Fault_Handler), H(Fault_Handler), H(Fault_Handler), H(Fault_Handler),
    H(Fault_Handler), {0}, {0}, {0}, {0}, H(Fault_Handler), H(Fault_Handler), {0}, H(Fault_Handler),
    H(SysTick_Handler)};

void Fault_Handler(void) {
    for (;;) {
    }
}

void SysTick_Handler(void) { fw_tick(&fw); }

void Reset_Handler(void) {
    CPACR |= 0xFu << 20; /* full access to CP10 and CP11: the FPU */
    __asm__ volatile("dsb\n isb");
    uint32_t *src = &_sidata;
    for (uint32_t *dst = &_sdata; dst < &_edata;) *dst++ = *src++;
    for (uint32_t *dst = &_sbss; dst < &_ebss;) *dst++ = 0;
    main();
    for (;;) {
    }
}

int main(void) {
    memset(nvm, 0xFF, sizeof nvm); /* blank: the default calibration */
    fw_cfg_t cfg = {1, FW_TICK_US, FW_PERIOD_TICKS, 0, 0};
    uint32_t period_us = cfg.tick_us * cfg.period_ticks;
    cfg.hb_periods = (uint16_t)((100000u + period_us - 1u) / period_us); /* every 0.1 s */
    cfg.timeout_ticks = 500000u / cfg.tick_us;                           /* 0.5 s */
    UART0->bauddiv = FW_CPU_HZ / FW_BAUD;
    UART0->ctrl = 3u; /* transmit and receive on */
    fw_init(&fw, &cfg);
    SYST_RVR = FW_CPU_HZ / 1000000u * FW_TICK_US - 1u;
    SYST_CVR = 0;
    SYST_CSR = 7u; /* the processor clock, the interrupt, on */
    for (;;) {
        while (UART0->state & UART_RX_FULL) fw_rx_byte(&fw, (uint8_t)UART0->data);
        fw_poll(&fw);
    }
}
