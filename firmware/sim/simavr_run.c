/* Run an AVR build of the firmware in simavr (libsimavr) with UART0 bridged to a pseudo-terminal:
 * prints the pty's path on the first line of stdout (everything simavr says goes to stderr), then
 * simulates until SIGINT/SIGTERM or the core stops. The sensors read a fixed voltage (--adc-mv, on
 * ADC0..ADC3; 200 mV is 0 Pa under the default calibration), or with --plant (Uno only) the pressures
 * of four first-order chambers driven by the Uno's pump and valve pins (see plant_step).
 *
 * The bridge runs in the simulation's own thread (simavr's uart_pty part uses a second thread and a
 * 512-byte queue that a starved thread lets overflow, corrupting lines): bytes the AVR sends go
 * straight to the pty, and bytes from the pty are fed to the UART while its receive queue has room
 * (the XON/XOFF signals).
 *
 * usage: hbma-fw-simavr FIRMWARE.elf [--mcu atmega328p] [--adc-mv MV | --plant] */
#define _DEFAULT_SOURCE
#define _XOPEN_SOURCE 700
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include "../hal/posix/pty.h"
#include "avr_adc.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"

#define UCSR0B_ADDR 0xC1 /* data-space address of UCSR0B on the ATmega328P and ATmega2560 */
#define RXEN0_MASK (1u << 4)

#include <math.h>

static volatile sig_atomic_t stop;

/* The Uno's outputs as data-space addresses (firmware/README.md's pinout): per chamber the pump's OCR,
 * its TCCR and COM bit (the pin follows the timer while set), the inlet's and the outlet's port and bit
 * (an outlet is normally open: high = closed). */
static const struct {
    uint16_t ocr, tccr;
    uint8_t com;
    uint16_t in_port;
    uint8_t in_bit;
    uint16_t out_port;
    uint8_t out_bit;
} uno[4] = {{0x47, 0x44, 7, 0x2B, 2, 0x25, 1},
            {0x48, 0x44, 5, 0x2B, 4, 0x25, 2},
            {0xB3, 0xB0, 7, 0x2B, 7, 0x25, 4},
            {0xB4, 0xB0, 5, 0x25, 0, 0x25, 5}};

/* One step of dt s of every chamber, as hbma_ctrl's FirstOrderPlant: dp/dt = 100 kPa/s x pump x inlet
 * - outlet x p / 0.2 s - p / 2 s, under the pins as they are now; the sensors then read
 * 200 mV + 45 mV/kPa (the default calibration's gauge sensor). */
static void plant_step(avr_t *avr, double p[4], double dt) {
    for (int i = 0; i < 4; i++) {
        const uint8_t *d = avr->data;
        double pump = (d[uno[i].tccr] >> uno[i].com) & 1 ? (d[uno[i].ocr] + 1) / 256.0 : 0.0;
        double in = (d[uno[i].in_port] >> uno[i].in_bit) & 1;
        double out = !((d[uno[i].out_port] >> uno[i].out_bit) & 1);
        double a = out / 0.2 + 1.0 / 2.0;
        double p_inf = 100e3 * pump * in / a;
        p[i] = p_inf + (p[i] - p_inf) * exp(-a * dt);
        double mv = 200.0 + 45.0 * p[i] / 1000.0;
        mv = mv < 0 ? 0 : mv > 5000 ? 5000 : mv;
        avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + i), (uint32_t)lround(mv));
    }
}
static int master = -1;
static int xon = 1;

static void on_signal(int sig) {
    (void)sig;
    stop = 1;
}

static void uart_out(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    uint8_t c = (uint8_t)value;
    if (write(master, &c, 1) != 1) { /* the host is not reading: the byte is lost, as on a wire */
    }
}

static void uart_xon(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq, (void)value, (void)param;
    xon = 1;
}

static void uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq, (void)value, (void)param;
    xon = 0;
}

int main(int argc, char **argv) {
    const char *elf = NULL, *mcu = "atmega328p";
    int adc_mv = 200, plant = 0;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--mcu") && i + 1 < argc) mcu = argv[++i];
        else if (!strcmp(argv[i], "--plant")) plant = 1;
        else if (!strcmp(argv[i], "--adc-mv") && i + 1 < argc) adc_mv = atoi(argv[++i]);
        else elf = argv[i];
    }
    if (!elf) {
        fprintf(stderr, "usage: %s FIRMWARE.elf [--mcu atmega328p] [--adc-mv MV | --plant]\n", argv[0]);
        return 2;
    }
    if (plant && strcmp(mcu, "atmega328p")) {
        fprintf(stderr, "--plant: the plant follows the Uno's pins (--mcu atmega328p)\n");
        return 2;
    }
    int out = dup(STDOUT_FILENO);
    dup2(STDERR_FILENO, STDOUT_FILENO); /* simavr's own messages must not look like the port line */
    elf_firmware_t f;
    memset(&f, 0, sizeof f);
    if (elf_read_firmware(elf, &f)) {
        fprintf(stderr, "cannot read %s\n", elf);
        return 1;
    }
    snprintf(f.mmcu, sizeof f.mmcu, "%s", mcu);
    f.frequency = 16000000;
    avr_t *avr = avr_make_mcu_by_name(f.mmcu);
    if (!avr) {
        fprintf(stderr, "simavr does not know %s\n", mcu);
        return 1;
    }
    avr_init(avr);
    avr_load_firmware(avr, &f);
    avr->vcc = avr->avcc = avr->aref = 5000;

    const char *name;
    int slave;
    if (open_raw_pty(&master, &slave, &name))
        return 1;

    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)AVR_UART_FLAG_STDIO;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), uart_out, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), uart_xon, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF), uart_xoff, NULL);
    avr_irq_t *uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    for (int i = 0; i < 4; i++) {
        avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + i), (uint32_t)adc_mv);
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    /* the port is announced once the firmware listens: a byte sent before its receiver is on is lost */
    int state = cpu_Running;
    while (!stop && state != cpu_Done && state != cpu_Crashed && !(avr->data[UCSR0B_ADDR] & RXEN0_MASK)) {
        state = avr_run(avr);
    }
    dprintf(out, "%s\n", name);
    close(out);

    int pending = -1; /* a byte read from the pty that the UART had no room for yet */
    double p[4] = {0};
    avr_cycle_count_t stepped = avr->cycle;
    const avr_cycle_count_t step = 1600; /* 100 us: the firmware's tick, so the valves' PWM is seen */
    while (!stop && state != cpu_Done && state != cpu_Crashed) {
        for (int i = 0; i < 200 && state != cpu_Done && state != cpu_Crashed; i++) state = avr_run(avr);
        if (plant && avr->cycle - stepped >= step) {
            plant_step(avr, p, (double)(avr->cycle - stepped) / (double)avr->frequency);
            stepped = avr->cycle;
        }
        while (xon) {
            if (pending < 0) {
                uint8_t c;
                if (read(master, &c, 1) != 1) break;
                pending = c;
            }
            avr_raise_irq(uart_in, (uint32_t)pending);
            pending = -1;
        }
    }
    close(slave);
    close(master);
    return state == cpu_Crashed ? 1 : 0;
}
