"""Numerics and settings shared by the EKF and the UKF (SI units).

Guards that filterpy leaves open (STYLE: "Avoid ... plain P = (I - K H) P updates and unchecked
Cholesky factorisations"): every covariance the filters keep goes through :func:`guard_cov`
(symmetrised, eigenvalues floored), gains come from linear solves, never inverses, and the update
is in Joseph form, which stays positive semi-definite for any gain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import is_finite, is_nan
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.models.actuation import sensor_delay_setting, valve_delay_setting
from hbma_ctrl.models.chamber import STATE_SCALE
from hbma_ctrl.models.reduced import MEMBRANES
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
class FilterSettings(Settings):
    """Settings shared by :class:`~hbma_ctrl.estimators.ekf.EKF` and :class:`~hbma_ctrl.estimators.ukf.UKF` (SI;
    each field's unit, range and one-line doc are in its declaration).

    A step whose ``t`` is k sample periods after the last one predicts k times (k = 0: update only).
    The measurement variance is noise_std^2 + (model_rel_std p)^2 (model_rel_std covers the modulus
    mismatch); the gas mass's process noise is (flow_rel_std |q| dt)^2 plus mass_std_abs^2 per second.
    A saturated reading is the one-sided observation "p >= sensor_range" with ``saturation_std``.

    Load: with ``load_init`` None the membrane is taken as resting until the pressure shows a lift-off
    (see :mod:`hbma_ctrl.estimators.ekf`); while it rests W is unobservable, only W >= pi r1^2 p is known.
    The lift-off detector is a CUSUM of the normalised innovation shortfall (-nu/sqrt(S) - lift_drift,
    less a fixed 5 % of the flat prediction's rise over the sample in sigmas:
    :data:`hbma_ctrl.estimators.ekf_step.LIFT_RISE_DRIFT`); above lift_threshold the membrane has lifted.
    Without a load prior a resting filter also takes the membrane as lifted when b / c falls far below
    its prior (:func:`hbma_ctrl.estimators.ekf_step.flat_ratio_min`). A load change is declared when
    the CUSUM of (NIS - change_drift) exceeds change_threshold; the load's variance then grows by
    change_std^2. The load state is kept in [load_min, load_max]; below zero the model sees no load
    (a dead zone that keeps a zero load unbiased), the reported F is >= 0. ``load_prior`` 'nominal'
    (a scene that knows its calibrated load) starts each trial's load at its nominal weight, applied
    by :func:`hbma_ctrl.app.scenes.evaluate.make_filter`.

    Factors: while the membrane is flat the pressure's rise gives only b / c; the prior spreads of the
    pump-flow and dead-volume factors set how that ratio is shared until venting (c alone) or the
    moving membrane separates them. output_rel_std is what the state's covariance cannot know (the
    rig's platform dynamics, the membrane law's residual error): it changes the reported std and NEES,
    not the estimate (2 %: tests/test_estimator_consistency.py).

    Gate: a reading whose NIS exceeds gate_nis is an outlier (400: twenty sigma; the model's own
    transients reach about 120); after gate_reopen gated readings in a row the covariance is inflated
    until the reading's NIS equals gate_nis (by at most ``INFLATION_MAX``) and the reading is used,
    so a real fast transient cannot lock the filter out. After a gap longer than max_gap the filter
    predicts max_gap only and widens the covariance by its initial spread. The valve and sensor delays
    are dead times on the commands (:class:`hbma_ctrl.models.actuation.CommandTiming`); the start-up
    calibration uses the same. The membrane law 'exact' is the exact membrane's tables in the cap's
    chart (docs/concepts/model.md §9; built on a material's first use, then loaded from the disk cache).
    """

    WHERE = "estimator"

    sample_period: float = setting(0.01, lo=0.0, hi=1.0, lo_open=True, unit="s", doc="time between steps")
    integrator: str = setting("rk4", choices=("rk4", "euler"), doc="the filter model's fixed-step scheme")
    nsub: int = setting(1, integer=True, lo=1, hi=50, unit="steps", doc="integrator sub-steps per sample")
    newton: int = setting(3, integer=True, lo=1, hi=10, unit="iterations",
                        doc="Newton iterations of the shape projection per sub-step")
    noise_std: float = setting(200.0, lo=0.0, hi=1e4, lo_open=True, unit="Pa", user="kPa",
                               doc="pressure-sensor noise, one sigma (a scenario: the rig's unless written)")
    model_rel_std: float = setting(0.05, lo=0.0, hi=1.0, doc="relative error of the model's pressure law")
    sensor_range: float = setting(35e3, lo=1e3, hi=1e6, unit="Pa", doc="readings at or above this are saturated")
    saturation_std: float = setting(2e3, lo=0.0, hi=1e5, lo_open=True, unit="Pa",
                                    doc="one sigma of the saturated reading's pseudo-measurement")
    flow_rel_std: float = setting(0.15, lo=0.0, hi=1.0, doc="relative error of the model's mass flow")
    mass_std_abs: float = setting(2e-8, lo=0.0, hi=1e-5, unit="kg/sqrt(s)", doc="gas-mass random walk")
    load_std: float = setting(0.05, lo=0.0, hi=100.0, unit="N/sqrt(s)", key="load_std_n", doc="load random walk")
    load_init: float | None = setting(None, lo=-1.0, hi=1000.0, unit="N", doc="initial load guess (None: unknown)")
    load_init_std: float = setting(3.0, lo=0.0, hi=1000.0, lo_open=True, unit="N", doc="its one sigma")
    load_rest_std: float = setting(1.0, lo=0.0, hi=1000.0, lo_open=True, unit="N",
                                   doc="one sigma of the load while the membrane rests flat (keeps P regular)")
    lift_threshold: float = setting(6.0, lo=0.0, hi=1e3, lo_open=True, doc="lift-off CUSUM threshold")
    lift_drift: float = setting(0.3, lo=0.0, hi=10.0, doc="lift-off CUSUM drift")
    lift_load_rel_std: float = setting(0.2, lo=0.0, hi=10.0, doc="relative one sigma of the load after a lift-off")
    flow_factor_std: float = setting(0.02, lo=0.0, hi=10.0, unit="1/sqrt(s)", doc="random walk of the pump-flow factor")
    flow_factor_init: float = setting(1.0, lo=FACTOR_RANGE[0], hi=FACTOR_RANGE[1],
                                      doc="the pump-flow factor's start (a fit's flow_scale)")
    flow_factor_init_std: float = setting(0.15, lo=0.0, hi=10.0, doc="its one sigma")
    modulus_std: float = setting(0.002, lo=0.0, hi=10.0, unit="1/sqrt(s)", doc="random walk of the modulus factor")
    modulus_init: float = setting(1.0, lo=FACTOR_RANGE[0], hi=FACTOR_RANGE[1],
                                  doc="the modulus factor's start (a fit's modulus_scale)")
    modulus_init_std: float = setting(0.15, lo=0.0, hi=10.0, doc="its one sigma")
    dead_volume_std: float = setting(0.0, lo=0.0, hi=10.0, unit="1/sqrt(s)", doc="random walk of the dead-volume factor")
    dead_volume_init: float = setting(1.0, lo=FACTOR_RANGE[0], hi=FACTOR_RANGE[1],
                                      doc="the dead-volume factor's start (a fit's V0 over [actuator] V0_cm3)")
    dead_volume_init_std: float = setting(0.2, lo=0.0, hi=10.0, doc="its one sigma")
    change_threshold: float = setting(20.0, lo=0.0, hi=1e6, lo_open=True, doc="CUSUM threshold of a load change")
    change_drift: float = setting(4.0, lo=1.0, hi=100.0, doc="NIS level the load-change CUSUM tolerates")
    change_std: float = setting(3.0, lo=0.0, hi=1000.0, unit="N", doc="one sigma added to the load on a change")
    load_min: float = setting(-1.0, lo=-10.0, hi=0.0, unit="N", doc="lowest load state")
    load_max: float = setting(100.0, lo=0.0, hi=1e4, lo_open=True, unit="N", doc="highest load state")
    mass_init_std: float = setting(1e-8, lo=0.0, hi=1e-3, lo_open=True, unit="kg", doc="one sigma of the initial gas mass")
    output_rel_std: float = setting(0.02, lo=0.0, hi=1.0, doc="relative model-form error of the reported h1, h2, h, F")
    force_std_floor: float = setting(0.1, lo=0.0, hi=100.0, unit="N", doc="model-form error added to the reported force std")
    cov_floor: float = setting(1e-12, lo=0.0, hi=1e-3, doc="covariance eigenvalue floor, relative to the state scales")
    compile: bool = setting(True, doc="compile the filter model to C")
    load_prior: str = setting("unknown", choices=("unknown", "nominal"), doc="learn the load or start at the nominal")
    load_prior_rel_std: float = setting(0.1, lo=0.0, hi=10.0, doc="relative sigma of the nominal load prior")
    reading_min: float = setting(VACUUM_GAUGE, lo=VACUUM_GAUGE, hi=0.0, unit="Pa",
                                 doc="lowest physical reading, gauge (below: an outlier)")
    reading_max_rel: float = setting(1.5, lo=1.0, hi=1000.0,
                                     doc="a reading above this times sensor_range is an outlier")
    gate_nis: float = setting(400.0, lo=1.0, hi=1e6, lo_open=True, doc="innovation gate on the NIS")
    gate_reopen: int = setting(5, integer=True, lo=1, hi=1000, doc="gated readings in a row that re-open the gate")
    max_gap: float = setting(1.0, lo=0.0, hi=3600.0, unit="s", doc="longest time a step predicts over")
    membrane: str = setting(DEFAULT_MEMBRANE, choices=MEMBRANES,
                            doc="the filter model's membrane law (docs/concepts/model.md §9)")
    valve_delay: float = valve_delay_setting(DEFAULT_VALVE_DELAY)
    sensor_delay: float = sensor_delay_setting(DEFAULT_SENSOR_DELAY)

    def check_rules(self) -> None:
        self.within("max_gap", lo=self.sample_period)

    def walk_var(self) -> list[float]:
        """Variances of the states' random walks over one sample period: m (kg^2), W (N^2), b, k, c (-)."""
        dt = self.sample_period
        return [self.mass_std_abs ** 2 * dt, self.load_std ** 2 * dt, self.flow_factor_std ** 2 * dt,
                self.modulus_std ** 2 * dt, self.dead_volume_std ** 2 * dt]

    def prior_var(self) -> list[float]:
        """Variances of the initial state: m (kg^2), W (N^2), b, k, c (-)."""
        return [self.mass_init_std ** 2, self.load_init_std ** 2, self.flow_factor_init_std ** 2,
                self.modulus_init_std ** 2, self.dead_volume_init_std ** 2]


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
