/* The hosted build's controllers (fw.h, FW_HOSTED): the chamber library `hbma-ctrl codegen CONFIG --library`
 * generates (hbma.h), one workspace per chamber, all started with the generation scenario's parameters.
 * Converts between the core's integers (per-mille, um, Pa, the clock's seconds and microseconds) and the
 * library's SI reals. */
#include <math.h>

#include "fw.h"
#include "hbma.h"

static hbma_workspace_t ws[FW_MAX_N]; /* about 240 KB each (sizeof is the library's) */
static hbma_params_t params;
static uint8_t have_params;

/* A command in [0, 1] as per-mille, rounded half up as the host's link rounds it; the library keeps its
 * commands in [0, 1], so the bounds only guard the conversion. */
static uint16_t permille(hbma_real x) {
    hbma_real v = (hbma_real)floor((double)x * 1000.0 + 0.5);
    if (!(v > 0)) return 0;
    return v >= 1000 ? 1000u : (uint16_t)v;
}

void fw_ctl_init(uint8_t ch) {
    if (!have_params) {
        hbma_default_params(&params);
        have_params = 1;
    }
    hbma_init(&ws[ch], &params);
}

void fw_ctl_target(uint8_t ch, uint32_t height_um) {
    hbma_set_target(&ws[ch], (hbma_real)((double)height_um * 1e-6), 0);
}

void fw_ctl_tick(uint8_t ch, uint32_t sec, uint32_t us, int32_t p_pa, uint8_t na, const uint16_t held[3],
                 fw_ctl_report_t *out) {
    hbma_real h[3], u[3];
    for (uint8_t k = 0; k < 3; k++) {
        h[k] = (hbma_real)(held[k] / 1000.0);
        u[k] = h[k];
    }
    hbma_real t = (hbma_real)((double)sec + (double)us * 1e-6);
    int rc = hbma_tick(&ws[ch], t, na ? (hbma_real)NAN : (hbma_real)p_pa, h, u);
    out->status = (int8_t)rc;
    for (uint8_t k = 0; k < 3; k++) out->u[k] = rc < 0 ? held[k] : permille(u[k]);
    hbma_outputs_t o;
    hbma_outputs(&ws[ch], &o);
    if (rc < 0 || !isfinite((double)o.height_m) || !isfinite((double)o.pressure_pa)) {
        out->height_um = FW_NO_HEIGHT;
        out->pressure_pa = 0;
    } else {
        out->height_um = (int32_t)floor((double)o.height_m * 1e6 + 0.5);
        out->pressure_pa = (int32_t)floor((double)o.pressure_pa + 0.5);
    }
}
