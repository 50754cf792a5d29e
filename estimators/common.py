"""Numerics and settings shared by the EKF and the UKF (SI units).

Guards that filterpy leaves open (STYLE: "Avoid ... plain P = (I - K H) P updates and unchecked
Cholesky factorisations"): every covariance the filters keep goes through :func:`guard_cov`
(symmetrised, eigenvalues floored), gains come from linear solves, never inverses, and the update
is in Joseph form, which stays positive semi-definite for any gain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import is_finite, is_nan
from hbma_ctrl.core.params import check_range
from hbma_ctrl.models.actuation import check_delays
from hbma_ctrl.models.chamber import STATE_SCALE
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE, DEFAULT_SENSOR_DELAY, DEFAULT_VALVE_DELAY

__all__ = ["FilterSettings", "guard_cov", "classify_measurement", "physical_reading_bounds", "MEAS_OK",
           "MEAS_MISSING", "MEAS_SATURATED", "MEAS_OUTLIER", "VACUUM_GAUGE", "nis_gate", "INFLATION_MAX"]

MEAS_OK, MEAS_MISSING, MEAS_SATURATED, MEAS_OUTLIER = "ok", "missing", "saturated", "outlier"
#: the most a re-opened gate inflates the prior covariance (a factor on P): where the pressure hardly
#: depends on the state (near a limit point, H P H^T -> 0) no inflation explains the reading, and
#: an unbounded one turns the update into a jump off the model's tables
INFLATION_MAX = 100.0
#: the lowest gauge pressure there is (absolute vacuum at the standard atmosphere), Pa
VACUUM_GAUGE = -101325.0
#: the pump-flow, modulus and dead-volume factors are kept in this range, their initial values too
#: (off by more is a broken rig, not a bias)
FACTOR_RANGE = (0.5, 2.0)


@dataclass
class FilterSettings:
    """Settings shared by :class:`~hbma_ctrl.estimators.ekf.EKF` and :class:`~hbma_ctrl.estimators.ukf.UKF` (SI).

    Fields
    ------
    sample_period : time between steps, s, (0, 1]. A step whose ``t`` is k periods after the last
        one predicts k times (k = 0: update only).
    integrator : 'rk4' | 'euler': the simulator's fixed-step scheme for the model's ODE.
    nsub : integrator sub-steps per sample period, [1, 50] (1: one RK4 step per 10 ms sample; 2
        gave the same accuracy on the protocol subset at twice the cost).
    newton : Newton iterations of the shape projection per sub-step, [1, 10] (3: a state far off
        the constraint, e.g. after a reset, is projected back within one step).
    noise_std : pressure-sensor noise, one sigma, Pa, (0, 1e4] (the rig's: 200 Pa).
    model_rel_std : relative error of the model's pressure law at a given shape (-), [0, 1]; the
        measurement variance is noise_std^2 + (model_rel_std p)^2. Covers the modulus mismatch.
    sensor_range : readings >= this are saturated (the true pressure is at least this), Pa.
    saturation_std : one sigma of the one-sided pseudo-measurement "p >= sensor_range" applied
        when the prediction is below the range, Pa, (0, 1e5].
    flow_rel_std : relative one-sigma error of the model's mass flow (compressor map, valves,
        dead volume), per sample: process noise on the gas mass is (flow_rel_std |q| dt)^2 plus
        (mass_std_abs)^2 per second, [0, 1].
    mass_std_abs : gas-mass random walk, kg/sqrt(s), [0, 1e-5].
    load_std : load random walk, N/sqrt(s), [0, 100] (how fast the load may change).
    load_init : initial load guess, N; None = unknown: the membrane is taken as resting until the
        pressure shows a lift-off (see :mod:`hbma_ctrl.estimators.ekf`). load_init_std its one sigma, N.
    load_rest_std : one sigma of the load while the membrane rests flat, N (W is unobservable
        then, only W >= pi r1^2 p is known; the value only keeps the covariance regular).
    lift_threshold, lift_drift : lift-off detector while resting: a CUSUM of the normalised
        innovation shortfall (-nu/sqrt(S) - lift_drift, less a fixed 5 % of the flat prediction's
        rise over the sample in sigmas: :data:`hbma_ctrl.estimators.ekf_step.LIFT_RISE_DRIFT`) above
        lift_threshold declares a lift-off (the pressure rises slower than a flat membrane allows),
        (0, 1e3] and [0, 10]. Without a load prior a resting filter also takes the membrane as lifted
        when b / c falls far below its prior (:func:`hbma_ctrl.estimators.ekf_step.flat_ratio_min`).
    lift_load_rel_std : relative one sigma of the load right after a detected lift-off, [0, 10].
    flow_factor_std : random walk of the pump-flow factor b, 1/sqrt(s), [0, 10];
        flow_factor_init its initial value (-, [0.5, 2]: 1 = the nominal pump map; a calibration's
        ``flow_scale``), flow_factor_init_std its initial one sigma, [0, 10].
    dead_volume_std : random walk of the dead-volume factor c, 1/sqrt(s), [0, 10];
        dead_volume_init its initial value ([0.5, 2]; a calibration's V0 over the nominal),
        dead_volume_init_std its initial one sigma, [0, 10]. While the membrane is
        flat the pressure's rise gives only b / c; the two prior spreads set how that ratio is
        shared until venting (c alone) or the moving membrane separates them.
    modulus_std : random walk of the modulus factor k, 1/sqrt(s), [0, 10]; modulus_init its initial
        value ([0.5, 2]; a calibration's ``modulus_scale``), modulus_init_std its initial one sigma, [0, 10].
    change_threshold : a load change is declared when the CUSUM of (NIS - change_drift) exceeds this
        (-), (0, 1e6]; the load's variance then grows by change_std^2 (N^2) so it re-converges.
    change_drift : NIS level tolerated by the CUSUM (-), [1, 100].
    change_std : one sigma added to the load on a detected change, N, [0, 1000].
    load_min, load_max : the load state is kept in [load_min, load_max], N; below zero the model
        sees no load (a dead zone that keeps a zero load unbiased), the reported F is >= 0.
    mass_init_std : one sigma of the initial gas mass, kg.
    output_rel_std : relative model-form error added to the reported variances of h1, h2, h and F
        (-), [0, 1]: what the state's covariance cannot know (the rig's platform dynamics and the
        membrane law's residual error); it changes the reported std and NEES, not the estimate
        (2 %: tests/test_estimator_consistency.py).
    force_std_floor : absolute model-form error added to the reported force std, N, [0, 100] (the
        load is only weakly separable from the modulus: a resolution of about 0.1 N).
    cov_floor : eigenvalue floor of the covariance, relative to the state scales (m: 1e-6 kg,
        W: 1 N, factors: 1), [0, 1e-3].
    compile : compile the model to C (cached) for speed; False = casadi's virtual machine.
    load_prior : 'unknown' (default: the load is learnt from the lift-off) or 'nominal': a scene
        that knows its calibrated load (the protocol's weights) starts the load at the trial's
        nominal weight, with one sigma load_prior_rel_std x that weight (+0.01 N). Applied per trial
        by :func:`hbma_ctrl.app.scenes.evaluate.make_filter`; load changes are still detected and tracked.
    load_prior_rel_std : relative one sigma of the nominal load prior, [0, 10].
    reading_min : the lowest reading that can be physical, Pa gauge, [-101325, 0] (default: vacuum);
        below it a reading is an outlier (predict only, counted), never an update.
    reading_max_rel : a reading above this multiple of ``sensor_range`` cannot come from the sensor
        (a saturated sensor reads its range), [1, 1000]: an outlier, not a saturation.
    gate_nis : innovation gate: a reading whose normalised innovation squared (NIS, chi-square with
        one degree of freedom) exceeds this is an outlier, (1, 1e6] (400: twenty sigma; the model's own
        transients reach about 120, at a touch-down while venting, and a load step's first samples
        feed the load-change detector at far less).
    gate_reopen : after this many gated readings in a row the gate re-opens, [1, 1000]: the
        covariance is inflated until the reading's NIS equals ``gate_nis`` (by at most
        ``INFLATION_MAX``) and the reading is used, and so on until a reading passes unaided (a real
        fast transient, e.g. a load slammed on, cannot lock the filter out).
    membrane : the model's membrane law, 'cap' (the spherical cap, README Model §3) or 'exact' (the
        exact axisymmetric membrane's tables in the cap's chart, README Model §9; the first use of a
        material builds its table, then it loads from the disk cache). Default exact
        (:mod:`hbma_ctrl.models.defaults`).
    max_gap : longest time, s, a step predicts over, [sample_period, 3600]: after a longer gap (a
        paused stream, a wall-clock timestamp) the filter predicts ``max_gap`` only and widens the
        covariance by its initial spread (the commands during the gap are unknown).
    valve_delay : the valves open and shut this long after their command, s, [0, 0.1] (default 5 ms,
        a small solenoid valve's datasheet switching time; 3-10 ms is usual). The pump's speed acts at once.
    sensor_delay : the pressure sensor reads the chamber this long late, s, [0, 0.1] (default 3 ms: a
        sensor behind a short tube). Both are modelled as dead times on the commands
        (:class:`hbma_ctrl.models.actuation.CommandTiming`); the start-up calibration uses the same.
    """

    sample_period: float = 0.01
    integrator: str = "rk4"
    nsub: int = 1
    newton: int = 3
    noise_std: float = 200.0
    model_rel_std: float = 0.05
    sensor_range: float = 35e3
    saturation_std: float = 2e3
    flow_rel_std: float = 0.15
    mass_std_abs: float = 2e-8
    load_std: float = 0.05
    load_init: float | None = None
    load_init_std: float = 3.0
    load_rest_std: float = 1.0
    lift_threshold: float = 6.0
    lift_drift: float = 0.3
    lift_load_rel_std: float = 0.2
    flow_factor_std: float = 0.02
    flow_factor_init: float = 1.0
    flow_factor_init_std: float = 0.15
    modulus_std: float = 0.002
    modulus_init: float = 1.0
    modulus_init_std: float = 0.15
    dead_volume_std: float = 0.0
    dead_volume_init: float = 1.0
    dead_volume_init_std: float = 0.2
    change_threshold: float = 20.0
    change_drift: float = 4.0
    change_std: float = 3.0
    load_min: float = -1.0
    load_max: float = 100.0
    mass_init_std: float = 1e-8
    output_rel_std: float = 0.02
    force_std_floor: float = 0.1
    cov_floor: float = 1e-12
    compile: bool = True
    load_prior: str = "unknown"
    load_prior_rel_std: float = 0.1
    reading_min: float = VACUUM_GAUGE
    reading_max_rel: float = 1.5
    gate_nis: float = 400.0
    gate_reopen: int = 5
    max_gap: float = 1.0
    membrane: str = DEFAULT_MEMBRANE
    valve_delay: float = DEFAULT_VALVE_DELAY
    sensor_delay: float = DEFAULT_SENSOR_DELAY

    def validate(self) -> "FilterSettings":
        w = "estimator"
        check_range(w, "sample_period", self.sample_period, 0.0, 1.0, "s", lo_open=True)
        if self.integrator not in ("rk4", "euler"):
            raise ValueError(f"{w}.integrator = '{self.integrator}': allowed rk4, euler")
        for name, lo, hi in (("nsub", 1, 50), ("newton", 1, 10)):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
                raise ValueError(f"{w}.{name} = {v!r} must be an integer in [{lo}, {hi}]")
        check_range(w, "noise_std", self.noise_std, 0.0, 1e4, "Pa", lo_open=True)
        check_range(w, "model_rel_std", self.model_rel_std, 0.0, 1.0)
        check_range(w, "sensor_range", self.sensor_range, 1e3, 1e6, "Pa")
        check_range(w, "saturation_std", self.saturation_std, 0.0, 1e5, "Pa", lo_open=True)
        check_range(w, "flow_rel_std", self.flow_rel_std, 0.0, 1.0)
        check_range(w, "mass_std_abs", self.mass_std_abs, 0.0, 1e-5, "kg/sqrt(s)")
        check_range(w, "load_std", self.load_std, 0.0, 100.0, "N/sqrt(s)")
        if self.load_prior not in ("unknown", "nominal"):
            raise ValueError(f"{w}.load_prior = {self.load_prior!r}: allowed unknown, nominal")
        check_range(w, "load_prior_rel_std", self.load_prior_rel_std, 0.0, 10.0)
        if self.load_init is not None:
            check_range(w, "load_init", self.load_init, -1.0, 1000.0, "N")
        check_range(w, "lift_threshold", self.lift_threshold, 0.0, 1e3, lo_open=True)
        check_range(w, "lift_drift", self.lift_drift, 0.0, 10.0)
        check_range(w, "lift_load_rel_std", self.lift_load_rel_std, 0.0, 10.0)
        check_range(w, "flow_factor_std", self.flow_factor_std, 0.0, 10.0, "1/sqrt(s)")
        check_range(w, "flow_factor_init_std", self.flow_factor_init_std, 0.0, 10.0)
        for name in ("flow_factor_init", "modulus_init", "dead_volume_init"):
            check_range(w, name, getattr(self, name), FACTOR_RANGE[0], FACTOR_RANGE[1])
        check_range(w, "modulus_std", self.modulus_std, 0.0, 10.0, "1/sqrt(s)")
        check_range(w, "modulus_init_std", self.modulus_init_std, 0.0, 10.0)
        check_range(w, "dead_volume_std", self.dead_volume_std, 0.0, 10.0, "1/sqrt(s)")
        check_range(w, "dead_volume_init_std", self.dead_volume_init_std, 0.0, 10.0)
        check_range(w, "load_init_std", self.load_init_std, 0.0, 1000.0, "N", lo_open=True)
        check_range(w, "load_rest_std", self.load_rest_std, 0.0, 1000.0, "N", lo_open=True)
        check_range(w, "change_threshold", self.change_threshold, 0.0, 1e6, lo_open=True)
        check_range(w, "change_drift", self.change_drift, 1.0, 100.0)
        check_range(w, "change_std", self.change_std, 0.0, 1000.0, "N")
        check_range(w, "load_min", self.load_min, -10.0, 0.0, "N")
        check_range(w, "load_max", self.load_max, 0.0, 1e4, "N", lo_open=True)
        check_range(w, "mass_init_std", self.mass_init_std, 0.0, 1e-3, "kg", lo_open=True)
        check_range(w, "output_rel_std", self.output_rel_std, 0.0, 1.0)
        check_range(w, "force_std_floor", self.force_std_floor, 0.0, 100.0, "N")
        check_range(w, "cov_floor", self.cov_floor, 0.0, 1e-3)
        check_range(w, "reading_min", self.reading_min, VACUUM_GAUGE, 0.0, "Pa")
        check_range(w, "reading_max_rel", self.reading_max_rel, 1.0, 1000.0)
        check_range(w, "gate_nis", self.gate_nis, 1.0, 1e6, lo_open=True)
        if not isinstance(self.gate_reopen, int) or isinstance(self.gate_reopen, bool) or \
                not 1 <= self.gate_reopen <= 1000:
            raise ValueError(f"{w}.gate_reopen = {self.gate_reopen!r} must be an integer in [1, 1000]")
        check_range(w, "max_gap", self.max_gap, self.sample_period, 3600.0, "s")
        check_delays(w, self.valve_delay, self.sensor_delay)
        if self.membrane not in ("cap", "exact"):
            raise ValueError(f"{w}.membrane = {self.membrane!r}: allowed cap, exact")
        if not isinstance(self.compile, bool):
            raise ValueError(f"{w}.compile = {self.compile!r} must be true or false")
        return self

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]




def guard_cov(P: np.ndarray, floor: float, scale: np.ndarray = STATE_SCALE) -> np.ndarray:
    """Symmetrise P and floor its eigenvalues at ``floor`` in scaled coordinates (SPD out)."""
    ss = np.outer(scale, scale)
    S = 0.5 * (P + P.T) / ss
    try:  # all eigenvalues >= floor  <=>  S - floor I has a Cholesky factor (cheap test)
        np.linalg.cholesky(S - floor * np.eye(S.shape[0]))
        return S * ss
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(S)
    if w.min() < floor or not np.all(np.isfinite(w)):
        w = np.maximum(np.nan_to_num(w, nan=floor), floor)
        S = (V * w) @ V.T
        S = 0.5 * (S + S.T)
    return S * ss


def physical_reading_bounds(sensor_range: float, reading_min: float = VACUUM_GAUGE,
                            reading_max_rel: float = 1.5) -> tuple[float, float]:
    """(lowest, highest) reading, Pa gauge, a pressure sensor of this range can give: vacuum (or a
    higher floor) and ``reading_max_rel`` times the range. Outside is an outlier."""
    return float(max(reading_min, VACUUM_GAUGE)), float(reading_max_rel * sensor_range)


def classify_measurement(z, sensor_range: float, reading_min: float = -math.inf,
                         reading_max: float = math.inf) -> str:
    """One pressure reading (Pa): 'missing' (None or NaN: a dropout), 'outlier' (cannot be physical:
    +-inf, not a number, below ``reading_min`` or above ``reading_max``), 'saturated' (>= sensor
    range) or 'ok'."""
    if isinstance(z, float) and reading_min <= z <= reading_max and z < sensor_range:
        return MEAS_OK  # the common case, decided in one test (NaN fails every comparison)
    if z is None:
        return MEAS_MISSING
    if isinstance(z, (str, bytes, bool)):
        return MEAS_OUTLIER  # "12.3" from a serial line is a parser's bug, not a reading
    try:
        zf = float(z)
    except (TypeError, ValueError):
        return MEAS_OUTLIER
    if math.isnan(zf):
        return MEAS_MISSING
    if math.isinf(zf) or zf < reading_min or zf > reading_max:
        return MEAS_OUTLIER
    if zf >= sensor_range:
        return MEAS_SATURATED
    return MEAS_OK


def classify_expr(z, sensor_range: float, reading_min: float, reading_max: float) -> tuple:
    """:func:`classify_measurement` on casadi expressions, elementwise, for loops without Python:
    (missing, outlier, saturated, ok), each 1 where the reading z (Pa; NaN a dropout) is of that kind."""
    missing = is_nan(z)
    outlier = ca.logic_and(ca.logic_not(missing),
                           ca.logic_or(ca.logic_not(is_finite(z)), ca.logic_or(z < reading_min, z > reading_max)))
    valid = ca.logic_not(ca.logic_or(missing, outlier))
    return missing, outlier, ca.logic_and(valid, z >= sensor_range), ca.logic_and(valid, z < sensor_range)


def nis_gate(innovation: float, hph: float, R: float, gate: float) -> tuple[float, float]:
    """(NIS, inflation) of a scalar innovation (Pa) with prior variance ``hph = H P H^T`` and
    measurement variance R (Pa^2): NIS = innovation^2 / (hph + R), and the factor on P that brings
    the NIS down to ``gate`` (1 when it is already within; at most :data:`INFLATION_MAX`, above 1
    whenever the NIS exceeds the gate)."""
    S = hph + R
    nis = innovation * innovation / S
    if nis <= gate:
        return nis, 1.0
    need = (innovation * innovation / gate - R) / hph if hph > 0.0 else INFLATION_MAX
    return nis, min(max(need, 1.0 + 1e-9), INFLATION_MAX)
