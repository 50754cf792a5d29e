/* Hardware abstraction: what the core (fw.c) asks of a board. One implementation per target
 * (hal/avr/hal_avr.c, hal/posix/main.c, the unit tests' fake in test/test_core.c).
 *
 * Chambers are numbered 0..n-1 in the protocol's order (the first three values of a CMD are
 * chamber 0's, the first pressure of a P line is chamber 0's). Valve calls are logical (open or
 * closed); the board maps them to pin levels (a normally open outlet is open when unpowered). */
#ifndef HBMA_HAL_H
#define HBMA_HAL_H

#include <stdint.h>

/* Enter/leave a section the timer interrupt must not split (nestable is not required). */
void hal_crit_enter(void);
void hal_crit_exit(void);

/* Queue len bytes for the UART, all or none (a full transmit buffer): returns len or 0. */
uint16_t hal_uart_write(const char *buf, uint16_t len);

/* Pump of chamber ch at speed permille 0..1000 (0 = off). */
void hal_pump(uint8_t ch, uint16_t permille);

/* Valve of chamber ch: which = 0 inlet, 1 outlet; open = 1 open, 0 closed. */
void hal_valve(uint8_t ch, uint8_t which, uint8_t open);

/* The newest ADC reading of chamber ch's pressure sensor, in the board's counts (fw_cal_t's scale). */
uint16_t hal_adc(uint8_t ch);

/* Non-volatile memory: read or write len bytes at addr. */
void hal_nvm_read(uint16_t addr, void *buf, uint16_t len);
void hal_nvm_write(uint16_t addr, const void *buf, uint16_t len);

#endif
