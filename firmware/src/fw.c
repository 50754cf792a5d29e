/* The rig firmware's core (see fw.h). Portable C99, no allocation. */
#include "fw.h"

#include <string.h>

#include "hal.h"

#define MAX_TOKENS (3 * FW_MAX_N + 2)

/* CRC-16 (poly 0x1021) of len bytes from the initial value crc. */
static uint16_t crc16_from(uint16_t crc, const uint8_t *data, uint16_t len) {
    while (len--) {
        crc ^= (uint16_t)((uint16_t)*data++ << 8);
        for (uint8_t b = 0; b < 8; b++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

uint16_t fw_crc16(const uint8_t *data, uint16_t len) { return crc16_from(0xFFFFu, data, len); }

#ifdef FW_DEFECTS
uint16_t fw_defects;
#endif

/* ---- outputs (caller is the tick or holds the critical section) ---------------------------- */

/* The pending command becomes the held one (no division here: the tick must stay short). */
static void latch(fw_t *fw) {
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        for (uint8_t k = 0; k < 3; k++) fw->held[i][k] = fw->pending[i][k];
        for (uint8_t k = 0; k < 2; k++) fw->on_ticks[i][k] = fw->pending_on[i][k];
        hal_pump(i, fw->pending[i][FW_PUMP]);
    }
    fw->held_seq = fw->pending_seq;
}

/* Open ticks per period for a valve duty in per-mille, rounded to the nearest tick. */
static uint16_t duty_ticks(const fw_t *fw, uint16_t permille) {
    return (uint16_t)(((uint32_t)permille * fw->cfg.period_ticks + 500u) / 1000u);
}

static void apply_valves(fw_t *fw) {
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        for (uint8_t k = 0; k < 2; k++) {
            hal_valve(i, k, fw->phase < fw->on_ticks[i][k] && !(FW_DEFECT(FW_D_STUCK_INLET) && i == 0 && k == 0));
        }
    }
}

/* Safe at once: pump off, inlet closed, outlet open, for the pending and the held command. */
static void go_safe_now(fw_t *fw, int32_t seq) {
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        fw->pending[i][FW_PUMP] = 0;
        fw->pending[i][FW_INLET] = 0;
        fw->pending[i][FW_OUTLET] = 1000;
        fw->pending_on[i][0] = 0;
        fw->pending_on[i][1] = fw->cfg.period_ticks;
    }
    fw->pending_seq = seq;
    fw->mode = FW_SAFE;
    latch(fw);
    apply_valves(fw);
}

/* ---- calibration ----------------------------------------------------------------------------- */

int32_t fw_pressure(const fw_cal_t *cal, uint16_t counts, uint8_t *na) {
    *na = (counts == FW_ADC_NONE || counts < FW_ADC_OPEN);
    /* |d * gain| <= 65535 * 32767 < 2^31: no overflow in 32 bits */
    int32_t x = ((int32_t)counts - (int32_t)cal->zero) * (int32_t)cal->gain;
    return (x >= 0 ? x + 500 : x - 500) / 1000;
}

static void cal_pack(fw_cal_t cal, uint8_t b[FW_NVM_BYTES_PER_CH]) {
    uint16_t g = (uint16_t)cal.gain;
    b[0] = (uint8_t)cal.zero;
    b[1] = (uint8_t)(cal.zero >> 8);
    b[2] = (uint8_t)g;
    b[3] = (uint8_t)(g >> 8);
    uint16_t c = fw_crc16(b, 4);
    b[4] = (uint8_t)c;
    b[5] = (uint8_t)(c >> 8);
}

void fw_set_cal(fw_t *fw, uint8_t ch, fw_cal_t cal) {
    uint8_t b[FW_NVM_BYTES_PER_CH];
    cal_pack(cal, b);
    hal_nvm_write((uint16_t)(ch * FW_NVM_BYTES_PER_CH), b, FW_NVM_BYTES_PER_CH);
    fw->cal[ch] = cal;
}

static fw_cal_t cal_load(uint8_t ch) {
    uint8_t b[FW_NVM_BYTES_PER_CH];
    fw_cal_t cal = {FW_CAL_ZERO, FW_CAL_GAIN};
    hal_nvm_read((uint16_t)(ch * FW_NVM_BYTES_PER_CH), b, FW_NVM_BYTES_PER_CH);
    uint16_t c = (uint16_t)(b[4] | (b[5] << 8));
    uint16_t g = (uint16_t)(b[2] | (b[3] << 8));
    if (fw_crc16(b, 4) == c && g != 0 && g <= 0x7FFFu) { /* a blank EEPROM (0xFF...) fails the CRC */
        cal.zero = (uint16_t)(b[0] | (b[1] << 8));
        cal.gain = (int16_t)g;
    }
    return cal;
}

/* ---- init and tick --------------------------------------------------------------------------- */

void fw_init(fw_t *fw, const fw_cfg_t *cfg) {
    memset((void *)fw, 0, sizeof *fw);
    fw->cfg = *cfg;
    if (fw->cfg.n < 1) fw->cfg.n = 1;
    if (fw->cfg.n > FW_MAX_N) fw->cfg.n = FW_MAX_N;
    fw->rx_expect = -1;
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        fw->cal[i] = cal_load(i);
#ifdef FW_HOSTED
        fw_ctl_init(i);
#endif
    }
    go_safe_now(fw, FW_NO_SEQ);
}

void fw_tick(fw_t *fw) {
    if (fw->silent_ticks < 0xFFFFFFFFu) fw->silent_ticks++;
    if (fw->mode == FW_RUN && fw->silent_ticks > fw->cfg.timeout_ticks && !FW_DEFECT(FW_D_NO_WATCHDOG)) {
        go_safe_now(fw, FW_NO_SEQ); /* the host fell silent */
    }
    if (fw->phase == 0) {
        if (fw->snap_ready) fw->stats.overruns++; /* the main loop did not send the previous one */
        for (uint8_t i = 0; i < fw->cfg.n; i++) {
            fw->snap_raw[i] = hal_adc(i);
        }
        fw->snap_sec = fw->t_sec;
        fw->snap_us = fw->t_us;
        fw->snap_seq = fw->held_seq; /* the command the period that ends now ran on */
#ifdef FW_HOSTED
        for (uint8_t i = 0; i < fw->cfg.n; i++) {
            for (uint8_t k = 0; k < 3; k++) fw->snap_held[i][k] = fw->held[i][k];
        }
#endif
        latch(fw);
        if (++fw->hb_count >= fw->cfg.hb_periods) fw->hb_count = 0;
        fw->snap_hb = (fw->hb_count == 0);
        fw->snap_mode = fw->mode;
        fw->snap_ready = 1;
    }
    apply_valves(fw);
    if (++fw->phase >= fw->cfg.period_ticks) fw->phase = 0;
    fw->t_us += fw->cfg.tick_us;
    while (fw->t_us >= 1000000u) {
        fw->t_us -= 1000000u;
        fw->t_sec++;
    }
}

/* ---- sending --------------------------------------------------------------------------------- */

typedef struct {
    char b[FW_TX_MAX];
    uint16_t len;
} line_t;

static void put(line_t *l, const char *s) {
    while (*s && l->len < FW_TX_MAX - 6) l->b[l->len++] = *s++;
}

static void put_u32(line_t *l, uint32_t v, uint8_t min_digits) {
    char d[10];
    uint8_t k = 0;
    do {
        d[k++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v || k < min_digits);
    while (k && l->len < FW_TX_MAX - 6) l->b[l->len++] = d[--k];
}

static void put_i32(line_t *l, int32_t v) {
    if (v < 0) {
        put(l, "-");
        put_u32(l, (uint32_t)(-(v + 1)) + 1u, 1);
    } else {
        put_u32(l, (uint32_t)v, 1);
    }
}

static void start(fw_t *fw, line_t *l, const char *kind) {
    l->len = 0;
    put(l, kind);
    put(l, " ");
    put_u32(l, fw->tx_seq, 1);
    if (!(FW_DEFECT(FW_D_SEQ_REPEAT) && kind[0] == 'H')) {
        fw->tx_seq = (uint16_t)(fw->tx_seq + 1u); /* a dropped line still uses its SEQ: the host sees a gap */
    }
}

static void finish(fw_t *fw, line_t *l) {
    static const char hex[] = "0123456789ABCDEF";
    uint16_t c = fw_crc16((const uint8_t *)l->b, l->len);
#ifdef FW_DEFECTS
    if (FW_DEFECT(FW_D_CRC)) c = crc16_from(0u, (const uint8_t *)l->b, l->len);
#endif
    l->b[l->len++] = '*';
    for (int8_t s = 12; s >= 0; s -= 4) l->b[l->len++] = hex[(c >> s) & 0xFu];
    l->b[l->len++] = '\n';
    if (hal_uart_write(l->b, l->len) != l->len) fw->stats.dropped_tx++;
}

/* Chamber i's reading in Pa as the P line sends it (*na: none). */
static int32_t reading(const fw_t *fw, uint8_t i, uint16_t raw, uint8_t *na) {
    int32_t p = fw_pressure(&fw->cal[i], raw, na);
    if (FW_DEFECT(FW_D_INVERTED)) p = -p;
    if (FW_DEFECT(FW_D_ZERO)) p += 2500;
    return p;
}

#ifdef FW_HOSTED
/* Tick every chamber's controller on the sample (readings raw, at sec + us / 1e6 s, after the period
 * that ran on held) and, while the board runs, make its command the pending one (latched at the next
 * sample instant). Checked inside the critical section: a SAFE or the watchdog between the sample and
 * here has already made the board safe, and the controller's command is then dropped. */
static void run_controllers(fw_t *fw, const uint16_t *raw, uint32_t sec, uint32_t us,
                            uint16_t held[][3]) {
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        uint8_t na;
        int32_t p = reading(fw, i, raw[i], &na);
        fw_ctl_report_t r;
        fw_ctl_tick(i, sec, us, p, na, held[i], &r);
        uint16_t on[2] = {duty_ticks(fw, r.u[FW_INLET]), duty_ticks(fw, r.u[FW_OUTLET])};
        hal_crit_enter();
        if (fw->mode == FW_RUN) {
            if (r.status < 0) { /* the library failed as a whole: its chamber vents, not the last command */
                r.u[FW_PUMP] = 0;
                r.u[FW_INLET] = 0;
                r.u[FW_OUTLET] = 1000;
                on[0] = 0;
                on[1] = fw->cfg.period_ticks;
            }
            for (uint8_t k = 0; k < 3; k++) fw->pending[i][k] = r.u[k];
            for (uint8_t k = 0; k < 2; k++) fw->pending_on[i][k] = on[k];
        }
        for (uint8_t k = 0; k < 3; k++) r.u[k] = fw->pending[i][k]; /* what the board will hold */
        hal_crit_exit();
        fw->report[i] = r;
    }
}

/* U seq: per chamber the command the board holds from the next sample instant (per-mille), the
 * estimated height (um) and pressure (Pa) and the controller's status; follows the P line of the sample
 * the controller ran on. */
static void send_report(fw_t *fw) {
    line_t l;
    start(fw, &l, "U");
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        const fw_ctl_report_t *r = &fw->report[i];
        for (uint8_t k = 0; k < 3; k++) {
            put(&l, " ");
            put_u32(&l, r->u[k], 1);
        }
        put(&l, " ");
        if (r->height_um == FW_NO_HEIGHT) {
            put(&l, "NA NA");
        } else {
            put_i32(&l, r->height_um);
            put(&l, " ");
            put_i32(&l, r->pressure_pa);
        }
        put(&l, " ");
        put_i32(&l, r->status);
    }
    finish(fw, &l);
}
#endif

void fw_poll(fw_t *fw) {
    uint16_t raw[FW_MAX_N] = {0};
    uint32_t sec, us;
    int32_t seq;
    uint8_t hb, mode;
#ifdef FW_HOSTED
    uint16_t held[FW_MAX_N][3];
#endif
    hal_crit_enter();
    uint8_t ready = fw->snap_ready;
    fw->snap_ready = 0;
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        raw[i] = fw->snap_raw[i];
#ifdef FW_HOSTED
        for (uint8_t k = 0; k < 3; k++) held[i][k] = fw->snap_held[i][k];
#endif
    }
    sec = fw->snap_sec;
    us = fw->snap_us;
    seq = fw->snap_seq;
    hb = fw->snap_hb;
    mode = fw->snap_mode;
    hal_crit_exit();
    if (!ready) return;
    if (!fw->session) {
#ifdef FW_HOSTED
        run_controllers(fw, raw, sec, us, held); /* the estimator keeps up between sessions */
#endif
        return;
    }
    line_t l;
    start(fw, &l, "P");
    put(&l, " ");
    if (sec) {
        put_u32(&l, sec, 1);
        put_u32(&l, us, 6);
    } else {
        put_u32(&l, us, 1);
    }
    put(&l, " ");
    if (seq == FW_NO_SEQ) {
        put(&l, "-");
    } else {
        put_u32(&l, (uint32_t)seq + (FW_DEFECT(FW_D_HELD) ? 1u : 0u), 1);
    }
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        uint8_t na;
        int32_t p = reading(fw, i, raw[i], &na);
        put(&l, " ");
        if (na) {
            put(&l, "NA");
        } else {
            put_i32(&l, p);
        }
    }
    finish(fw, &l);
#ifdef FW_HOSTED
    run_controllers(fw, raw, sec, us, held);
    send_report(fw);
#endif
    if (hb && !FW_DEFECT(FW_D_NO_HEARTBEAT)) {
        start(fw, &l, "HB");
        put(&l, mode == FW_RUN ? " RUN" : " SAFE");
        finish(fw, &l);
    }
}

/* ---- receiving ------------------------------------------------------------------------------- */

/* Decimal digits only (no sign, at least one), value <= max; returns 1 and *out when valid. */
static uint8_t parse_uint(const char *s, uint32_t max, uint32_t *out) {
    uint32_t v = 0;
    if (!*s) return 0;
    for (; *s; s++) {
        if (*s < '0' || *s > '9') return 0;
        v = v * 10u + (uint32_t)(*s - '0');
        if (v > max) return 0;
    }
    *out = v;
    return 1;
}

static int8_t hexval(char c) {
    if (c >= '0' && c <= '9') return (int8_t)(c - '0');
    if (c >= 'A' && c <= 'F') return (int8_t)(c - 'A' + 10);
    if (c >= 'a' && c <= 'f') return (int8_t)(c - 'a' + 10);
    return -1;
}

static void restart_watchdog(fw_t *fw) {
    hal_crit_enter();
    fw->silent_ticks = 0;
    hal_crit_exit();
}

static void on_hello(fw_t *fw, uint32_t seq, char **tok, uint8_t ntok) {
    hal_crit_enter();
    go_safe_now(fw, (int32_t)seq);
    fw->silent_ticks = 0;
    hal_crit_exit();
    fw->tx_seq = 0;
    line_t l;
    start(fw, &l, "VER");
    put(&l, " ");
    put_u32(&l, FW_DEFECT(FW_D_VERSION) ? 3u : FW_PROTOCOL_VERSION, 1);
    put(&l, " ");
    put_u32(&l, fw->cfg.n, 1);
    put(&l, " ");
    uint32_t period_us = fw->cfg.tick_us * fw->cfg.period_ticks;
    put_u32(&l, FW_DEFECT(FW_D_PERIOD) ? period_us + period_us / 4u : period_us, 1);
#ifdef FW_HOSTED
    put(&l, " hosted"); /* a host that drives a board by CMD does not recognise this VER and stops */
#endif
    finish(fw, &l);
#ifdef FW_HOSTED
    for (uint8_t i = 0; i < fw->cfg.n; i++) fw_ctl_init(i); /* a new session starts its controllers afresh */
#endif
    fw->session = (ntok == 3 && strcmp(tok[2], "2") == 0 && !FW_DEFECT(FW_D_VERSION));
    fw->rx_expect = (int32_t)((seq + 1u) & 0xFFFFu);
}

static uint8_t on_cmd(fw_t *fw, uint32_t seq, char **tok, uint8_t ntok) {
    uint16_t u[FW_MAX_N][3];
#ifdef FW_HOSTED
    (void)seq;
    (void)tok;
    (void)ntok;
    return 0; /* the board's controller commands: a host's command is refused */
#endif
    if (ntok != 2 + 3 * fw->cfg.n) return 0;
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        for (uint8_t k = 0; k < 3; k++) {
            uint32_t v;
            if (!parse_uint(tok[2 + 3 * i + k], 1000u, &v)) return 0;
            u[i][k] = (uint16_t)v;
        }
    }
    hal_crit_enter(); /* latched by the tick at the next sample instant */
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        for (uint8_t k = 0; k < 3; k++) fw->pending[i][k] = u[i][k];
        for (uint8_t k = 0; k < 2; k++) fw->pending_on[i][k] = duty_ticks(fw, u[i][FW_INLET + k]);
    }
    fw->pending_seq = (int32_t)seq;
    fw->mode = FW_RUN;
    hal_crit_exit();
    fw->stats.commands++;
    return 1;
}

#ifdef FW_HOSTED
/* TGT seq h_1 ... h_n: the chambers' target heights (um, 0..FW_HEIGHT_MAX_UM) for the board's
 * controllers, and the board runs them (RUN) until SAFE, HELLO or the watchdog. Only a hosted build
 * takes it (any other build counts it as an unknown line); any other count or value and the line is
 * ignored as a whole. */
static uint8_t on_tgt(fw_t *fw, uint32_t seq, char **tok, uint8_t ntok) {
    uint32_t h[FW_MAX_N] = {0};
    if (ntok != 2 + fw->cfg.n) return 0;
    for (uint8_t i = 0; i < fw->cfg.n; i++) {
        if (!parse_uint(tok[2 + i], FW_HEIGHT_MAX_UM, &h[i])) return 0;
    }
    for (uint8_t i = 0; i < fw->cfg.n; i++) fw_ctl_target(i, h[i]);
    hal_crit_enter(); /* the controller's next command is latched at the sample instant after its tick */
    fw->pending_seq = (int32_t)seq;
    fw->mode = FW_RUN;
    hal_crit_exit();
    fw->stats.commands++;
    return 1;
}
#endif

/* CAL seq ch zero gain: store a chamber's calibration (an extension for bench tools; the host's
 * SerialRig never sends it). Only while safe. */
static uint8_t on_cal(fw_t *fw, char **tok, uint8_t ntok) {
    uint32_t ch, zero, gain;
    if (ntok != 5 || fw->mode != FW_SAFE || !parse_uint(tok[2], fw->cfg.n - 1u, &ch) ||
        !parse_uint(tok[3], 0xFFFEu, &zero) || !parse_uint(tok[4], 0x7FFFu, &gain) || gain == 0) {
        return 0;
    }
    fw_cal_t cal = {(uint16_t)zero, (int16_t)gain};
    fw_set_cal(fw, (uint8_t)ch, cal);
    return 1;
}

static void handle_line(fw_t *fw, char *s, uint16_t len) {
    if (len && s[len - 1] == '\r' && !FW_DEFECT(FW_D_NO_CRLF)) s[--len] = '\0';
    if (len < 5 || s[len - 5] != '*') {
        fw->stats.bad_lines++;
        return;
    }
    uint16_t want = 0;
    for (uint8_t k = 0; k < 4; k++) {
        int8_t h = hexval(s[len - 4 + k]);
        if (h < 0) {
            fw->stats.bad_lines++;
            return;
        }
        want = (uint16_t)((want << 4) | (uint8_t)h);
    }
    len -= 5;
    if (fw_crc16((const uint8_t *)s, len) != want && !FW_DEFECT(FW_D_NO_CRC_CHECK)) {
        fw->stats.crc_errors++;
        return;
    }
    s[len] = '\0';
    char *tok[MAX_TOKENS];
    uint8_t ntok = 0;
    tok[ntok++] = s;
    for (char *p = s; *p; p++) {
        if ((uint8_t)*p < 0x20 || (uint8_t)*p > 0x7E) { /* not printable ASCII */
            fw->stats.bad_lines++;
            return;
        }
        if (*p == ' ') {
            *p = '\0';
            if (ntok == MAX_TOKENS) {
                fw->stats.bad_lines++;
                return;
            }
            tok[ntok++] = p + 1;
        }
    }
    uint32_t seq;
    if (ntok < 2 || !parse_uint(tok[1], 0xFFFFu, &seq)) {
        fw->stats.bad_lines++;
        return;
    }
    if (strcmp(tok[0], "HELLO") == 0) {
        fw->stats.lines++;
        on_hello(fw, seq, tok, ntok);
        return;
    }
    if (!fw->session) { /* a line from before the handshake */
        fw->stats.bad_lines++;
        return;
    }
    if (fw->rx_expect >= 0) fw->stats.seq_gaps += (uint16_t)((seq - (uint32_t)fw->rx_expect) & 0xFFFFu);
    fw->rx_expect = (int32_t)((seq + 1u) & 0xFFFFu);
    uint8_t ok = 1;
    if (strcmp(tok[0], "CMD") == 0) {
        ok = on_cmd(fw, seq, tok, ntok);
    } else if (strcmp(tok[0], "SAFE") == 0) {
        hal_crit_enter();
        go_safe_now(fw, (int32_t)seq); /* at once: the safe state does not wait for a sample instant */
        hal_crit_exit();
#ifdef FW_HOSTED
    } else if (strcmp(tok[0], "TGT") == 0) {
        ok = on_tgt(fw, seq, tok, ntok);
#endif
    } else if (strcmp(tok[0], "CAL") == 0) {
        ok = on_cal(fw, tok, ntok);
    } else if (strcmp(tok[0], "HB") != 0) {
        ok = 0;
    }
    if (!ok) {
        fw->stats.bad_lines++;
        return;
    }
    fw->stats.lines++;
    restart_watchdog(fw);
}

void fw_rx_byte(fw_t *fw, uint8_t c) {
    if (c == '\n') {
        if (fw->rx_overflow) {
            fw->stats.bad_lines++;
        } else {
            fw->rx[fw->rx_len] = '\0';
            handle_line(fw, fw->rx, fw->rx_len);
        }
        fw->rx_len = 0;
        fw->rx_overflow = 0;
    } else if (fw->rx_len < FW_RX_MAX) {
        fw->rx[fw->rx_len++] = (char)c;
    } else {
        fw->rx_overflow = 1; /* dropped up to the next newline, then counted as one bad line */
    }
}
