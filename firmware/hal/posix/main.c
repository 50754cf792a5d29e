/* The firmware on a POSIX host: the UART is a pseudo-terminal (its path printed on the first line of
 * stdout), and the "hardware" (timer, ADC in, pump and valve outputs out) is driven by a plant over
 * a second channel, a socket or pipe given as an open file descriptor (--plant-fd). Time passes only
 * when the plant says, so a plant can run the firmware in step with a simulation or in real time.
 *
 * Plant channel, ASCII lines:
 *   firmware -> plant, once at start:  I n tick_us period_ticks zero_1 gain_1 ... zero_n gain_n
 *   plant -> firmware:                 T k [c_1 ... c_n]   set the ADC counts (if given), run k ticks
 *   firmware -> plant, per T:          O t_us mode commands crc_errors bad_lines seq_gaps lines held
 *                                        pump_1 in_1 out_1 ... pump_n in_n out_n
 *                                        cmd_pump_1 cmd_in_1 cmd_out_1 ... cmd_out_n
 * where held is the SEQ of the host line whose command the outputs hold ("-": none, the firmware's own
 * safe state), pump_i the sum over the k ticks of chamber i's pump speed (per-mille), in_i and out_i
 * the ticks its inlet and outlet were open, cmd_* the newest command received (per-mille, latched at
 * the next sample instant); lines counts the valid host lines received. Before running the ticks the
 * firmware reads every byte already waiting on the pty, so a line written before the T is seen before
 * those ticks. Test knobs, each answered by an O line of zero ticks (R by "R path"):
 *   F names    inject defects (comma-separated names of --defect, "-" for none) from now on
 *   X k        corrupt the next k lines sent (one bit of the body flipped; the checksum kept)
 *   L k        lose the next k lines sent (their SEQ used: the host sees a gap)
 *   V          vanish: close the pty, as an unplugged cable (the firmware runs on)
 *   R          reappear on a new pty (a re-plug), answered "R path"
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
static int master = -1, slave_fd = -1;
static char txbuf[TXBUF];
static size_t txlen;
static uint16_t adc[FW_MAX_N];
static uint16_t pump[FW_MAX_N];
static uint8_t valve[FW_MAX_N][2];
static uint8_t nvm[NVM_SIZE];
static const char *nvm_path;
static volatile sig_atomic_t stop;
static unsigned corrupt_n, lose_n; /* lines sent still to corrupt, to lose */

/* --defect names, in the order of the FW_D_* bits */
static const char *const defect_names[] = {"crc", "stuck_inlet", "inverted_pressure", "no_watchdog",
                                           "wrong_period", "no_heartbeat", "seq_repeat", "no_crlf",
                                           "sensor_zero", "no_crc_check", "held_seq", "version"};
#define N_DEFECTS (sizeof defect_names / sizeof defect_names[0])

/* Comma-separated defect names ("-": none) as FW_D_* bits in *out; 0, or -1 for an unknown name. */
static int parse_defects(const char *text, uint16_t *out) {
    uint16_t bits = 0;
    char buf[256];
    snprintf(buf, sizeof buf, "%s", text);
    char *save = NULL;
    for (char *tok = strtok_r(buf, ",", &save); tok; tok = strtok_r(NULL, ",", &save)) {
        if (!strcmp(tok, "-")) continue;
        size_t k = 0;
        while (k < N_DEFECTS && strcmp(tok, defect_names[k])) k++;
        if (k == N_DEFECTS) return -1;
        bits = (uint16_t)(bits | (1u << k));
    }
    *out = bits;
    return 0;
}

void hal_crit_enter(void) {}
void hal_crit_exit(void) {}

static void tx_flush(void) {
    if (master < 0) txlen = 0; /* nobody on the line */
    while (txlen) {
        ssize_t w = write(master, txbuf, txlen);
        if (w <= 0) return; /* full (EAGAIN): the rest goes when the host reads */
        memmove(txbuf, txbuf + w, txlen - (size_t)w);
        txlen -= (size_t)w;
    }
}

uint16_t hal_uart_write(const char *buf, uint16_t len) {
    if (txlen + len > TXBUF) return 0;
    if (lose_n) {
        lose_n--;
        return len;
    }
    memcpy(txbuf + txlen, buf, len);
    if (corrupt_n && len > 7) { /* the body's last byte, before "*CCCC\n" */
        corrupt_n--;
        txbuf[txlen + len - 7] ^= 0x01;
    }
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

/* Answer a plant line with the state after its ticks (see the top of this file). */
static void report(int fd, unsigned long ps[], unsigned long on[][2]) {
    char out[96 + FW_MAX_N * 64];
    int len = snprintf(out, sizeof out, "O %llu %s %u %u %u %u %u ",
                       (unsigned long long)fw.t_sec * 1000000ull + fw.t_us, fw.mode == FW_RUN ? "RUN" : "SAFE",
                       fw.stats.commands, fw.stats.crc_errors, fw.stats.bad_lines, fw.stats.seq_gaps, fw.stats.lines);
    len += fw.held_seq == FW_NO_SEQ ? snprintf(out + len, sizeof out - (size_t)len, "-")
                                    : snprintf(out + len, sizeof out - (size_t)len, "%ld", (long)fw.held_seq);
    for (uint8_t i = 0; i < fw.cfg.n; i++) {
        len += snprintf(out + len, sizeof out - (size_t)len, " %lu %lu %lu", ps[i], on[i][0], on[i][1]);
    }
    for (uint8_t i = 0; i < fw.cfg.n; i++) {
        len += snprintf(out + len, sizeof out - (size_t)len, " %u %u %u", fw.pending[i][0], fw.pending[i][1],
                        fw.pending[i][2]);
    }
    out[len++] = '\n';
    if (write(fd, out, (size_t)len) != len) stop = 1;
}

static void read_pty(void) {
    char b[256];
    ssize_t r;
    while (master >= 0 && (r = read(master, b, sizeof b)) > 0) {
        for (ssize_t j = 0; j < r; j++) fw_rx_byte(&fw, (uint8_t)b[j]);
    }
}

static void vanish(void) {
    if (master < 0) return;
    close(slave_fd);
    close(master);
    master = slave_fd = -1;
    txlen = 0;
}

static void plant_line(int fd, char *s) {
    char *save = NULL;
    char *tok = strtok_r(s, " \r", &save);
    unsigned long ps[FW_MAX_N] = {0}, on[FW_MAX_N][2] = {{0}};
    if (!tok) return;
    char *arg = strtok_r(NULL, " \r", &save);
    if (!strcmp(tok, "F")) {
        if (arg) parse_defects(arg, &fw_defects);
    } else if (!strcmp(tok, "X")) {
        corrupt_n = arg ? (unsigned)strtoul(arg, NULL, 10) : 1u;
    } else if (!strcmp(tok, "L")) {
        lose_n = arg ? (unsigned)strtoul(arg, NULL, 10) : 1u;
    } else if (!strcmp(tok, "V")) {
        vanish();
    } else if (!strcmp(tok, "R")) {
        const char *name = "";
        if (master < 0 && open_raw_pty(&master, &slave_fd, &name)) stop = 1;
        if (master >= 0 && !*name) name = ptsname(master);
        char out[128];
        int len = snprintf(out, sizeof out, "R %s\n", name);
        if (write(fd, out, (size_t)len) != len) stop = 1;
        return;
    } else if (!strcmp(tok, "T") && arg) {
        long k = strtol(arg, NULL, 10);
        for (uint8_t i = 0; i < fw.cfg.n && (tok = strtok_r(NULL, " \r", &save)); i++) {
            adc[i] = (uint16_t)strtoul(tok, NULL, 10);
        }
        read_pty(); /* what the host wrote before this T */
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
    } else {
        return;
    }
    report(fd, ps, on);
}

static int usage(const char *argv0) {
    fprintf(stderr,
            "usage: %s --plant-fd FD [--n N] [--tick-us US] [--period-ticks K] [--timeout-ms MS] "
            "[--eeprom FILE] [--defect NAME,...]\n",
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
        else if (!strcmp(a, "--defect")) {
            if (parse_defects(v, &fw_defects)) {
                fprintf(stderr, "--defect %s: allowed", v);
                for (size_t k = 0; k < N_DEFECTS; k++) fprintf(stderr, " %s", defect_names[k]);
                fprintf(stderr, "\n");
                return 2;
            }
        } else return usage(argv[0]);
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
    if (open_raw_pty(&master, &slave_fd, &name))
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
        if (p[0].revents & POLLIN) read_pty();
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
    vanish();
    return 0;
}
