/* The firmware on a POSIX host: the UART is a pseudo-terminal (its path printed on the first line of
 * stdout), and the "hardware" (timer, ADC in, pump and valve outputs out) is driven by a plant over
 * a second channel, a socket or pipe given as an open file descriptor (--plant-fd). Time passes only
 * when the plant says, so a plant can run the firmware in step with a simulation or in real time.
 *
 * Plant channel, ASCII lines:
 *   firmware -> plant, once at start:  I n tick_us period_ticks zero_1 gain_1 ... zero_n gain_n
 *   plant -> firmware:                 T k [c_1 ... c_n]   set the ADC counts (if given), run k ticks
 *   firmware -> plant, per T:          O t_us mode commands crc_errors bad_lines seq_gaps lines
 *                                        pump_1 in_1 out_1 ... pump_n in_n out_n
 * where pump_i is the sum over the k ticks of chamber i's pump speed (per-mille) and in_i, out_i the
 * ticks its inlet and outlet were open; lines counts the valid host lines received. Before running the ticks the firmware reads every byte
 * already waiting on the pty, so a line written before the T is seen before those ticks.
 * The firmware exits when the plant channel closes, or on SIGINT/SIGTERM. */
#define _XOPEN_SOURCE 700
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include "pty.h"
#include "fw.h"
#include "hal.h"

#define NVM_SIZE 1024
#define TXBUF 65536

static fw_t fw;
static int master = -1;
static char txbuf[TXBUF];
static size_t txlen;
static uint16_t adc[FW_MAX_N];
static uint16_t pump[FW_MAX_N];
static uint8_t valve[FW_MAX_N][2];
static uint8_t nvm[NVM_SIZE];
static const char *nvm_path;
static volatile sig_atomic_t stop;

void hal_crit_enter(void) {}
void hal_crit_exit(void) {}

static void tx_flush(void) {
    while (txlen) {
        ssize_t w = write(master, txbuf, txlen);
        if (w <= 0) return; /* full (EAGAIN): the rest goes when the host reads */
        memmove(txbuf, txbuf + w, txlen - (size_t)w);
        txlen -= (size_t)w;
    }
}

uint16_t hal_uart_write(const char *buf, uint16_t len) {
    if (txlen + len > TXBUF) return 0;
    memcpy(txbuf + txlen, buf, len);
    txlen += len;
    tx_flush();
    return len;
}

void hal_pump(uint8_t ch, uint16_t permille) { pump[ch] = permille; }
void hal_valve(uint8_t ch, uint8_t which, uint8_t open) { valve[ch][which] = open; }
uint16_t hal_adc(uint8_t ch) { return adc[ch]; }

void hal_nvm_read(uint16_t addr, void *buf, uint16_t len) { memcpy(buf, nvm + addr, len); }

void hal_nvm_write(uint16_t addr, const void *buf, uint16_t len) {
    memcpy(nvm + addr, buf, len);
    if (nvm_path) {
        FILE *f = fopen(nvm_path, "wb");
        if (f) {
            fwrite(nvm, 1, NVM_SIZE, f);
            fclose(f);
        }
    }
}

static void on_signal(int sig) {
    (void)sig;
    stop = 1;
}

static void plant_line(int fd, char *s) {
    char *save = NULL;
    char *tok = strtok_r(s, " \r", &save);
    if (!tok || strcmp(tok, "T") != 0) return;
    tok = strtok_r(NULL, " \r", &save);
    if (!tok) return;
    long k = strtol(tok, NULL, 10);
    for (uint8_t i = 0; i < fw.cfg.n && (tok = strtok_r(NULL, " \r", &save)); i++) {
        adc[i] = (uint16_t)strtoul(tok, NULL, 10);
    }
    char b[64];
    ssize_t r;
    while ((r = read(master, b, sizeof b)) > 0) { /* what the host wrote before this T */
        for (ssize_t j = 0; j < r; j++) fw_rx_byte(&fw, (uint8_t)b[j]);
    }
    unsigned long ps[FW_MAX_N] = {0}, on[FW_MAX_N][2] = {{0}};
    for (long t = 0; t < k; t++) {
        fw_tick(&fw);
        fw_poll(&fw);
        for (uint8_t i = 0; i < fw.cfg.n; i++) {
            ps[i] += pump[i];
            on[i][0] += valve[i][0];
            on[i][1] += valve[i][1];
        }
    }
    fw_poll(&fw);
    char out[64 + FW_MAX_N * 40];
    int len = snprintf(out, sizeof out, "O %llu %s %u %u %u %u %u",
                       (unsigned long long)fw.t_sec * 1000000ull + fw.t_us, fw.mode == FW_RUN ? "RUN" : "SAFE",
                       fw.stats.commands, fw.stats.crc_errors, fw.stats.bad_lines, fw.stats.seq_gaps, fw.stats.lines);
    for (uint8_t i = 0; i < fw.cfg.n; i++) {
        len += snprintf(out + len, sizeof out - (size_t)len, " %lu %lu %lu", ps[i], on[i][0], on[i][1]);
    }
    out[len++] = '\n';
    if (write(fd, out, (size_t)len) != len) stop = 1;
}

static int usage(const char *argv0) {
    fprintf(stderr,
            "usage: %s --plant-fd FD [--n N] [--tick-us US] [--period-ticks K] [--timeout-ms MS] "
            "[--eeprom FILE]\n",
            argv0);
    return 2;
}

int main(int argc, char **argv) {
    fw_cfg_t cfg = {1, 100, 100, 10, 5000};
    unsigned timeout_ms = 500;
    int plant = -1;
    for (int i = 1; i < argc; i++) {
        if (i + 1 >= argc) return usage(argv[0]);
        const char *a = argv[i], *v = argv[++i];
        if (!strcmp(a, "--n")) cfg.n = (uint8_t)atoi(v);
        else if (!strcmp(a, "--tick-us")) cfg.tick_us = (uint32_t)atol(v);
        else if (!strcmp(a, "--period-ticks")) cfg.period_ticks = (uint16_t)atoi(v);
        else if (!strcmp(a, "--timeout-ms")) timeout_ms = (unsigned)atol(v);
        else if (!strcmp(a, "--plant-fd")) plant = atoi(v);
        else if (!strcmp(a, "--eeprom")) nvm_path = v;
        else return usage(argv[0]);
    }
    if (plant < 0 || cfg.n < 1 || cfg.n > FW_MAX_N || cfg.tick_us < 1 || cfg.period_ticks < 1) {
        return usage(argv[0]);
    }
    uint32_t period_us = cfg.tick_us * cfg.period_ticks;
    cfg.hb_periods = (uint16_t)((100000u + period_us - 1u) / period_us); /* every 0.1 s */
    cfg.timeout_ticks = (uint32_t)((uint64_t)timeout_ms * 1000u / cfg.tick_us);
    memset(nvm, 0xFF, sizeof nvm);
    if (nvm_path) {
        FILE *f = fopen(nvm_path, "rb");
        if (f) {
            size_t got = fread(nvm, 1, NVM_SIZE, f);
            (void)got;
            fclose(f);
        }
    }
    const char *name;
    int slave;
    if (open_raw_pty(&master, &slave, &name))
        return 1;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    fw_init(&fw, &cfg);
    printf("%s\n", name);
    fflush(stdout);
    char info[32 + FW_MAX_N * 16];
    int len = snprintf(info, sizeof info, "I %u %lu %u", fw.cfg.n, (unsigned long)cfg.tick_us, cfg.period_ticks);
    for (uint8_t i = 0; i < fw.cfg.n; i++) {
        len += snprintf(info + len, sizeof info - (size_t)len, " %u %d", fw.cal[i].zero, fw.cal[i].gain);
    }
    info[len++] = '\n';
    if (write(plant, info, (size_t)len) != len) return 1;

    char pbuf[1024];
    size_t plen = 0;
    while (!stop) {
        struct pollfd p[2] = {{master, (short)(POLLIN | (txlen ? POLLOUT : 0)), 0}, {plant, POLLIN, 0}};
        if (poll(p, 2, -1) < 0) {
            if (errno == EINTR) continue;
            break;
        }
        if (p[0].revents & POLLOUT) tx_flush();
        if (p[0].revents & POLLIN) {
            char b[256];
            ssize_t r = read(master, b, sizeof b);
            for (ssize_t j = 0; j < r; j++) fw_rx_byte(&fw, (uint8_t)b[j]);
        }
        if (p[1].revents & (POLLIN | POLLHUP)) {
            ssize_t r = read(plant, pbuf + plen, sizeof pbuf - 1 - plen);
            if (r <= 0) break; /* the plant is gone */
            plen += (size_t)r;
            char *nl;
            while ((nl = memchr(pbuf, '\n', plen))) {
                *nl = '\0';
                plant_line(plant, pbuf);
                plen -= (size_t)(nl + 1 - pbuf);
                memmove(pbuf, nl + 1, plen);
            }
            if (plen == sizeof pbuf - 1) plen = 0; /* no newline in sight: noise */
        }
    }
    close(slave);
    close(master);
    return 0;
}
