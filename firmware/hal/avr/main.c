/* The firmware on an AVR board: ATmega328P (Arduino Uno) or ATmega2560 (Arduino Mega), 16 MHz.
 * UART0 at FW_BAUD (interrupt driven, ring buffers), Timer1 CTC interrupt every FW_TICK_US (the
 * core's tick), Timer0/Timer2 hardware PWM for the pumps (976 Hz), valves on plain GPIO switched by
 * the tick (software PWM, period = the sample period), ADC free-running round robin by interrupt
 * (16 conversions summed per reading: counts 0..16368), calibration in EEPROM, and the hardware
 * watchdog (a hung main loop resets the chip: every pin then floats, which is the safe state with the
 * wiring in firmware/README.md). Pinout: firmware/README.md. */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>

#include "fw.h"
#include "hal.h"

#ifndef F_CPU
#define F_CPU 16000000UL
#endif
#ifndef FW_BAUD
#define FW_BAUD 115200UL
#endif
#ifndef FW_TICK_US
#define FW_TICK_US 100 /* 10 kHz tick */
#endif
#ifndef FW_PERIOD_TICKS
#define FW_PERIOD_TICKS 100 /* 10 ms sample period */
#endif
#ifndef FW_OUTLET_NO
#define FW_OUTLET_NO 1 /* outlets normally open: energised (pin high) = closed */
#endif
#define RING 128 /* bytes, a power of two */

typedef struct {
    volatile uint8_t *port, *ddr;
    uint8_t mask;
} pin_t;

typedef struct {
    volatile uint8_t *ocr, *tccr;
    uint8_t com; /* COMxn1 bit: connects the pin to the timer */
    pin_t pin;
} pwm_t;

#if defined(__AVR_ATmega2560__)
/* Mega: pumps D13 (OC0A), D4 (OC0B), D10 (OC2A), D9 (OC2B); inlets D22..D25 (PA0..3), outlets
 * D26..D29 (PA4..7); sensors A0..A3 */
static const pwm_t pumps[4] = {{&OCR0A, &TCCR0A, COM0A1, {&PORTB, &DDRB, 1 << 7}},
                               {&OCR0B, &TCCR0A, COM0B1, {&PORTG, &DDRG, 1 << 5}},
                               {&OCR2A, &TCCR2A, COM2A1, {&PORTB, &DDRB, 1 << 4}},
                               {&OCR2B, &TCCR2A, COM2B1, {&PORTH, &DDRH, 1 << 6}}};
static const pin_t valves[4][2] = {{{&PORTA, &DDRA, 1 << 0}, {&PORTA, &DDRA, 1 << 4}},
                                   {{&PORTA, &DDRA, 1 << 1}, {&PORTA, &DDRA, 1 << 5}},
                                   {{&PORTA, &DDRA, 1 << 2}, {&PORTA, &DDRA, 1 << 6}},
                                   {{&PORTA, &DDRA, 1 << 3}, {&PORTA, &DDRA, 1 << 7}}};
#else
/* Uno: pumps D6 (OC0A), D5 (OC0B), D11 (OC2A), D3 (OC2B); inlets D2, D4, D7, D8; outlets D9, D10,
 * D12, D13; sensors A0..A3 */
static const pwm_t pumps[4] = {{&OCR0A, &TCCR0A, COM0A1, {&PORTD, &DDRD, 1 << 6}},
                               {&OCR0B, &TCCR0A, COM0B1, {&PORTD, &DDRD, 1 << 5}},
                               {&OCR2A, &TCCR2A, COM2A1, {&PORTB, &DDRB, 1 << 3}},
                               {&OCR2B, &TCCR2A, COM2B1, {&PORTD, &DDRD, 1 << 3}}};
static const pin_t valves[4][2] = {{{&PORTD, &DDRD, 1 << 2}, {&PORTB, &DDRB, 1 << 1}},
                                   {{&PORTD, &DDRD, 1 << 4}, {&PORTB, &DDRB, 1 << 2}},
                                   {{&PORTD, &DDRD, 1 << 7}, {&PORTB, &DDRB, 1 << 4}},
                                   {{&PORTB, &DDRB, 1 << 0}, {&PORTB, &DDRB, 1 << 5}}};
#endif

#if defined(USART0_RX_vect) /* the Mega's four UARTs are numbered */
#define UART_RX_VECT USART0_RX_vect
#define UART_UDRE_VECT USART0_UDRE_vect
#else
#define UART_RX_VECT USART_RX_vect
#define UART_UDRE_VECT USART_UDRE_vect
#endif

#if FW_MAX_N > 4
#error "the AVR boards have pins for 4 chambers"
#endif

static fw_t fw;
static volatile uint8_t rx_ring[RING], tx_ring[RING];
static volatile uint8_t rx_head, rx_tail, tx_head, tx_tail;
static volatile uint16_t adc_val[FW_MAX_N];
static uint8_t sreg_saved;

void hal_crit_enter(void) {
    sreg_saved = SREG;
    cli();
}

void hal_crit_exit(void) { SREG = sreg_saved; }

uint16_t hal_uart_write(const char *buf, uint16_t len) {
    uint8_t used = (uint8_t)(tx_head - tx_tail); /* 8-bit indices wrap with the ring */
    if (len > (uint16_t)(RING - 1u - (used & (RING - 1u)))) return 0;
    for (uint16_t i = 0; i < len; i++) {
        tx_ring[tx_head & (RING - 1u)] = (uint8_t)buf[i];
        tx_head++;
    }
    UCSR0B |= (1 << UDRIE0);
    return len;
}

ISR(UART_UDRE_VECT) {
    if (tx_head == tx_tail) {
        UCSR0B &= (uint8_t)~(1 << UDRIE0);
    } else {
        UDR0 = tx_ring[tx_tail & (RING - 1u)];
        tx_tail++;
    }
}

ISR(UART_RX_VECT) {
    uint8_t c = UDR0;
    if ((uint8_t)(rx_head - rx_tail) < RING) { /* else lost: the line fails its checksum */
        rx_ring[rx_head & (RING - 1u)] = c;
        rx_head++;
    }
}

void hal_pump(uint8_t ch, uint16_t permille) {
    const pwm_t *p = &pumps[ch];
    if (permille == 0) { /* fast PWM at OCR = 0 still pulses once a cycle: disconnect, drive low */
        *p->tccr &= (uint8_t)~(1 << p->com);
        *p->pin.port &= (uint8_t)~p->pin.mask;
    } else {
        *p->ocr = (uint8_t)(((uint32_t)permille * 16711u + 32768u) >> 16); /* 255 * permille / 1000 without a division: it runs in the tick */
        *p->tccr |= (uint8_t)(1 << p->com);
    }
}

void hal_valve(uint8_t ch, uint8_t which, uint8_t open) {
    const pin_t *p = &valves[ch][which];
    uint8_t high = which == 0 ? open : (FW_OUTLET_NO ? !open : open);
    if (high) {
        *p->port |= p->mask;
    } else {
        *p->port &= (uint8_t)~p->mask;
    }
}

uint16_t hal_adc(uint8_t ch) { return adc_val[ch]; } /* read in the tick: no interrupt splits it */

void hal_nvm_read(uint16_t addr, void *buf, uint16_t len) {
    eeprom_read_block(buf, (const void *)(uintptr_t)addr, len);
}

void hal_nvm_write(uint16_t addr, const void *buf, uint16_t len) {
    eeprom_update_block(buf, (void *)(uintptr_t)addr, len);
}

ISR(TIMER1_COMPA_vect) { fw_tick(&fw); }

/* Round robin over the chambers' channels: 1 discarded conversion after a channel switch, then 16
 * summed. */
ISR(ADC_vect) {
    static uint8_t ch, count;
    static uint16_t sum;
    uint16_t v = ADC;
    if (count > 0) sum += v;
    if (++count > 16) {
        adc_val[ch] = sum;
        sum = 0;
        count = 0;
        if (++ch >= fw.cfg.n) ch = 0;
        ADMUX = (uint8_t)((1 << REFS0) | ch);
    }
    ADCSRA |= (1 << ADSC);
}

static void board_init(void) {
    for (uint8_t i = 0; i < FW_MAX_N; i++) {
        *pumps[i].pin.ddr |= pumps[i].pin.mask;
        for (uint8_t k = 0; k < 2; k++) *valves[i][k].ddr |= valves[i][k].mask;
    }
    TCCR0A = (1 << WGM01) | (1 << WGM00); /* fast PWM, 16 MHz / 64 / 256 = 976 Hz */
    TCCR0B = (1 << CS01) | (1 << CS00);
    TCCR2A = (1 << WGM21) | (1 << WGM20);
    TCCR2B = (1 << CS22); /* timer 2's /64 */
    TCCR1A = 0;           /* CTC on OCR1A, /8: 2 MHz */
    TCCR1B = (1 << WGM12) | (1 << CS11);
    OCR1A = (uint16_t)(F_CPU / 8UL / 1000000UL * FW_TICK_US - 1UL);
    TIMSK1 = (1 << OCIE1A);
    UCSR0A = (1 << U2X0);
    UBRR0 = (uint16_t)((F_CPU + 4UL * FW_BAUD) / (8UL * FW_BAUD) - 1UL);
    UCSR0C = (1 << UCSZ01) | (1 << UCSZ00); /* 8N1 */
    UCSR0B = (1 << RXEN0) | (1 << TXEN0) | (1 << RXCIE0);
    ADMUX = (1 << REFS0); /* AVcc reference, channel 0 */
    ADCSRA = (1 << ADEN) | (1 << ADIE) | (1 << ADSC) | (1 << ADPS2) | (1 << ADPS1) | (1 << ADPS0);
}

/* After a watchdog reset the watchdog stays on at its shortest timeout: off before the C start-up. */
void wdt_off_early(void) __attribute__((naked, used, section(".init3")));
void wdt_off_early(void) {
    MCUSR = 0;
    wdt_disable();
}

int main(void) {
    static const fw_cfg_t cfg = {FW_MAX_N, FW_TICK_US, FW_PERIOD_TICKS,
                                 (100000u + FW_TICK_US * FW_PERIOD_TICKS - 1u) / (FW_TICK_US * FW_PERIOD_TICKS),
                                 500000UL / FW_TICK_US};
    wdt_enable(WDTO_250MS);
    fw_init(&fw, &cfg); /* before the pins are outputs: they are driven safe from the start */
    board_init();
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
    for (;;) {
        wdt_reset();
        while (rx_head != rx_tail) {
            uint8_t c = rx_ring[rx_tail & (RING - 1u)];
            rx_tail++;
            fw_rx_byte(&fw, c);
        }
        fw_poll(&fw);
        cli();
        if (rx_head == rx_tail && !fw.snap_ready) {
            sleep_enable();
            sei();
            sleep_cpu(); /* any interrupt (tick, byte, ADC) wakes the loop */
            sleep_disable();
        }
        sei();
    }
}
