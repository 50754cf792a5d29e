/* The rig firmware's core: line protocol version 2 (hbma_ctrl/system/serial_link.py's firmware side),
 * hardware independent, no malloc. A board calls fw_init once, fw_tick from its timer interrupt every
 * tick, fw_rx_byte for every received byte and fw_poll from its main loop (see hal.h for what the
 * core asks of the board, and firmware/README.md).
 *
 * Timing, in ticks of tick_us: every period_ticks ticks is a sample instant. At a sample instant the
 * tick snapshots every chamber's ADC reading and the SEQ of the command held over the period that
 * ends, then latches the newest command received (a CMD arriving mid-period waits for the next sample
 * instant); fw_poll then sends the P line (and HB every hb_periods samples). SAFE, HELLO and the
 * watchdog (timeout_ticks without a valid host line while running) act at once. The valves' PWM
 * period is the sample period: a valve at duty d is open for the first round(d * period_ticks / 1000)
 * ticks of every period, so each period holds exactly its command's duty. */
#ifndef HBMA_FW_H
#define HBMA_FW_H

#include <stdint.h>

#define FW_PROTOCOL_VERSION 2

#ifndef FW_MAX_N
#define FW_MAX_N 4 /* chambers this build can serve */
#endif
#ifndef FW_RX_MAX
#define FW_RX_MAX 128 /* longest host line accepted, bytes without the newline */
#endif
#ifdef FW_HOSTED
#define FW_TX_MAX (40 + 40 * FW_MAX_N) /* longest line sent: U with FW_MAX_N chambers' reports */
#else
#define FW_TX_MAX (40 + 8 * FW_MAX_N) /* longest line sent: P with FW_MAX_N pressures */
#endif
#define FW_NO_SEQ (-1)                /* held by the firmware's own watchdog or since boot: "-" */
#define FW_ADC_NONE 0xFFFFu           /* hal_adc: no reading (sent as NA) */
#ifndef FW_ADC_OPEN
#define FW_ADC_OPEN 64 /* readings below this are an open sensor line (NA) */
#endif
/* Default calibration: an MPX5100-type gauge sensor on 5 V (0.2 V at 0 Pa, 45 mV/kPa) read as 16
 * times oversampled 10-bit counts: 655 counts at zero, 6.788 Pa per count. */
#ifndef FW_CAL_ZERO
#define FW_CAL_ZERO 655
#endif
#ifndef FW_CAL_GAIN
#define FW_CAL_GAIN 6788
#endif
#define FW_NVM_BYTES_PER_CH 6 /* zero (u16), gain (i16), CRC-16 of those four bytes (u16) */

enum { FW_PUMP = 0, FW_INLET = 1, FW_OUTLET = 2 };

/* Defects a host build (FW_DEFECTS defined: the POSIX board only) can inject, one bit each, to show
 * what a bring-up check catches; every other build compiles them out (FW_DEFECT(d) is 0). */
enum {
    FW_D_CRC = 1u << 0,          /* sends a checksum of another CRC-16 variant (init 0) */
    FW_D_STUCK_INLET = 1u << 1,  /* chamber 0's inlet never opens */
    FW_D_INVERTED = 1u << 2,     /* pressures sent with the wrong sign */
    FW_D_NO_WATCHDOG = 1u << 3,  /* host silence never makes it safe */
    FW_D_PERIOD = 1u << 4,       /* VER declares a sample period 25 % longer than it samples */
    FW_D_NO_HEARTBEAT = 1u << 5, /* no HB lines */
    FW_D_SEQ_REPEAT = 1u << 6,   /* HB lines reuse the next P line's SEQ */
    FW_D_NO_CRLF = 1u << 7,      /* a '\r' before the newline stays in the line (it fails its checksum) */
    FW_D_ZERO = 1u << 8,         /* pressures 2.5 kPa high (a sensor zero off) */
    FW_D_NO_CRC_CHECK = 1u << 9, /* acts on host lines whatever their checksum */
    FW_D_HELD = 1u << 10,        /* P lines name the SEQ after the held command's */
    FW_D_VERSION = 1u << 11      /* answers HELLO with protocol version 3 */
};
#ifdef FW_DEFECTS
extern uint16_t fw_defects; /* the defects injected, FW_D_* bits */
#define FW_DEFECT(d) (fw_defects & (d))
#else
#define FW_DEFECT(d) 0
#endif
enum { FW_SAFE = 0, FW_RUN = 1 };

#if defined(FW_HOSTED) && defined(__AVR__)
#error "FW_HOSTED: the generated controller library needs about 240 KB of RAM and 1 MB of flash; an ATmega has 2-8 KB of RAM. Host it on the POSIX board (make host-hosted LIB=DIR) or a Cortex-M part"
#endif
#ifdef FW_HOSTED
/* A hosted build (FW_HOSTED) runs a controller on the board: the chamber library that
 * `hbma-ctrl codegen CONFIG --library` generates, one instance per chamber (src/fw_ctl.c; the unit tests
 * bring a fake). At every sample instant the tick snapshots the readings and the command held over the
 * period that ends; fw_poll then ticks each chamber's controller on them and, while the board runs,
 * makes its command the pending one, latched at the next sample instant as a CMD would be. The host
 * sends targets (TGT) instead of commands; SAFE, HELLO and the watchdog act as in every build. */
#define FW_NO_HEIGHT INT32_MIN /* fw_ctl_report_t.height_um: no estimate */
#define FW_HEIGHT_MAX_UM 1000000u /* largest target a TGT line takes, um */

/* One controller tick's outcome: its command (per-mille: pump, inlet, outlet), the estimated height (um)
 * and pressure (Pa), and the library's status code (0 ok, 1 the controller's step failed and the
 * supervisor's fallback is out, negative: an error, no command: the core holds the chamber vented). */
typedef struct {
    uint16_t u[3];
    int32_t height_um, pressure_pa;
    int8_t status;
} fw_ctl_report_t;

/* Start (or restart) chamber ch's controller: the estimator at its prior, the target 0. */
void fw_ctl_init(uint8_t ch);
/* Chamber ch's target height from now on, um. */
void fw_ctl_target(uint8_t ch, uint32_t height_um);
/* One period of chamber ch at firmware time sec + us / 1e6 s: the reading p_pa (none when na), the
 * command held over the period it ends (per-mille) -> *out. */
void fw_ctl_tick(uint8_t ch, uint32_t sec, uint32_t us, int32_t p_pa, uint8_t na, const uint16_t held[3],
                 fw_ctl_report_t *out);
#endif

/* Pressure calibration of one chamber: p [Pa] = (counts - zero) * gain / 1000, gain in mPa/count. */
typedef struct {
    uint16_t zero;
    int16_t gain;
} fw_cal_t;

typedef struct {
    uint8_t n;              /* chambers, 1..FW_MAX_N */
    uint32_t tick_us;       /* timer tick, us */
    uint16_t period_ticks;  /* sample period = valve PWM period, ticks */
    uint16_t hb_periods;    /* heartbeat every this many sample periods */
    uint32_t timeout_ticks; /* host silence before the watchdog goes safe, ticks */
} fw_cfg_t;

typedef struct {
    uint16_t lines, crc_errors, bad_lines, seq_gaps, commands, dropped_tx, overruns; /* lines: valid host lines */
} fw_stats_t;

typedef struct {
    fw_cfg_t cfg;
    fw_cal_t cal[FW_MAX_N];
    fw_stats_t stats;
    /* main context: the line being received and the session */
    char rx[FW_RX_MAX + 1];
    uint16_t rx_len;
    uint8_t rx_overflow;
    uint8_t session;
    uint16_t tx_seq;
    int32_t rx_expect; /* next host SEQ expected, -1 none */
    /* shared with the tick (written by main only inside hal_crit_enter/exit) */
    volatile uint16_t pending[FW_MAX_N][3]; /* newest command received, per-mille */
    volatile uint16_t pending_on[FW_MAX_N][2]; /* its inlet, outlet open ticks per period */
    volatile int32_t pending_seq;
    volatile uint16_t held[FW_MAX_N][3]; /* command held over the current period */
    volatile int32_t held_seq;
    volatile uint16_t on_ticks[FW_MAX_N][2]; /* inlet, outlet open ticks per period under held */
    volatile uint8_t mode;
    volatile uint32_t silent_ticks;
    volatile uint16_t phase; /* tick within the sample period, 0 = sample instant */
    volatile uint16_t hb_count;
    volatile uint32_t t_sec, t_us; /* firmware time since boot */
    /* the newest sample instant's snapshot, for fw_poll */
    volatile uint8_t snap_ready, snap_hb, snap_mode;
    volatile uint32_t snap_sec, snap_us;
    volatile int32_t snap_seq;
    volatile uint16_t snap_raw[FW_MAX_N];
#ifdef FW_HOSTED
    volatile uint16_t snap_held[FW_MAX_N][3]; /* the command held over the period that ends */
    fw_ctl_report_t report[FW_MAX_N];         /* the controller's newest tick, for the U line */
#endif
} fw_t;

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of len bytes. */
uint16_t fw_crc16(const uint8_t *data, uint16_t len);

/* Reset the state (safe, no session), load the calibration from NVM (defaults where it is blank or
 * corrupt) and apply the safe outputs. cfg is copied. */
void fw_init(fw_t *fw, const fw_cfg_t *cfg);

/* Timer interrupt: one tick (PWM, clock, watchdog, sample instant). */
void fw_tick(fw_t *fw);

/* One received byte (main context); a complete line is parsed and acted on. */
void fw_rx_byte(fw_t *fw, uint8_t c);

/* Main loop: send the newest sample's P line (and HB when due) if a session is open. */
void fw_poll(fw_t *fw);

/* Pressure in Pa of counts under cal; *na set when the reading is none or an open line. */
int32_t fw_pressure(const fw_cal_t *cal, uint16_t counts, uint8_t *na);

/* Store chamber ch's calibration in NVM and use it. */
void fw_set_cal(fw_t *fw, uint8_t ch, fw_cal_t cal);

#endif
