/* Unit tests of the firmware core (fw.c) on a fake board: the UART is a buffer, the outputs are
 * recorded, the NVM is an array. Built and run by `make test`; exits non-zero on the first failure. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fw.h"
#include "hal.h"

static char out[8192];
static uint16_t out_len;
static uint16_t pump[FW_MAX_N];
static uint8_t valve[FW_MAX_N][2];
static uint16_t adc[FW_MAX_N];
static uint8_t nvm[256];
static int crit_depth;
static fw_t fw;

void hal_crit_enter(void) { crit_depth++; }
void hal_crit_exit(void) { crit_depth--; }
uint16_t hal_uart_write(const char *buf, uint16_t len) {
    if (out_len + len > sizeof out) return 0;
    memcpy(out + out_len, buf, len);
    out_len = (uint16_t)(out_len + len);
    return len;
}
void hal_pump(uint8_t ch, uint16_t permille) { pump[ch] = permille; }
void hal_valve(uint8_t ch, uint8_t which, uint8_t open) { valve[ch][which] = open; }
uint16_t hal_adc(uint8_t ch) { return adc[ch]; }
void hal_nvm_read(uint16_t addr, void *buf, uint16_t len) { memcpy(buf, nvm + addr, len); }
void hal_nvm_write(uint16_t addr, const void *buf, uint16_t len) { memcpy(nvm + addr, buf, len); }

#ifdef FW_HOSTED
/* A fake controller: its command is the target's millimetres as the pump's per-mille with the inlet open,
 * its "estimate" the reading; it records what it was ticked with. */
static uint32_t ctl_target[FW_MAX_N];
static uint16_t ctl_held[FW_MAX_N][3];
static int32_t ctl_p[FW_MAX_N];
static uint32_t ctl_us[FW_MAX_N];
static int ctl_ticks, ctl_inits;
static int8_t ctl_status; /* the status the fake reports */
void fw_ctl_init(uint8_t ch) {
    ctl_target[ch] = 0;
    ctl_inits++;
}
void fw_ctl_target(uint8_t ch, uint32_t height_um) { ctl_target[ch] = height_um; }
void fw_ctl_tick(uint8_t ch, uint32_t sec, uint32_t us, int32_t p_pa, uint8_t na, const uint16_t held[3],
                 fw_ctl_report_t *r) {
    ctl_ticks++;
    ctl_us[ch] = sec * 1000000u + us;
    ctl_p[ch] = na ? -1 : p_pa;
    for (int k = 0; k < 3; k++) ctl_held[ch][k] = held[k];
    r->u[0] = (uint16_t)(ctl_target[ch] / 1000u);
    r->u[1] = 1000;
    r->u[2] = 0;
    r->height_um = (int32_t)ctl_target[ch] / 2;
    r->pressure_pa = p_pa;
    r->status = ctl_status;
}
#endif

static int failures;
#define CHECK(cond)                                                       \
    do {                                                                  \
        if (!(cond)) {                                                    \
            fprintf(stderr, "%s:%d: %s failed\n", __FILE__, __LINE__, #cond); \
            failures++;                                                   \
        }                                                                 \
    } while (0)

/* Feed body with its checksum and the given line end. */
static void send_end(const char *body, const char *end) {
    char line[600];
    snprintf(line, sizeof line, "%s*%04X%s", body, fw_crc16((const uint8_t *)body, (uint16_t)strlen(body)), end);
    for (const char *p = line; *p; p++) fw_rx_byte(&fw, (uint8_t)*p);
}
static void send(const char *body) { send_end(body, "\n"); }

static void ticks(int k) {
    for (int i = 0; i < k; i++) {
        fw_tick(&fw);
        fw_poll(&fw);
    }
}

/* The i-th line sent (0 = first) since the last clear, body only, after checking its checksum. */
static const char *line_at(int i) {
    static char body[600];
    const char *p = out;
    for (; i > 0; i--) {
        p = memchr(p, '\n', (size_t)(out + out_len - p));
        if (!p) return "";
        p++;
    }
    const char *nl = memchr(p, '\n', (size_t)(out + out_len - p));
    if (!nl || nl - p < 5) return "";
    size_t n = (size_t)(nl - p - 5);
    memcpy(body, p, n);
    body[n] = '\0';
    unsigned crc;
    if (p[n] != '*' || sscanf(p + n + 1, "%4X", &crc) != 1 || crc != fw_crc16((const uint8_t *)body, (uint16_t)n))
        return "BAD-CRC";
    return body;
}
static int lines(void) {
    int k = 0;
    for (uint16_t i = 0; i < out_len; i++) k += out[i] == '\n';
    return k;
}
static void clear(void) { out_len = 0; }

static void boot(uint8_t n) {
    fw_cfg_t cfg = {n, 100, 100, 10, 5000}; /* 10 ms period, HB every 0.1 s, watchdog 0.5 s */
    clear();
    fw_init(&fw, &cfg);
    for (uint8_t i = 0; i < n; i++) adc[i] = FW_CAL_ZERO;
}

/* Boot, handshake and run the first tick (a sample instant, P 1); tick call k is at t = k * 100 us and
 * a sample instant when k is a multiple of 100. */
static void session(uint8_t n) {
    boot(n);
    send("HELLO 0 2");
    ticks(1);
    clear();
}

static void test_crc(void) {
    CHECK(fw_crc16((const uint8_t *)"123456789", 9) == 0x29B1);
    CHECK(fw_crc16((const uint8_t *)"", 0) == 0xFFFF);
}

#ifndef FW_HOSTED /* the tests of a board the host commands */
static void test_handshake(void) {
    boot(1);
    ticks(150);
    CHECK(lines() == 0); /* nothing streams before a HELLO */
    send("HELLO 0 2");
    CHECK(strcmp(line_at(0), "VER 0 2 1 10000") == 0);
    ticks(50); /* calls 150..199 */
    CHECK(lines() == 1);
    ticks(1); /* call 200: the sample instant at t = 20 ms; it names HELLO, which acted at once */
    CHECK(strcmp(line_at(1), "P 1 20000 0 0") == 0);
    boot(2);
    send_end("HELLO 0 2", "\r\n");
    CHECK(strcmp(line_at(0), "VER 0 2 2 10000") == 0);
    CHECK(fw.session == 1);
}

static void test_other_version(void) {
    boot(1);
    send("HELLO 0 1");
    CHECK(strcmp(line_at(0), "VER 0 2 1 10000") == 0);
    ticks(200);
    CHECK(lines() == 1); /* answered, no session: no P lines */
    send("CMD 1 600 1000 0");
    CHECK(fw.stats.commands == 0 && fw.stats.bad_lines == 1);
}

static void test_bad_lines(void) {
    session(1);
    fw_rx_byte(&fw, 'C');
    send("MD 1 600 1000 0"); /* "CMD 1 ...*crc of the wrong body" */
    CHECK(fw.stats.crc_errors == 1 && fw.stats.commands == 0);
    const char *bad = "CMD 1 600 1000 0*0000\n";
    for (const char *p = bad; *p; p++) fw_rx_byte(&fw, (uint8_t)*p);
    CHECK(fw.stats.crc_errors == 2 && fw.stats.commands == 0);
    send("CMD 1 600 1000"); /* 2 values for 1 chamber */
    send("CMD 2 600 1001 0"); /* out of range */
    send("CMD 3 600 -1 0");
    send("CMD 4 600 10x 0");
    send("NOPE 5");
    send("CMD");
    CHECK(fw.stats.bad_lines == 6 && fw.stats.commands == 0);
    for (int i = 0; i < FW_RX_MAX + 10; i++) fw_rx_byte(&fw, 'x');
    send("CMD 6 600 1000 0"); /* the overlong line ends here: both are one bad line */
    CHECK(fw.stats.bad_lines == 7 && fw.stats.commands == 0);
    send("CMD 7 600 1000 0");
    CHECK(fw.stats.commands == 1);
    send("TGT 8 5000"); /* a target for a board's own controller: this build has none */
    CHECK(fw.stats.bad_lines == 8 && fw.stats.commands == 1);
    ticks(200);
    CHECK(pump[0] == 600);
    CHECK(crit_depth == 0);
}

static void test_latching(void) {
    session(1);
    ticks(49); /* calls 1..49: mid-period */
    send("CMD 1 600 300 0");
    CHECK(pump[0] == 0);
    ticks(50); /* calls 50..99: the period's last tick still runs on HELLO's safe state */
    CHECK(pump[0] == 0 && valve[0][0] == 0 && valve[0][1] == 1);
    CHECK(lines() == 0);
    ticks(1); /* call 100, the sample instant: the P line names HELLO (0), the outputs switch to CMD 1 */
    CHECK(strncmp(line_at(0), "P 2 10000 0 ", 12) == 0);
    CHECK(pump[0] == 600 && valve[0][0] == 1 && valve[0][1] == 0);
    int open = valve[0][0];
    for (int i = 1; i < 100; i++) {
        ticks(1);
        open += valve[0][0];
    }
    CHECK(open == 30); /* duty 300 per-mille of a 100-tick period */
    ticks(1);
    CHECK(strncmp(line_at(1), "P 3 20000 1 ", 12) == 0);
    CHECK(strcmp(fw.mode == FW_RUN ? "RUN" : "SAFE", "RUN") == 0);
}

static void test_safe_at_once(void) {
    session(1);
    send("CMD 1 600 1000 0");
    ticks(100);
    CHECK(pump[0] == 600);
    ticks(30);
    send("SAFE 2");
    CHECK(pump[0] == 0 && valve[0][0] == 0 && valve[0][1] == 1 && fw.mode == FW_SAFE);
    ticks(1);
    CHECK(valve[0][0] == 0 && valve[0][1] == 1);
    ticks(69);
    CHECK(strncmp(line_at(lines() - 1), "P 3 20000 2 ", 12) == 0); /* the period ended on SAFE 2 */
}

static void test_watchdog(void) {
    session(1);
    send("CMD 1 600 1000 0");
    for (int i = 0; i < 10; i++) { /* a heartbeat every 0.1 s keeps it running */
        ticks(1000);
        char hb[16];
        snprintf(hb, sizeof hb, "HB %d", 2 + i);
        send(hb);
    }
    CHECK(fw.mode == FW_RUN && pump[0] == 600);
    ticks(5000); /* 0.5 s of silence: not yet */
    CHECK(fw.mode == FW_RUN && pump[0] == 600);
    clear();
    ticks(1); /* one tick more: safe at once, mid-period */
    CHECK(fw.mode == FW_SAFE && pump[0] == 0 && valve[0][0] == 0 && valve[0][1] == 1);
    ticks(1000);
    CHECK(strstr(out, " - 0*") != NULL); /* P lines name the watchdog's safe state */
    CHECK(strstr(out, "HB ") != NULL && strstr(out, " SAFE*") != NULL);
    send("CMD 12 600 1000 0"); /* a command after silence runs again */
    ticks(100);
    CHECK(fw.mode == FW_RUN && pump[0] == 600);
}

static void test_heartbeat_and_seq(void) {
    session(1);
    send("CMD 1 0 0 0");
    ticks(1000); /* 10 samples: 10 P and 1 HB */
    int p = 0, hb = 0;
    for (int i = 0; i < lines(); i++) {
        p += line_at(i)[0] == 'P';
        hb += strncmp(line_at(i), "HB ", 3) == 0;
    }
    CHECK(p == 10 && hb == 1);
    send("HB 5"); /* 2, 3, 4 lost */
    CHECK(fw.stats.seq_gaps == 3);
    send("HB 6");
    CHECK(fw.stats.seq_gaps == 3);
}

static void test_pressure_and_time(void) {
    session(2);
    adc[0] = FW_CAL_ZERO + 1000; /* 6788 Pa */
    adc[1] = 0;                  /* open line: NA */
    ticks(100 * 101);            /* calls 1..10100: the last sample instant at t = 1.01 s */
    const char *last = line_at(lines() - 1)[0] == 'P' ? line_at(lines() - 1) : line_at(lines() - 2);
    CHECK(strstr(last, " 1010000 0 6788 NA") != NULL);
    uint8_t na;
    fw_cal_t cal = {655, 6788};
    CHECK(fw_pressure(&cal, 655 - 10, &na) == -68 && !na);
    CHECK(fw_pressure(&cal, FW_ADC_NONE, &na) && na);
}

static void test_calibration(void) {
    memset(nvm, 0xFF, sizeof nvm);
    boot(2);
    CHECK(fw.cal[0].zero == FW_CAL_ZERO && fw.cal[0].gain == FW_CAL_GAIN); /* blank NVM: defaults */
    send("HELLO 0 2");
    send("CAL 1 1 700 5000");
    CHECK(fw.cal[1].zero == 700 && fw.cal[1].gain == 5000 && fw.stats.bad_lines == 0);
    send("CMD 2 0 0 0 0 0 0");
    send("CAL 3 0 700 5000"); /* refused while running */
    CHECK(fw.stats.bad_lines == 1 && fw.cal[0].zero == FW_CAL_ZERO);
    boot(2); /* a reset keeps it */
    CHECK(fw.cal[1].zero == 700 && fw.cal[1].gain == 5000 && fw.cal[0].zero == FW_CAL_ZERO);
    nvm[1 * FW_NVM_BYTES_PER_CH] ^= 1; /* a corrupt record falls back to the defaults */
    boot(2);
    CHECK(fw.cal[1].zero == FW_CAL_ZERO && fw.cal[1].gain == FW_CAL_GAIN);
}

static void test_hello_is_safe_at_once(void) {
    session(1);
    send("CMD 1 600 1000 0");
    ticks(150);
    CHECK(pump[0] == 600);
    send("HELLO 0 2");
    CHECK(pump[0] == 0 && fw.mode == FW_SAFE && strcmp(line_at(lines() - 1), "VER 0 2 1 10000") == 0);
    ticks(50);
    CHECK(strncmp(line_at(lines() - 1), "P 1 ", 4) == 0 && strstr(line_at(lines() - 1), " 0 0") != NULL);
}
#endif


#ifdef FW_HOSTED
static void test_hosted_handshake_and_targets(void) {
    boot(1);
    send("HELLO 0 2");
    CHECK(strcmp(line_at(0), "VER 0 2 1 10000 hosted") == 0);
    ticks(1);
    clear();
    send("CMD 1 600 1000 0"); /* the board's controller commands: a host's CMD is refused */
    CHECK(fw.stats.bad_lines == 1 && fw.stats.commands == 0 && fw.mode == FW_SAFE);
    send("TGT 2 5000 1"); /* one height for one chamber */
    send("TGT 3 1000001");
    send("TGT 4 -5");
    CHECK(fw.stats.bad_lines == 4 && fw.mode == FW_SAFE);
    ticks(100); /* call 100: a sample instant while safe: the controller ticks, its command is dropped */
    CHECK(pump[0] == 0);
    CHECK(strcmp(line_at(0), "P 3 10000 0 0") == 0);
    CHECK(strcmp(line_at(1), "U 4 0 0 1000 0 0 0") == 0); /* the safe command it will hold */
    adc[0] = FW_CAL_ZERO + 1000; /* 6788 Pa */
    send("TGT 5 600000");
    CHECK(fw.mode == FW_RUN && ctl_target[0] == 600000 && fw.stats.commands == 1);
    ticks(100); /* call 200: the controller ticks on this sample; its command waits for the next instant */
    CHECK(pump[0] == 0 && ctl_p[0] == 6788 && ctl_us[0] == 20000);
    CHECK(ctl_held[0][0] == 0 && ctl_held[0][2] == 1000);
    CHECK(strcmp(line_at(2), "P 5 20000 0 6788") == 0); /* the period ran on HELLO's safe state */
    CHECK(strcmp(line_at(3), "U 6 600 1000 0 300000 6788 0") == 0);
    ticks(100); /* call 300: latched */
    CHECK(pump[0] == 600 && valve[0][0] == 1 && valve[0][1] == 0);
    ticks(100); /* call 400: the controller is told the period ran on its command, named by TGT 5 */
    CHECK(ctl_held[0][0] == 600 && ctl_held[0][1] == 1000 && ctl_held[0][2] == 0);
    CHECK(strncmp(line_at(lines() - 2), "P 9 40000 5 ", 12) == 0);
    CHECK(crit_depth == 0);
}

static void test_hosted_safe_and_watchdog_win(void) {
    session(1);
    send("TGT 1 600000");
    ticks(200);
    CHECK(pump[0] == 600 && fw.mode == FW_RUN);
    ticks(30);
    send("SAFE 2"); /* at once, mid-period */
    CHECK(pump[0] == 0 && valve[0][0] == 0 && valve[0][1] == 1 && fw.mode == FW_SAFE);
    ticks(300); /* the controller keeps ticking; its commands are dropped */
    CHECK(pump[0] == 0 && valve[0][1] == 1 && ctl_held[0][0] == 0);
    send("TGT 3 600000");
    ticks(200);
    CHECK(pump[0] == 600);
    clear();
    for (int i = 0; i < 5; i++) { /* heartbeats keep it running */
        ticks(1000);
        char hb[16];
        snprintf(hb, sizeof hb, "HB %d", 4 + i);
        send(hb);
    }
    CHECK(fw.mode == FW_RUN && pump[0] == 600);
    ticks(5001); /* 0.5 s of silence and a tick: safe at once */
    CHECK(fw.mode == FW_SAFE && pump[0] == 0 && valve[0][0] == 0 && valve[0][1] == 1);
    ticks(500);
    CHECK(pump[0] == 0 && strstr(out, " - 0*") != NULL);
    CHECK(lines() > 0);
    int inits = ctl_inits;
    send("HELLO 0 2"); /* a new session restarts the controllers */
    CHECK(ctl_inits == inits + 1 && ctl_target[0] == 0);
}

static void test_hosted_library_error_vents_the_chamber(void) {
    session(1);
    send("TGT 1 600000");
    ticks(200);
    CHECK(pump[0] == 600);
    ctl_status = -2; /* the library failed: its command is not used */
    ticks(200);
    CHECK(fw.mode == FW_RUN && pump[0] == 0 && valve[0][0] == 0 && valve[0][1] == 1);
    CHECK(strstr(line_at(lines() - 1), " 0 0 1000 300000 0 -2") != NULL);
    ctl_status = 0;
    ticks(200);
    CHECK(pump[0] == 600);
}
#endif

int main(void) {
    test_crc();
#ifdef FW_HOSTED
    test_hosted_handshake_and_targets();
    test_hosted_safe_and_watchdog_win();
    test_hosted_library_error_vents_the_chamber();
#else
    test_handshake();
    test_other_version();
    test_bad_lines();
    test_latching();
    test_safe_at_once();
    test_watchdog();
    test_heartbeat_and_seq();
    test_pressure_and_time();
    test_calibration();
    test_hello_is_safe_at_once();
#endif
    if (failures) {
        fprintf(stderr, "%d check(s) failed\n", failures);
        return 1;
    }
#ifdef FW_HOSTED
    printf("firmware core, hosted: all tests passed\n");
#else
    printf("firmware core: all tests passed\n");
#endif
    return 0;
}
