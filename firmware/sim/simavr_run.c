/* Run an AVR build of the firmware in simavr (libsimavr) with UART0 bridged to a pseudo-terminal:
 * prints the pty's path on the first line of stdout (everything simavr says goes to stderr), then
 * simulates until SIGINT/SIGTERM or the core stops. The sensors read a fixed voltage (--adc-mv, on
 * ADC0..ADC3; 200 mV is 0 Pa under the default calibration).
 *
 * usage: hbma-fw-simavr FIRMWARE.elf [--mcu atmega328p] [--adc-mv MV] */
#define _DEFAULT_SOURCE
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "avr_adc.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "uart_pty.h"

static volatile sig_atomic_t stop;
static void on_signal(int sig) {
    (void)sig;
    stop = 1;
}

int main(int argc, char **argv) {
    const char *elf = NULL, *mcu = "atmega328p";
    int adc_mv = 200;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--mcu") && i + 1 < argc) mcu = argv[++i];
        else if (!strcmp(argv[i], "--adc-mv") && i + 1 < argc) adc_mv = atoi(argv[++i]);
        else elf = argv[i];
    }
    if (!elf) {
        fprintf(stderr, "usage: %s FIRMWARE.elf [--mcu atmega328p] [--adc-mv MV]\n", argv[0]);
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
    static uart_pty_t pty;
    uart_pty_init(avr, &pty);
    uart_pty_connect(&pty, '0');
    for (int i = 0; i < 4; i++) {
        avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + i), (uint32_t)adc_mv);
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    dprintf(out, "%s\n", pty.port[0].slavename);
    close(out);
    int state = cpu_Running;
    while (!stop && state != cpu_Done && state != cpu_Crashed) state = avr_run(avr);
    uart_pty_stop(&pty);
    avr_terminate(avr);
    return state == cpu_Crashed ? 1 : 0;
}
