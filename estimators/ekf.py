"""Extended Kalman filter: membrane shape and contact force from the chamber pressure alone.

State ``x = [m, W, b, k, c]``: the gas mass (kg, referred to the nominal dead volume: the true
mass is c m), the load on the membrane (N, a random walk), the pump-flow factor b, the modulus
factor k and the dead-volume factor c (-, slow random walks; see :mod:`hbma_ctrl.models.chamber`). Why:

- The gas mass is the plant's own drift-free differential state (the gas law G = m R T); the flow model (pump
  map, valves) drives it directly, so the commands enter the filter where they act. Referred to
  the nominal dead volume, the flat membrane's pressure depends on it alone.
- The shape ``(h1, h2)`` is not a state: given (m, W) it is fixed by the gas law and the contact
  condition (``G(h1, h2) = m R T``, ``F(h1, h2) = W``) or, when ``pi r1^2 p_rest(m) <= W``, the
  membrane rests flat. Carrying h1, h2 as filter states would give a covariance of rank 2 in a 4-d
  space (two exact constraints), which the update cannot keep consistent. They are outputs, with
  their covariance mapped through the implicit-function Jacobian.
- The load W is unknown to the user, piecewise constant (put on, taken off): a random walk.
  ``W = F`` in steady contact; ``W = 0`` is free inflation (h2 = 0). The state may dip below zero
  (the model sees ``max(W, 0)``): clipping it at zero would make the random walk drift up to a
  phantom load, which bends a free cap into a contact shape (a 0.7 mm height bias at 8 mm).
- The flow factor b and the dead-volume factor c: the pump map and the chamber's dead volume are
  the least certain parts of the model (the rig's pump is 10 % weaker, its dead volume 20 %
  larger). While the membrane rests both change only dp/dt per unit command, so the filter learns
  the ratio b / c (the covariance keeps the ridge); that is what lets it tell a lift-off (the
  pressure rise slows by a factor of 2-10) from a weak pump. They separate when the membrane
  moves (the dead volume sets how much of the gas the pressure rise takes from the cap: 0.4 mm of
  height over a 14 kPa rise at r1 = 7.5 mm) and when the chamber vents through the known outlet
  (c alone). Without c, b would carry both, and the cap's growth would be off by the dead volume's share.
- The modulus factor k: in free inflation the height is a function of p / k alone, so k is what
  turns a measured pressure into a height; it is learnt while gas flows (the cap's compliance
  changes dp/dt) and held when nothing flows. In contact a stiffer membrane and a heavier load
  both raise the pressure of a given gas mass; over a trajectory they are only weakly separable,
  so part of the modulus error stays as measurement-model error (``model_rel_std``), see
  :mod:`hbma_ctrl.estimators.observability`.

What pressure alone tells (see :mod:`hbma_ctrl.estimators.observability`): resting flat, only m is known
(``W`` is unobservable, only ``W >= pi r1^2 p``); in contact or free inflation both m and W are
observable while gas flows, and W is not when nothing flows (every (m, W) pair on a level set of
p is then an equilibrium).

Resting is a sticky mode of the filter: while the membrane is flat, the model is held at rest
(W unobservable, kept >= pi r1^2 p). The filter leaves it when the load estimate is exceeded
(pi r1^2 p > W, a known or previously learnt load) or when the lift-off detector fires: the
pressure keeps rising slower than a flat membrane allows (a one-sided CUSUM of the normalised
innovations, run only while the pump fills the chamber: nothing lifts off while venting); then
W = pi r1^2 p_lift, the lift-off condition, which needs no modulus, or no load at all when p_lift
is within ``NO_LOAD_SIGMAS`` sensor sigmas of zero (a free membrane lifts at once). The detector
needs several samples; filtered as flat, they would push the lifted membrane's extra volume into
b and k, so on a detection the filter goes back to the posterior before the detector's sum
started to grow and replays those samples with the membrane lifted (flag ``lift_off_replayed``),
for a no-load lift-off only: a loaded one's sum can start on the flow factor's early learning,
where a lift-off contradicts the data. The sum's drift grows with the flat prediction's rise (the
pump map's error of shape is a few per cent of it, ``LIFT_RISE_DRIFT``). Without a load prior the
filter also leaves rest when a flat chamber would need b / c far below its prior
(:func:`hbma_ctrl.estimators.ekf_step.flat_ratio_min`: a free membrane lifting in the pump's first samples,
whose shortfall the wide factors took up): no load, replayed from the last posterior at ambient
pressure; this test holds only until the membrane first leaves rest (the factors are then learnt,
no longer the prior). In contact a one-sided sum of the innovation's excess (``EXCESS_THRESHOLD``, readings
persistently above the contact model while the pressure rises, as after a false lift-off)
declares a load change, as the NIS sum does.
A touch-down (the contact model reaching h = 0) re-enters rest. With the flow stopped the load is
carried by its random walk.

Tuning (defaults of :class:`~hbma_ctrl.estimators.common.FilterSettings`, chosen against the mismatched rig
on a 24-trial protocol subset, never against the filter's own model):

=======================  ==============  ======================================================
noise_std                200 Pa          the sensor's datasheet sigma (the rig's)
model_rel_std            0.05            pressure-law error in contact (5 % of p); 0 when flat
                                         (the flat pressure is the gas law, no modulus)
flow_rel_std             0.15            mass process noise, 15 % of the period's flow, moving
mass_std_abs             2e-8 kg/sqrt(s) leaks, temperature
load_std                 0.05 N/sqrt(s)  a load is piecewise constant; steps are detected
change_threshold/drift   20 / 4          CUSUM of the NIS: a load step fires in 1-3 samples
change_std               3 N             spread given to the load on a detected step
lift_threshold/drift     6 / 0.3         CUSUM of the innovation shortfall while flat
lift_load_rel_std        0.2 (+0.2 N)    the lift-off pressure is known to a sample's rise
flow_factor_init_std     0.15            the pump map alone (the dead volume is c's; rig: -10 %)
flow_factor_std          0.02 /sqrt(s)   slow drift only
dead_volume_init_std     0.2             dead volume off by up to 20 % (rig: +20 %)
dead_volume_std          0               a geometric constant
modulus_init_std         0.15            the +-15 % modulus mismatch a rig may have
modulus_std              0.002 /sqrt(s)  a material constant: learnt, hardly drifting
output_rel_std           0.02            model-form error of the reported h, F (rig is not model;
                                         0.04 before the filter took the exact law: 600 g NEES 0.6)
force_std_floor          0.1 N           force resolution (load and modulus are weakly separable)
=======================  ==============  ======================================================

Known limits (measured: tests/test_estimator*.py, ``hbma-ctrl bench loop``): a lift-off above the
sensor range is invisible (the filter stays flat while the rig rises by a fraction of a
millimetre); a start far past the load path's pressure maximum can settle on the wrong branch
(pressure alone cannot tell); with the load unknown, the slow start of a free inflation can be
taken for a flat membrane under a weak pump or a large dead volume until the lift-off detector
or the ratio test fires, which can set a small phantom load (seen at r1 10 mm on some noise seeds);
a heavy load's lift-off dated early by the pump map's error, within a few kPa of the sensor range,
is kept (the readings saturate before the excess sum grows); in free
inflation the modulus, flow and dead-volume factors trade off until the chamber
vents (an 8 mm free cap at r1 12.5 mm reads up to 0.4 mm high in ``bench loop``); fast lift-offs
of small loaded chambers are over-confident and large free caps under-confident (Monte-Carlo NEES
outside the chi-square bounds, on either side).

Live-stream guards: a reading that cannot be physical (+-inf, not a number, below vacuum or
``reading_min``, above ``reading_max_rel`` times the sensor range) is an outlier (flag ``outlier``),
and so is one whose NIS exceeds ``gate_nis`` (flag ``gated``): predict only, counted in
:meth:`EKF.stats`. ``gate_reopen`` gated readings in a row re-open the gate (the covariance is
inflated until the reading passes, by at most ``INFLATION_MAX``; flag ``gate_reopened``; it stays
open until a reading passes unaided), so a real fast transient cannot lock the filter out. A gap longer than ``max_gap`` (a paused stream) predicts ``max_gap`` only and widens
the covariance (flag ``time_jump``); a non-finite or backwards ``t`` is a ValueError.

Measurements: a missing (None or NaN) reading skips the update (flag ``missing``); a saturated
reading (>= sensor range) is a one-sided observation ``p >= range``: if the prediction is below
the range, an update towards the range with ``saturation_std``; otherwise no update (flag
``saturated``). Numerics: Joseph-form update, gains by solves, covariance symmetrised with an
eigenvalue floor after every predict and update (:mod:`hbma_ctrl.estimators.common`). No global state; the
filter is deterministic.

Speed: a step one sample period after the last (the normal case) is ONE call of the compiled
:func:`hbma_ctrl.estimators.ekf_step.ekf_step_function` (predict, gate, update, both detectors, lift-off,
touch-down, clamps and outputs; generated as C, compiled once per machine and called through
preallocated buffers). The first step, a late or early tick, a re-opened gate, a covariance that
needs its eigenvalue floor and a no-load lift-off (replayed from the flat phase) run the reference
path (:meth:`EKF.step_reference`: separate predict, update and output calls, the same model); both
give the same numbers (tests/test_ekf_compiled.py). ``hbma-ctrl bench ekf`` times both paths and
filterpy's ExtendedKalmanFilter on the same model.
"""

from __future__ import annotations

import math
import time
from functools import lru_cache

import casadi as ca
import numpy as np

from hbma_ctrl.estimators.common import (
    MEAS_MISSING,
    MEAS_OK,
    MEAS_OUTLIER,
    MEAS_SATURATED,
    FilterSettings,
    classify_measurement,
    guard_cov,
    physical_reading_bounds,
)
from hbma_ctrl.estimators.ekf_reference import OUTPUT_INDEX as _Y
from hbma_ctrl.estimators.ekf_reference import OUTPUT_KEYS, ReferenceSteps
from hbma_ctrl.estimators.ekf_step import (
    FLAG_BITS,
    KIND_NONE,
    KIND_OK,
    KIND_SATURATED,
    NO_LOAD_SIGMAS,
    ekf_step_function,
    fast,
    flat_ratio_min,
    glue_functions,
    lift_floor,
    observer_functions,
)
from hbma_ctrl.core.interfaces import Command, Estimate, EstimatorBase
from hbma_ctrl.core.loopgen import LogColumn, Part, Stage
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.chamber import NX, STATE_NAMES
from hbma_ctrl.models.actuation import CommandTiming, acting_function, acting_state

__all__ = ["EKF", "EKFSettings", "OUTPUT_KEYS"]

#: at most this many samples are kept for the lift-off replay (beyond, no replay: the lift-off applies
#: from the step that detects it)
REPLAY_MAX = 200


class EKFSettings(FilterSettings):
    """EKF settings: the fields of :class:`hbma_ctrl.estimators.common.FilterSettings` (documented there)."""


_KIND_CODE = {MEAS_OK: KIND_OK, MEAS_SATURATED: KIND_SATURATED}
_LIFT_DETECTED = 1 << FLAG_BITS.index("lift_off_detected")


@lru_cache(maxsize=None)
def _flag_set(bits: int) -> frozenset:
    """The flags of :data:`hbma_ctrl.estimators.ekf_step.FLAG_BITS` raised in ``bits`` (memoised)."""
    return frozenset(n for i, n in enumerate(FLAG_BITS) if bits >> i & 1 and n != "lift_off_detected")


def _estimate(t: float, h1: float, h2: float, h: float, F: float, p: float, mean: np.ndarray, cov: np.ndarray,
              state_names: tuple, std: dict, flags: frozenset) -> Estimate:
    """An :class:`Estimate` from the compiled step's floats: its field type checks cannot fail
    there (every value is a float the Function wrote), and cost a quarter of the step."""
    e = object.__new__(Estimate)
    e.__dict__.update(t=t, h1=h1, h2=h2, h=h, F=F, p=p, mean=mean, cov=cov, state_names=state_names, std=std,
                      flags=flags)
    return e


class EKF(ReferenceSteps, EstimatorBase):
    """Extended Kalman filter on ``x = [m, W, b, k, c]`` (see module docstring). SI throughout.

    ``step(t, measurement, applied_command) -> Estimate``: predicts over the periods since the
    last step with ``applied_command`` (the command held since then), then updates with the
    pressure reading (Pa). The first call initialises the state from the reading (membrane flat,
    load ``load_init``). ``reset(t, mean, cov, resting)`` sets the state explicitly.
    After each step (the :class:`~hbma_ctrl.core.interfaces.Estimator` diagnostics): ``last_nis`` and
    ``last_innovation`` (None without a normal update), ``last_output_cov`` (covariance
    of ``OUTPUT_KEYS``), ``last_step_s`` (wall time of the step), ``resting`` (the mode),
    ``last_A`` and ``measurement_jacobian()`` (the linearisation, for observability).

    A step one sample period after the last runs as one call of the compiled
    :func:`hbma_ctrl.estimators.ekf_step.ekf_step_function` (``compiled_step``; the UKF, the first step, a
    late or early tick and the rare events that Function leaves out run the reference path of
    separate predict, update and output calls, :meth:`step_reference`). Both give the same numbers.
    """

    state_names = STATE_NAMES
    #: class default: the normal step is the one compiled Function (False: the reference path)
    compiled_step = True

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings | None = None):
        self.settings = (settings or EKFSettings()).validate()
        actuator.validate()
        pneumatics.validate()
        self.model, self._pred, self._outf, _, self._upd = observer_functions(actuator, pneumatics,
                                                                              self.settings)
        self.theta = np.asarray(self.model.theta, dtype=float)
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.s = np.zeros(2)  # shape warm start (h1, h2)
        self.t: float | None = None
        self.resting = True
        self.last_nis: float | None = None
        self.last_innovation: float | None = None
        self.last_output_cov = np.zeros((5, 5))
        self.last_step_s = 0.0
        self._A_flat = np.eye(NX).ravel()
        self._theta_set: set = set()
        s = self.settings
        q = s.walk_var() + [s.cov_floor]
        self._qv_rest = np.array([0.0] + q)
        self._qv_move = np.array([s.flow_rel_std] + q)
        self._p_pred = 0.0
        self._H = np.zeros(NX)
        self._cusum = 0.0
        self._lift = 0.0
        self._lift_start = 0.0
        self._p_lift = 0.0
        self._p_post = 0.0
        self._excess = 0.0  # the contact phase's excess sum (ekf_step.EXCESS_THRESHOLD)
        self._lift_floor = lift_floor(s)  # the load prior's floor on a detected lift-off (ekf_step)
        # the command as the chamber feels it and the sensor sees it (valve and sensor delays)
        self._timing = CommandTiming(self.settings.sample_period, self.settings.valve_delay,
                                     self.settings.sensor_delay)
        self._innov = 0.0  # innovation of the last update, Pa
        self._sqrt_S = 1.0  # and its standard deviation, Pa
        self._events: set = set()
        self._snap: tuple | None = None  # lift-off replay: posterior before the detector's sum grew
        self._replay: list = []
        # and the last resting posterior at ambient pressure, with the samples since (the replay of a
        # lift-off the factors' ratio showed, ekf_step.FLAT_RATIO_SIGMAS)
        self._rise: tuple | None = None
        self._rise_replay: list = []
        self._replay_now: tuple | None = None  # (snapshot, samples) a detected lift-off re-filters
        self._ratio_min = 0.0  # set by reset() from the prior (ekf_step.flat_ratio_min)
        self._ambient = NO_LOAD_SIGMAS * s.noise_std  # a posterior below this is at ambient pressure, Pa
        self._pumping = False
        self._bounds = physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel)
        self._gated = 0  # gated readings in a row
        self.counts = {"outliers_bound": 0, "gated": 0, "gate_reopened": 0, "missing": 0, "time_jumps": 0}
        #: the normal step as one casadi Function (what a generated loop runs, :meth:`stages`)
        self.step_function = ekf_step_function(actuator, pneumatics, s)
        self._step_fn = fast(self.step_function, s.compile) if self.compiled_step else None
        self._finish_fn = fast(ekf_step_function(actuator, pneumatics, s, "finish"), s.compile)
        self._theta_step = True  # theta not yet in the step's buffer
        self._k_max = max(1, int(round(s.max_gap / s.sample_period)))  # most periods one step predicts
        if self._step_fn is not None:
            # column-major 5 x 5 views of the step's covariance buffers
            self._P_in = self._step_fn.inp[1].reshape(NX, NX).T
            self._P_out = self._step_fn.out[1].reshape(NX, NX).T
            self._C_out = self._step_fn.out[6].reshape(5, 5).T

    # --- state handling -----------------------------------------------------------------------
    def reset(self, t: float, mean, cov=None, shape=None, resting: bool | None = None) -> None:
        """Set the state [m (kg), W (N), b (-), k (-), c (-)] and covariance at time t (s).

        ``shape`` = warm start (h1, h2) in m; ``resting`` = the mode (None: from the state). The
        prior's b / c and its spread set the lowest ratio a resting membrane is taken as flat at
        (:func:`hbma_ctrl.estimators.ekf_step.flat_ratio_min`; a start-up calibration hands its prior over here).
        """
        s = self.settings
        x = np.array(mean, dtype=float).ravel()
        x = np.append(x, np.ones(NX - x.size))  # b, k and c default to 1 (nominal)
        self.x = x.reshape(NX)
        self.P = np.diag(s.prior_var()) if cov is None else np.array(cov, dtype=float).reshape(NX, NX)
        self.P = guard_cov(self.P, s.cov_floor)
        self._ratio_min = flat_ratio_min(self.x, self.P)
        self.t = float(t)
        self.s = np.zeros(2) if shape is None else np.array(shape, dtype=float).reshape(2)
        if resting is None:
            out = self._outf(0.0, self.x, self.s, self._theta_arg(self._outf), 0.0, self.P)
            resting = bool(out[1][_Y["rest"]] > 0.5)
        self.resting = resting
        self._cusum = self._lift = self._lift_start = self._excess = 0.0
        self._snap, self._replay, self._replay_now = None, [], None
        self._rise, self._rise_replay = None, []
        self._refresh()

    def _theta_arg(self, fun):
        """theta for a compiled call: passed once per Function, then kept in its buffer."""
        if fun in self._theta_set:
            return None
        self._theta_set.add(fun)
        return self.theta

    def _refresh(self) -> None:
        hold = float(self.resting)
        out = self._outf(hold, self.x, self.s, self._theta_arg(self._outf), hold, self.P)
        self.s = out[0].copy()
        self._p_pred = float(out[1][_Y["p"]])
        self._H = out[2].copy()

    def _init_from(self, t: float, z: float, kind: str) -> None:
        s = self.settings
        p0 = float(z) if kind == "ok" else (s.sensor_range if kind == MEAS_SATURATED else 0.0)
        act = self.model.actuator
        # the prior's factors (1: nominal; a calibration's values); m is referred to the nominal dead
        # volume (hbma_ctrl.models.chamber), so the flat chamber's mass does not depend on c
        b0, k0, c0 = s.flow_factor_init, s.modulus_init, s.dead_volume_init
        m0 = (max(p0, 0.0) + act.p_env) * act.V0 / self.model.rt
        W0 = s.load_max if s.load_init is None else s.load_init
        self.reset(t, [m0, W0, b0, k0, c0], resting=True if s.load_init is None else None)

    @property
    def last_A(self) -> np.ndarray:
        """A = dx+/dx of the last predict (n x n)."""
        return self._A_flat.reshape(NX, NX, order="F").copy()

    def measurement_jacobian(self) -> np.ndarray:
        """H = dp/dx (1 x n) at the current estimate and mode."""
        return self._H.reshape(1, NX).copy()

    def step(self, t: float, measurement, applied_command: Command) -> Estimate:
        """Advance to time t (s) with the command held since the last step, then update.

        A reading that cannot be physical (see :func:`hbma_ctrl.estimators.common.classify_measurement`) or
        that fails the innovation gate is not used (predict only; flags ``outlier`` / ``gated``,
        counted in :meth:`stats`). A gap longer than ``max_gap`` predicts ``max_gap`` only and
        widens the covariance (flag ``time_jump``). Raises ValueError when t is not a finite time
        or is before the last step's."""
        t_wall = time.perf_counter()
        s = self.settings
        t = self._check_time(t)
        kind = classify_measurement(measurement, s.sensor_range, *self._bounds)
        self._events = set()
        if kind != "ok":
            self._events.add(kind)
            key = {MEAS_OUTLIER: "outliers_bound", MEAS_MISSING: "missing"}.get(kind)
            if key:
                self.counts[key] += 1
        jump = False
        if self.x is None:
            self._init_from(t, measurement, kind)
            k = 0
        else:
            k = int(round((t - self.t) / s.sample_period))
            k_max = self._k_max
            if k > k_max:
                k, jump = k_max, True
                self._events.add("time_jump")
                self.counts["time_jumps"] += 1
        u = applied_command.as_array() if isinstance(applied_command, Command) else \
            np.asarray(applied_command, dtype=float).reshape(3)
        if self._timing.active:
            u = self._timing.acting(u, k)
        if jump:
            self._snap, self._replay = None, []  # a replay across a gap would predict the gap again
            self._rise, self._rise_replay = None, []
            self._lift = self._lift_start = 0.0
        if not self.resting:
            self._rise = None
        elif k > 0:
            # lift-off replay: while the detector's sum is at zero, remember the posterior; the
            # samples after it are kept so a detected lift-off can be re-filtered from there; the
            # same for the last posterior at ambient pressure (the ratio's lift-off)
            # by reference: the compiled step replaces these arrays and never writes into them;
            # the reference path below detaches them first
            post = (self.x, self.P, self.s, self.t, self._p_pred, self._H, self._p_post)
            sample = (float(t), measurement, kind, u, k)
            if self._lift == 0.0:
                self._snap, self._replay = post, []
            if self._snap is not None and len(self._replay) < REPLAY_MAX:
                self._replay.append(sample)
            else:
                self._snap = None  # too long ago: no replay (the lift-off is applied now)
            if self._p_post < self._ambient:
                self._rise, self._rise_replay = post, []
            if self._rise is not None and len(self._rise_replay) < REPLAY_MAX:
                self._rise_replay.append(sample)
            else:
                self._rise = None
        if self._step_fn is not None and k == 1 and not jump:
            est = self._step_compiled(t, measurement, kind, u)
            if est is not None:
                self.last_step_s = time.perf_counter() - t_wall
                return est
        # the reference path writes into the state arrays: never into a snapshot's
        self.x, self.P, self.s, self._H = self.x.copy(), self.P.copy(), self.s.copy(), self._H.copy()
        self._advance(t, measurement, kind, u, k, detect=True, jump=jump)
        if self._replay_now is not None:
            snap, replay = self._replay_now
            self._replay_now = None
            self._replay_from_snapshot(snap, replay)
        est = self._finish()
        self.last_step_s = time.perf_counter() - t_wall
        return est

    def step_reference(self, t: float, measurement, applied_command: Command) -> Estimate:
        """:meth:`step` on the reference path (separate predict, update and output calls, the
        detectors in Python): what the compiled step is tested against."""
        fn, self._step_fn = self._step_fn, None
        try:
            return self.step(t, measurement, applied_command)
        finally:
            self._step_fn = fn

    def _step_compiled(self, t: float, measurement, kind: str, u: np.ndarray) -> Estimate | None:
        """One period as one call of the compiled step; None (nothing changed) when the step met an
        event it leaves to the reference path (its output ``exact`` = 0, or a lift-off to replay)."""
        fn = self._step_fn
        inp, out = fn.inp, fn.out
        inp[0][:] = self.x
        self._P_in[:] = self.P
        inp[2][:] = self.s
        inp[3][:] = u
        if self._theta_step:
            inp[4][:] = self.theta
            self._theta_step = False
        code = _KIND_CODE.get(kind, KIND_NONE)
        inp[5][0] = 1.0 if self.resting else 0.0
        inp[6][0] = float(measurement) if code == KIND_OK else 0.0
        inp[7][0] = code
        inp[8][:] = self.detector_state()
        fn._eval()
        bits = int(out[13][0])
        # a detected lift-off with no load is re-filtered from the snapshot: the reference path
        if out[14][0] < 0.5 or (bits & _LIFT_DETECTED and out[0][1] == 0.0
                                and (self._snap is not None or self._rise is not None)):
            return None
        flags = _flag_set(bits)
        if self._events:
            flags = flags | self._events
        self._pumping = bool(u[0] > 0.0 and u[1] > 0.0)
        self.x = x = out[0].copy()
        self.P = P = self._P_out.copy()
        self.s = out[2].copy()
        self._A_flat = out[8].copy()
        self.resting = bool(out[9][0] > 0.5)
        (self._cusum, self._lift, self._lift_start, self._p_lift, self._p_post, g, _, self._excess,
         self._ratio_min) = out[10].tolist()
        self._gated = int(g)
        e0, e1, e2, e3, e4 = out[4].tolist()
        self._p_pred = e4
        self._H = out[7].copy()
        self.t = t
        if code == KIND_OK:
            self.last_nis = float(out[11][0])
            if bits & 1:
                self.last_innovation = None
                self.counts["gated"] += 1
            else:
                self.last_innovation = float(out[12][0])
        else:
            self.last_nis = self.last_innovation = None
        self.last_output_cov = self._C_out.copy()
        return _estimate(t, e0, e1, e2, e3, e4, x.copy(), P.copy(), self.state_names,
                         dict(zip(OUTPUT_KEYS, out[5].tolist())), flags)

    def detector_state(self) -> list:
        """The detectors' state in :data:`hbma_ctrl.estimators.ekf_step.DET_NAMES` order (the compiled step's
        ``det`` input; sums -, pressures Pa, loads N, b / c -)."""
        return [self._cusum, self._lift, self._lift_start, self._p_lift, self._p_post, float(self._gated),
                self._lift_floor, self._excess, self._ratio_min]

    def _check_time(self, t) -> float:
        """t as a float; ValueError naming ``t`` when it is not a finite number or goes backwards."""
        if type(t) is float and self.t is not None and self.t - 1e-9 <= t < math.inf:
            return t  # the common case in one test
        try:
            tf = float(t)
        except (TypeError, ValueError):
            raise ValueError(f"estimator.step: t = {t!r} must be a finite time in s") from None
        if not math.isfinite(tf) or isinstance(t, (str, bytes, bool)):
            raise ValueError(f"estimator.step: t = {t!r} must be a finite time in s")
        if self.t is not None and tf < self.t - 1e-9:
            raise ValueError(f"estimator.step: t = {tf} s is before the last step's {self.t} s "
                             "(time must not go backwards)")
        return tf

    def stats(self) -> dict:
        """Counts since construction: ``outliers`` (readings not used as implausible: out of the
        physical bounds or gated), ``outliers_bound``, ``gated``, ``gate_reopened``, ``missing``
        (dropouts) and ``time_jumps`` (bounded gaps)."""
        c = dict(self.counts)
        c["outliers"] = c["outliers_bound"] + c["gated"]
        return c

    def stages(self, t: np.ndarray, z0: float) -> Part:
        """The filter in a generated loop (:mod:`hbma_ctrl.core.loopgen`) over the tick times ``t`` (s),
        initialised here from the first reading z0 (Pa) as its first :meth:`step` does (the loop's
        Functions run from tick 1): the reading's kind, the command acting through the valve and sensor
        delays it models, the step Function and its estimate (:func:`hbma_ctrl.estimators.ekf_step.glue_functions`).
        Reads the signals ``p`` (the reading) and ``u`` (the command held); writes ``est_h``, ``est_p``,
        ``est_F``, ``resting`` and counts in ``ekf_n_ref`` the steps it would have left to the reference path."""
        fun, s = self.step_function, self.settings
        kind, out = glue_functions(s, self._bounds)
        e0 = self.step(float(t[0]), z0, Command(0.0, 0.0, 0.0))
        flags = sum(2 ** i for i, n in enumerate(FLAG_BITS) if n in e0.flags)
        signals = {"ekf_x": self.x, "ekf_P": np.asarray(self.P).ravel(order="F"), "ekf_s": self.s,
                   "ekf_theta": self.theta, "ekf_resting": [float(self.resting)], "z_in": [0.0], "kind": [0.0],
                   "ekf_det": self.detector_state(), "ekf_y": np.zeros(fun.nnz_out(3)),
                   "ekf_est": [e0.h1, e0.h2, e0.h, e0.F, e0.p], "ekf_std": np.zeros(5), "ekf_C": np.zeros(25),
                   "ekf_H": np.zeros(5), "ekf_A": np.zeros(25), "ekf_nis": [0.0], "ekf_innov": [0.0],
                   "ekf_flags": [float(flags)], "ekf_exact": [1.0], "est_h": [e0.h], "est_p": [e0.p],
                   "est_F": [e0.F], "resting": [float("resting" in e0.flags)], "ekf_n_ref": [0.0],
                   "not_first": [0.0], "one": [1.0]}
        timing = self._timing
        step_in = ["ekf_x", "ekf_P", "ekf_s", "u_act" if timing.active else "u", "ekf_theta", "ekf_resting", "z_in",
                   "kind", "ekf_det"]
        step_out = ["ekf_x", "ekf_P", "ekf_s", "ekf_y", "ekf_est", "ekf_std", "ekf_C", "ekf_H", "ekf_A",
                    "ekf_resting", "ekf_det", "ekf_nis", "ekf_innov", "ekf_flags", "ekf_exact"]
        first = ca.Function("mark_started", [ca.SX.sym("one")], [ca.SX(1.0)], ["one"], ["started"])
        stages = [Stage(kind, ["p"], ["z_in", "kind"], gate="not_first")]
        if timing.active:
            hist, fill = acting_state(timing)  # the commands sent so far, as the initialisation left them
            signals.update(u_act=np.zeros(3), ekf_uhist=hist, ekf_ufill=[fill])
            stages.append(Stage(acting_function(timing, "ekf_acting"), ["u", "ekf_uhist", "ekf_ufill"],
                                ["u_act", "ekf_uhist", "ekf_ufill"], gate="not_first"))
        stages += [Stage(fun, step_in, step_out, gate="not_first"),
                   Stage(out, ["ekf_est", "ekf_flags", "ekf_exact", "ekf_x", "ekf_n_ref"],
                         ["est_h", "est_p", "est_F", "resting", "ekf_n_ref"], gate="not_first"),
                   Stage(first, ["one"], ["not_first"])]
        delays = (f", commands acting {s.valve_delay * 1e3:g} + {s.sensor_delay * 1e3:g} ms late" if timing.active
                  else "")
        log = [LogColumn("h_est_mm", "est_h", 0, 1e3), LogColumn("p_est_kpa", "est_p", 0, 1e-3),
               LogColumn("F_est_n", "est_F", 0, 1.0), LogColumn("ekf_reference_events", "ekf_n_ref", 0)]
        return Part(stages, signals, log=log,
                    meta={"estimator": f"EKF (hbma_ctrl.estimators.ekf_step), {s.sample_period * 1e3:g} ms{delays}"})
