"""The EKF's normal step as ONE casadi Function (numeric inputs and outputs only, C-generable).

:func:`ekf_step_function` builds ``ekf_step`` for the filter of :mod:`hbma_ctrl.estimators.ekf`: predict one
sample period with its Jacobians, the innovation gate, the scalar Joseph-form update (a reading,
the one-sided saturation pseudo-reading, or none), the lift-off and load-change detectors, the
detected lift-off, the flat-load bound, the state clamps and the reported outputs with their
covariance. The mode logic is inside (casadi ``if_else``): resting or in contact (input
``resting``), lift-off (a detector firing, the flow and dead-volume factors' ratio out of its
prior, or the flat-load bound exceeded), touch-down, a
saturated reading and a missing one (input ``kind``). A resting step evaluates the model's flat
predict and outputs (``predict_rest``, ``outputs_rest``: no contact-branch shape projection), a
lifted one the full ones (a casadi switch, so only one runs). The Function holds no Python callbacks and
depends only on the settings it reads (:data:`STEP_SETTINGS`, plus the model's sample period,
integrator, sub-steps and Newton iterations), the material family and the compressor map: the
actuator's numbers come in through ``theta``, so one compiled library serves every actuator.

Signature (SI; P, C column-major 5 x 5; all inputs and outputs dense)::

    ekf_step(x[5], P[5x5], s[2], u[3], theta[nt], resting, z, kind, det[9])
        -> (x_next[5], P_next[5x5], s_next[2], y[8], est[5], std[5], C[5x5], H[1x5], A[5x5],
            resting_next, det_next[9], nis, innov, flags, exact)

Inputs: the state ``x = [m, W, b, k, c]`` and covariance P at the last step; the shape warm start
``s = (h1, h2)`` (m); the command held over the period ``u = [speed, inlet, outlet]``; the model
parameters ``theta`` (:attr:`hbma_ctrl.models.chamber.ObserverModel.theta`); the mode (1 resting
flat, 0 lifted); the reading z (Pa) and its ``kind`` (:data:`KIND_OK` 0 a reading, :data:`KIND_NONE`
1 none: missing or an outlier, :data:`KIND_SATURATED` 2 at or above the sensor range); the
detector state ``det`` (:data:`DET_NAMES`: the load-change CUSUM, the lift-off CUSUM and its dating
sum, the dated lift-off pressure Pa, the last posterior pressure Pa, the gated readings in a row,
the lowest load N a lift-off may carry: a detected lift-off whose load, pi r1^2 p at the dated
lift-off, is below it is implausible (flag ``lift_off_implausible``): the sums restart and the
membrane stays flat; 0 = no floor; the contact phase's excess sum, :data:`EXCESS_THRESHOLD`; and the
lowest b / c a resting membrane is taken as flat at, :func:`flat_ratio_min`, 0 = the test off).

Outputs: the posterior state, covariance and warm start; ``y`` the model outputs
(:data:`hbma_ctrl.models.chamber.OUT_NAMES`) at the posterior; ``est`` = (h1, h2 >= 0, h >= 0, F >= 0, p)
as reported (m, N, Pa) and ``std`` their one sigma; C their covariance (with the model-form
terms); H = dp/dx at the posterior; A = dx+/dx of the predict; the mode and detector state after
the step; ``nis`` (of the update, or of the gated reading) and ``innov`` (normalised innovation;
both 0 without an update); ``flags`` = sum of ``2**i`` over the :data:`FLAG_BITS` raised; and
``exact`` = 1 when the step stayed on the normal path. ``exact`` = 0 marks a rare event this
Function does not finish, for which the caller re-runs the step on the reference path
(:meth:`hbma_ctrl.estimators.ekf.EKF.step_reference`) from the same inputs: the model's projection failed
(non-finite), a covariance lost its eigenvalue floor (the reference floors it by an eigen
decomposition), a re-opened gate or a non-positive innovation variance. A detected lift-off
with no load (flag ``lift_off_detected`` with ``x_next[1] == 0``) is also re-filtered by the
Python EKF from its snapshot of the flat phase (the replay needs the past samples). C callers
take ``exact`` as the test that selects between this step and their own handling of those events.
"""

from __future__ import annotations

import math
import warnings

import casadi as ca
import numpy as np

from hbma_ctrl.estimators.common import FACTOR_RANGE, FilterSettings
from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, compiled
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.chamber import NX, REST_EPS, STATE_SCALE, ObserverModel, min_pivot
from hbma_ctrl.models.reduced import law_key

__all__ = ["ekf_step_function", "observer_model", "STEP_SETTINGS", "KIND_OK", "KIND_NONE", "KIND_SATURATED", "DET_NAMES",
           "FLAG_BITS", "STEP_IN", "STEP_OUT", "FACTOR_RANGE", "LIGHT_LOAD", "LIFT_LOAD_ABS_STD",
           "NO_LOAD_SIGMAS", "LIFT_START_DRIFT", "CENSOR_SIGMAS", "LIFT_PRIOR_SIGMAS", "lift_floor",
           "FLAT_RATIO_SIGMAS", "FLAT_RATIO_STD_MIN", "flat_ratio_min", "EXCESS_DRIFT", "EXCESS_THRESHOLD",
           "LIFT_RISE_DRIFT", "cse", "glue_functions", "fast", "mode_switch", "observer_functions"]

#: reading kinds (input ``kind``)
KIND_OK, KIND_NONE, KIND_SATURATED = 0, 1, 2
#: the detector state carried between steps (input ``det``)
DET_NAMES = ("cusum", "lift", "lift_start", "p_lift", "p_post", "gated_run", "lift_floor", "excess", "ratio_min")
#: flags raised by the step, bit i of output ``flags``
FLAG_BITS = ("gated", "load_change", "lift_off", "clamped", "resting", "not_converged", "touch_down",
             "lift_off_detected", "lift_off_implausible", "lift_off_ratio", "load_excess")
STEP_IN = ("x", "P", "s", "u", "theta", "resting", "z", "kind", "det")
STEP_OUT = ("x_next", "P_next", "s_next", "y", "est", "std", "C", "H", "A", "resting_next", "det_next",
            "nis", "innov", "flags", "exact")

#: a resting load below this (N) may be no load at all: the flat height is then uncertain
LIGHT_LOAD = 0.5
#: absolute one sigma of the load right after a detected lift-off, N (the detection delay)
LIFT_LOAD_ABS_STD = 0.2
#: a lift-off below this many sensor sigmas of pressure is taken as no load (free inflation)
NO_LOAD_SIGMAS = 3.0
#: drift of the sum that dates a lift-off (normalised innovation shortfall per sample): only
#: shortfalls beyond one sigma count
LIFT_START_DRIFT = 1.0
#: the lift-off detector holds its sums on a reading within this many sensor sigmas of the sensor's
#: range: near the range the readings that were clipped are taken out (the saturated kind), so the
#: ones left are a sample biased low, which the detector would read as a membrane lifting (800 g on
#: the 7.5 mm chamber, lifting at 45 kPa, was taken as lifting at 34 kPa by readings 0.4 kPa under
#: the 35 kPa range)
CENSOR_SIGMAS = 3.0

#: the lift-off sum's drift grows by this fraction of the flat prediction's rise over the sample (in
#: the innovation's sigmas): the pump's flow is known to within its map's shape, so a shortfall of a
#: few per cent of the rise is the flow model's, not a lift-off. Through a heavy load's long flat rise
#: at full speed (a rise of 3-4 sigma per sample) the rig's tilted map read -0.5 to -0.9 sigma per
#: sample, above lift_drift alone, and the sum dated false lift-offs at 21-30 kPa for loads lifting at
#: 45 kPa; a true lift-off's shortfall is most of the rise. 0.05 against 0.1: the same false lift-offs
#: gone, fewer true ones delayed (unknown-load protocol, seeds 0-2)
LIFT_RISE_DRIFT = 0.05

#: in contact, a one-sided sum of the normalised innovation's excess (nu / sqrt(S) - EXCESS_DRIFT),
#: summed while the pressure rises, declares a load change (the load's variance widened, as the NIS
#: sum does) above EXCESS_THRESHOLD. The NIS sum needs innovations beyond two sigma; a membrane
#: taken as lifted while it is still flat (a false lift-off dated by the pump's flow falling with
#: back pressure faster than the model's) reads about one sigma high for as long as the pump runs,
#: with the load stuck at the false lift-off's (800 g on the 7.5 mm chamber, taken as 2.9 N at 21 kPa:
#: +0.8 sigma per sample). A threshold of 10 left every trial of noise seed 0's unknown-load protocol
#: as it was; 6 fired on two true lift-offs there
EXCESS_DRIFT = 0.3
EXCESS_THRESHOLD = 10.0

#: a filter told its load (``load_init``, e.g. a scene's ``load_prior = "nominal"``) takes a detected
#: lift-off whose load is more than this many of the prior's sigmas below it as implausible: the
#: flow model's error through a heavy load's long flat rise (the rig's pump loses flow with back
#: pressure faster than the model's) reads like a lift-off, and an 800 g load on the 7.5 mm chamber,
#: lifting at 45 kPa, was taken as lifting at 21 kPa (protocol, noise seed 1)
LIFT_PRIOR_SIGMAS = 3.0


def lift_floor(s: FilterSettings) -> float:
    """The lowest load (N) a detected lift-off may carry for settings s: ``load_init`` less
    :data:`LIFT_PRIOR_SIGMAS` of ``load_init_std`` (>= 0), or 0 without a load prior."""
    if s.load_init is None:
        return 0.0
    return max(0.0, s.load_init - LIFT_PRIOR_SIGMAS * s.load_init_std)


#: while the membrane rests flat its pressure's rise fixes only the ratio of the flow and dead-volume
#: factors, b / c. A resting filter whose posterior ratio has fallen this many of its prior's
#: sigmas below the prior's ratio takes the membrane as lifted: a flat chamber cannot explain the
#: readings, a growing volume can. A free membrane (no load, or a light one) lifts within the pump's
#: first samples, while the factors' spread is still wide, so they absorb its shortfall and the
#: innovation sum never grows (the free 7.5 mm chamber at 80 % speed, noise seed 1: b / c went to 0.38
#: in 50 ms and the membrane was taken as flat up to 5.4 mm). The rig's own factors (flow x0.9, dead
#: volume x1.2, the pump's tilted map) keep b / c near 0.7-0.85, about 1.5 sigma below the default
#: prior's 1. The test holds until the membrane first leaves rest: from then on the factors are
#: learnt, far from the prior the threshold was set from, and a chamber that touches down and is
#: pumped again has its lift-off detector and its learnt load. Kept armed, it fired at the first
#: sample of every later pump from rest: the start-up calibration's flat ratio 1.41 set a threshold
#: of 1.03, the contact phase then learnt b / c = 0.92, and a 400 g chamber re-pumped after a vent was
#: taken as free (`mpc_pressure_limit.toml`, its estimate 10 mm high while the rig sat at 0.4 mm)
FLAT_RATIO_SIGMAS = 3.0
#: the ratio's relative sigma in that test is at least this: the flow model's error of shape (the
#: pump's flow falling with back pressure faster than the model's moves b / c by about 10 % through a
#: flat rise), which a tight prior (the start-up calibration's) does not cover
FLAT_RATIO_STD_MIN = 0.1


def flat_ratio_min(x: np.ndarray, P: np.ndarray) -> float:
    """The lowest b / c (-) a resting filter whose prior is (x, P) (state :data:`NX`, b and c at 2
    and 4) takes as flat: the prior's b / c times exp(-FLAT_RATIO_SIGMAS sigma), sigma the relative
    spread of b / c under P (at least FLAT_RATIO_STD_MIN); 0 (the test off) when the prior holds b
    and c fixed."""
    b, c = float(x[2]), float(x[4])
    if b <= 0 or c <= 0 or not (P[2, 2] > 0 or P[4, 4] > 0):
        return 0.0
    var = P[2, 2] / b ** 2 + P[4, 4] / c ** 2 - 2.0 * P[2, 4] / (b * c)
    return b / c * math.exp(-FLAT_RATIO_SIGMAS * max(math.sqrt(max(var, 0.0)), FLAT_RATIO_STD_MIN))


#: the settings the step Function depends on (the model's are in the model's key): a trial's own
#: load prior, say, must not build and compile another one
STEP_SETTINGS = ("noise_std", "model_rel_std", "sensor_range", "saturation_std", "flow_rel_std", "mass_std_abs",
                 "load_std", "load_rest_std", "lift_threshold", "lift_drift", "lift_load_rel_std",
                 "flow_factor_std", "modulus_std", "dead_volume_std", "change_threshold", "change_drift",
                 "change_std", "load_min", "load_max", "output_rel_std", "force_std_floor", "cov_floor",
                 "gate_nis", "gate_reopen")

_MODEL_CACHE: dict = {}
_STEP_CACHE: dict = {}


def _model_key(actuator: Actuator, pneumatics: Pneumatics, s: FilterSettings) -> tuple:
    return (type(actuator.material), str(pneumatics.csv_path), s.sample_period, s.integrator, s.nsub,
            s.newton, law_key(actuator, pneumatics, s.membrane))


def observer_model(actuator: Actuator, pneumatics: Pneumatics, s: FilterSettings) -> ObserverModel:
    """The estimators' model for this actuator: casadi Functions shared per material family,
    compressor map and integration settings, numeric parameters (``theta``) the actuator's."""
    key = _model_key(actuator, pneumatics, s)
    if key not in _MODEL_CACHE:
        _MODEL_CACHE[key] = ObserverModel(actuator, pneumatics, s.sample_period, s.integrator, s.nsub, s.newton,
                                          membrane=s.membrane)
    return _MODEL_CACHE[key].rebind(actuator, pneumatics)


def ekf_step_function(actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings,
                      part: str = "step") -> ca.Function:
    """The EKF step as one casadi Function (signature in the module docstring), or with ``part`` 'finish'
    the step's end the reference path shares (:func:`_finish_function`); cached per material family,
    compressor map and settings (the actuator's numbers are the input ``theta``)."""
    s = settings.validate()
    om = observer_model(actuator, pneumatics, s)
    key = (_model_key(actuator, pneumatics, s), tuple(getattr(s, n) for n in STEP_SETTINGS))
    if key not in _STEP_CACHE:
        _STEP_CACHE[key] = dict(zip(("step", "finish"), _build(om, s)))
    return _STEP_CACHE[key][part]


def _pivot_function() -> ca.Function:
    """Smallest LDL^T pivot of P / (s s^T) - floor I (s = STATE_SCALE): > 0 iff the covariance keeps
    its eigenvalue floor (the test :func:`hbma_ctrl.estimators.common.guard_cov` makes by a Cholesky factor)."""
    P = ca.SX.sym("P", NX, NX)
    fl = ca.SX.sym("floor")
    out = min_pivot(P, fl)
    return ca.Function("ekf_min_pivot", [P, fl], [out])


_CSE_CACHE: dict = {}


def cse(f: ca.Function) -> ca.Function:
    """The SX Function ``f`` with common subexpressions merged (casadi's ``cse``): a quarter fewer
    instructions in the predict, the same operations on the same values, so the same results.
    One per Function (cached: the reference path's callers compile it once per process)."""
    hit = _CSE_CACHE.get(id(f))
    if hit is None:
        sx_in = f.sx_in()
        hit = _CSE_CACHE[id(f)] = (f, ca.Function(f.name() + "_cse", sx_in, f.call(sx_in), f.name_in(),
                                                  f.name_out(), {"cse": True}))  # f kept: its id stays unique
    return hit[1]


_SWITCH_CACHE: dict = {}


def mode_switch(om: ObserverModel, name: str) -> ca.Function:
    """The model's ``name`` Function ('predict' or 'outputs') behind a switch on a first input: nonzero
    (a resting step) evaluates its flat variant (``predict_rest``, ``outputs_rest``: the same values at
    hold = 1, without the contact branch's shape projection), zero the full one; both with their common
    subexpressions merged (:func:`cse`). One per pair of Functions (cached: compiled once per process)."""
    rest, full = getattr(om, name + "_rest"), getattr(om, name)
    key = (id(rest), id(full))
    if key not in _SWITCH_CACHE:
        _SWITCH_CACHE[key] = (rest, full, ca.Function.if_else(f"ekf_{name}_mode", cse(rest), cse(full)))
    return _SWITCH_CACHE[key][2]


_FN_CACHE: dict = {}


def fast(fun: ca.Function, compile: bool) -> FastFunction:
    """A buffered caller of ``fun``, compiled once per process (generating the C source only to look
    up the cached library costs milliseconds, paid per filter otherwise)."""
    key = (id(fun), compile)
    if key not in _FN_CACHE:
        done = compiled(fun, HOT_OPT, HOT_FLAGS) if compile else fun
        if compile and done is fun:
            warnings.warn(f"{fun.name()}: no working C compiler (cc, gcc or clang): the estimator runs on "
                          "casadi's virtual machine, several times slower per step", RuntimeWarning, stacklevel=2)
        _FN_CACHE[key] = (fun, done)  # fun kept: its id stays unique
    return FastFunction(_FN_CACHE[key][1], False)


def observer_functions(actuator: Actuator, pneumatics: Pneumatics, s: FilterSettings) -> tuple:
    """(ObserverModel, predict, outputs, propagate Function, update), the model's Functions as the
    reference path calls them: predict and outputs are the compiled step's :func:`mode_switch` (first
    argument nonzero: a resting step), update its Joseph-form update; the casadi Functions are shared
    per configuration, the buffered callers (:func:`fast`) are per filter."""
    om = observer_model(actuator, pneumatics, s)
    return (om, fast(mode_switch(om, "predict"), s.compile), fast(mode_switch(om, "outputs"), s.compile),
            om.propagate, fast(om.update, s.compile))


def _only_if(f: ca.Function) -> ca.Function:
    """``f`` behind a switch on a first input: evaluated when it is nonzero, zeros otherwise (for a
    result that is read only then)."""
    zero = ca.Function(f.name() + "_skipped", [ca.SX.sym(n, f.sparsity_in(i)) for i, n in enumerate(f.name_in())],
                       [ca.DM.zeros(f.sparsity_out(i)) for i in range(f.n_out())], f.name_in(), f.name_out())
    return ca.Function.if_else(f.name() + "_if", f, zero)


def _finite(e) -> ca.MX:
    """1 when every entry of e is a finite number (|sum| <= max double is false for NaN and inf)."""
    return ca.fabs(ca.sum1(ca.sum2(e))) <= 1.7976931348623157e308


def _area_function(om: ObserverModel) -> ca.Function:
    """theta -> the membrane's clamped area pi r1^2 (m^2)."""
    thp, Pd = om.chamber.symbols()
    return ca.Function("ekf_area", [thp], [ca.pi * Pd["r1"] ** 2])


#: the load's row and column zeroed (mask) and its variance alone (E11): a re-started load
_LOAD_MASK = ca.DM.ones(NX, NX)
_LOAD_MASK[1, :] = 0.0
_LOAD_MASK[:, 1] = 0.0
_LOAD_E11 = ca.DM.zeros(NX, NX)
_LOAD_E11[1, 1] = 1.0


def _restart_load(P, var):
    """P with the load uncorrelated with the other states and its variance ``var`` (N^2)."""
    return P * _LOAD_MASK + var * _LOAD_E11


def _finish_function(om: ObserverModel, s: FilterSettings) -> ca.Function:
    """``ekf_finish``, the end of a step on both paths: the flat-load bound, the clamps, the outputs and
    their covariance (with the model-form terms), touch-down.

        ekf_finish(x[5], P[5x5], s[2], theta, resting, touch_down, pumping, saturated)
            -> (x_out, P_out, s_out, y[8], est[5], std[5], C[5x5], H[1x5], resting_out, lift_off, clamped,
                touch_down_out, not_converged)

    The state, covariance and warm start after the update, the mode (1 resting), whether the predict
    touched down, the pump filled the chamber and the reading was saturated (0 / 1); the outputs as in
    :data:`STEP_OUT`, the flags 0 / 1: a lift-off by the exceeded flat-load bound, a state clamped, a
    touch-down here, the shape projection not converged."""
    x = ca.MX.sym("x", NX)
    P = ca.MX.sym("P", NX, NX)
    sh = ca.MX.sym("s", 2)
    th = ca.MX.sym("theta", int(np.asarray(om.theta).size))
    resting2, td1, pumping, is_sat = (ca.MX.sym(n) for n in ("resting", "touch_down", "pumping", "saturated"))
    area = _area_function(om)(th)
    outputs = mode_switch(om, "outputs")
    bound = area * om.flat_pressure(x, th)
    # a dead load cannot come down while the pump fills the chamber: after a touch-down the load
    # goes back to the pressure's bound (no ratchet near the lift-off point)
    W2 = ca.if_else(ca.logic_and(ca.logic_and(resting2, td1), pumping), ca.fmin(x[1], bound), x[1])
    xl = ca.vertcat(x[0], W2, x[2:])
    lift_b = ca.logic_and(resting2, bound > W2)  # the (known) load is exceeded: it lifts
    resting3 = ca.logic_and(resting2, ca.logic_not(lift_b))
    # flat, the load is unobservable (only W >= pi r1^2 p): uncorrelated, with the spread that keeps P regular
    Pf = ca.if_else(resting3, _restart_load(P, s.load_rest_std ** 2), P)
    lo = ca.DM([-np.inf, s.load_min, FACTOR_RANGE[0], FACTOR_RANGE[0], FACTOR_RANGE[0]])
    hi = ca.DM([np.inf, s.load_max, FACTOR_RANGE[1], FACTOR_RANGE[1], FACTOR_RANGE[1]])
    xc = ca.fmin(ca.fmax(xl, lo), hi)
    clamped = ca.sum1(ca.logic_or(xl < lo, xl > hi)) > 0
    o2 = outputs(resting3, xc, sh, th, resting3, Pf)
    s2, y, H, C0 = o2[0], o2[1], o2[2], o2[4]
    td2 = ca.logic_and(ca.logic_not(resting3), y[5] > 0.5)
    resting4 = ca.logic_or(resting3, td2)
    W4 = ca.if_else(ca.logic_and(td2, pumping), ca.fmin(xc[1], area * y[4]), xc[1])
    xc = ca.vertcat(xc[0], W4, xc[2:])
    Pf = ca.if_else(td2, _restart_load(Pf, s.load_rest_std ** 2), Pf)
    # model-form error of the shape map (the rig is not the model): relative floor on h1, h2, h and F
    d = (s.output_rel_std * y[:5]) ** 2
    d = d * ca.DM([1.0, 1.0, 1.0, 1.0, 0.0]) + ca.DM([0.0, 0.0, 0.0, s.force_std_floor ** 2, 0.0])
    # flat under a light (or no) load, or flat while saturated (a lift-off would be invisible): the
    # membrane may bulge by up to about the flat cap height h1
    bulge = ca.logic_and(resting4, ca.logic_or(xc[1] < LIGHT_LOAD, is_sat))
    d = d + ca.if_else(bulge, (0.5 * y[0]) ** 2, 0.0) * ca.DM([0.0, 0.0, 1.0, 0.0, 0.0])
    C = C0 + ca.diag(d)
    std = ca.sqrt(ca.fmax(ca.diag(C), 0.0))
    # reported in the shapes' domain (h2, h, F >= 0); a projection that did not converge can leave h2
    # above h1, a plate below the base
    est = ca.vertcat(y[0], ca.fmax(y[1], 0.0), ca.fmax(y[2], 0.0), ca.fmax(y[3], 0.0), y[4])
    not_conv = ca.logic_or(y[7] > 1e-3, ca.logic_not(_finite(y)))
    outs = [xc, Pf, s2, y, est, std, C, H, resting4, lift_b, clamped, td2, not_conv]
    return ca.Function("ekf_finish", [x, P, sh, th, resting2, td1, pumping, is_sat], [ca.densify(e) for e in outs],
                       ["x", "P", "s", "theta", "resting", "touch_down", "pumping", "saturated"],
                       ["x_out", "P_out", "s_out", "y", "est", "std", "C", "H", "resting_out", "lift_off", "clamped",
                        "touch_down_out", "not_converged"])


def _build(om: ObserverModel, s: FilterSettings) -> tuple[ca.Function, ca.Function]:
    """(ekf_step, ekf_finish): the step and the finish it ends with (:func:`_finish_function`)."""
    finish = _finish_function(om, s)
    nt = int(np.asarray(om.theta).size)
    x = ca.MX.sym("x", NX)
    P = ca.MX.sym("P", NX, NX)
    sh = ca.MX.sym("s", 2)
    u = ca.MX.sym("u", 3)
    th = ca.MX.sym("theta", nt)
    rest = ca.MX.sym("resting")
    z = ca.MX.sym("z")
    kind = ca.MX.sym("kind")
    det = ca.MX.sym("det", len(DET_NAMES))
    cusum, lift, lift_start, p_lift, p_post, gated_run, W_floor, excess, ratio_min = (det[i] for i in
                                                                                      range(len(DET_NAMES)))
    area = _area_function(om)(th)
    piv = _pivot_function()
    ss = ca.DM(np.outer(STATE_SCALE, STATE_SCALE))
    rest_in = rest > 0.5

    # --- predict (the mode is held over the period: hold = resting) -------------------------------
    qv = ca.vertcat(ca.if_else(rest_in, 0.0, s.flow_rel_std), *s.walk_var(), s.cov_floor)
    update = cse(om.update)
    # a resting step runs the flat membrane's predict and outputs: a switch evaluates one or the other
    predict = mode_switch(om, "predict")
    xn, A, s1, y1, H1, P1, piv1 = predict(rest_in, x, sh, u, th, rest, P, qv)
    exact = _finite(xn) * _finite(y1) * _finite(P1) * (piv1 > 0)
    # touch-down: the contact model reached the flat membrane; resting from here on
    td1 = ca.logic_and(ca.logic_not(rest_in), y1[5] > 0.5)
    resting = ca.logic_or(rest_in, td1)
    p_pred = y1[4]
    pumping = ca.logic_and(u[0] > 0, u[1] > 0)
    keep = ca.if_else(ca.logic_and(resting, xn[1] < REST_EPS), ca.DM([1.0, 1.0, 0.0, 0.0, 0.0]), ca.DM.ones(NX))
    rel = ca.if_else(resting, 0.0, s.model_rel_std)

    def meas_var(p):
        return s.noise_std ** 2 + (rel * ca.fmax(p, 0.0)) ** 2

    # --- gate and update ----------------------------------------------------------------------
    is_ok = kind == KIND_OK
    is_sat = kind == KIND_SATURATED
    R = meas_var(p_pred)
    nu0 = z - p_pred
    nis_gate = nu0 ** 2 / (ca.mtimes([H1, P1, H1.T]) + R)
    over = ca.logic_and(is_ok, nis_gate > s.gate_nis)
    run = ca.if_else(is_ok, ca.if_else(over, gated_run + 1, 0.0), gated_run)
    reopen = ca.logic_and(over, run >= s.gate_reopen)
    gated = ca.logic_and(over, ca.logic_not(reopen))
    exact = exact * ca.logic_not(reopen)
    sat_upd = ca.logic_and(is_sat, p_pred < s.sensor_range)
    upd = ca.logic_or(ca.logic_and(is_ok, ca.logic_not(over)), sat_upd)
    z_eff = ca.if_else(is_sat, s.sensor_range, z)
    R_eff = ca.if_else(is_sat, s.saturation_std ** 2 + meas_var(s.sensor_range), R)
    nu = z_eff - p_pred
    xu, Pu, Su, pivu = update(xn, P1, H1, nu, R_eff, s.cov_floor, keep)
    exact = exact * ca.if_else(upd, (pivu > 0) * (Su > 0) * _finite(Su), 1)
    r = nu / ca.sqrt(Su)
    detect = ca.logic_and(is_ok, ca.logic_not(over))

    # lift-off detector (resting, the pump filling the chamber; held on a reading near the range)
    censored = z > s.sensor_range - CENSOR_SIGMAS * s.noise_std
    armed = ca.logic_and(ca.logic_and(detect, resting), ca.logic_not(censored))
    filling = ca.logic_and(pumping, p_pred > p_post)
    p_lift_n = ca.if_else(lift_start == 0, 0.5 * (p_post + ca.fmin(p_pred, z)), p_lift)
    ls_n = ca.fmax(0.0, lift_start - r - LIFT_START_DRIFT)
    l_n = ca.fmax(0.0, lift - r - s.lift_drift - LIFT_RISE_DRIFT * ca.fmax(p_pred - p_post, 0.0) / ca.sqrt(Su))
    watching = ca.logic_and(armed, filling)  # the lift-off tests run only then
    fire_lift = ca.logic_and(watching, l_n > s.lift_threshold)
    p_lift2 = ca.if_else(watching, p_lift_n, p_lift)

    # load-change detector (in contact): a change redoes the update with the load's variance widened
    # and the excess sum (EXCESS_THRESHOLD), while the pressure rises
    armed_c = ca.logic_and(detect, ca.logic_not(resting))
    c_n = ca.fmax(0.0, cusum + r * r - s.change_drift)
    rising = p_pred > p_post
    e_n = ca.fmax(0.0, excess + r - EXCESS_DRIFT)
    fire_e = ca.logic_and(armed_c, ca.logic_and(rising, e_n > EXCESS_THRESHOLD))
    fire_c = ca.logic_or(ca.logic_and(armed_c, c_n > s.change_threshold), fire_e)
    cusum2 = ca.if_else(armed_c, ca.if_else(fire_c, 0.0, c_n), cusum)
    excess2 = ca.if_else(armed_c, ca.if_else(ca.logic_and(rising, ca.logic_not(fire_c)), e_n, 0.0),
                         ca.if_else(detect, 0.0, excess))  # detect and not armed_c: resting
    P1w = P1 + ca.DM(np.diag([0.0, s.change_std ** 2, 0.0, 0.0, 0.0]))
    # the update with the load's variance widened, evaluated only on a load change (a switch)
    xw, Pw, Sw, pivw = _only_if(update)(fire_c, xn, P1w, H1, nu, R_eff, s.cov_floor, keep)
    exact = exact * ca.if_else(fire_c, (pivw > 0) * (Sw > 0) * _finite(Sw), 1)
    xa = ca.if_else(upd, ca.if_else(fire_c, xw, xu), xn)
    Pa = ca.if_else(upd, ca.if_else(fire_c, Pw, Pu), P1)

    # a flat chamber that fits its readings only with b / c far below its prior has lifted
    # (FLAT_RATIO_SIGMAS; not under a load prior's floor: a known load lifts at its bound)
    fire_ratio = ca.logic_and(ca.logic_and(watching, ca.logic_not(fire_lift)),
                              ca.logic_and(W_floor == 0, xa[2] < ratio_min * xa[4]))
    fire_any = ca.logic_or(fire_lift, fire_ratio)
    summing = ca.logic_and(filling, ca.logic_not(fire_any))  # armed: the sums go on, else restart
    lift2 = ca.if_else(armed, ca.if_else(summing, l_n, 0.0), lift)
    lift_start2 = ca.if_else(armed, ca.if_else(summing, ls_n, 0.0), lift_start)

    # --- detected lift-off: W = pi r1^2 p at the dated lift-off, none within the sensor's resolution
    # p_flat, the flat membrane's pressure at the posterior (the outputs' resting value), is read only
    # while resting (every use below is gated by it)
    p_flat = om.flat_pressure(xa, th)
    W_lift = area * ca.fmax(ca.fmin(p_flat, p_lift2), 0.0)
    # the ratio's lift-off starts from no load: it is not dated (the Python EKF re-filters it from
    # the last posterior at ambient pressure, where the membrane was still flat)
    W_new = ca.if_else(ca.logic_or(fire_ratio, W_lift < area * NO_LOAD_SIGMAS * s.noise_std), 0.0, W_lift)
    var_new = ca.if_else(fire_ratio, 0.0, (s.lift_load_rel_std * W_lift) ** 2) + LIFT_LOAD_ABS_STD ** 2
    # a lift-off the load's prior rules out (below W_floor, :func:`lift_floor`): the sums restart (as
    # on a lift-off), the membrane stays flat
    implausible = ca.logic_and(fire_lift, W_lift < W_floor)
    fire_lift = ca.logic_and(fire_any, ca.logic_not(implausible))
    Pd_ = _restart_load(Pa, var_new)
    Pd_ = (0.5 * (Pd_ + Pd_.T)) / ss * ss  # guard_cov's symmetrisation, same float operations
    exact = exact * ca.if_else(fire_lift, piv(Pd_, s.cov_floor) > 0, 1)
    xl = ca.if_else(fire_lift, ca.vertcat(xa[0], W_new, xa[2:]), xa)
    Pl = ca.if_else(fire_lift, Pd_, Pa)
    cusum2 = ca.if_else(fire_lift, 0.0, cusum2)
    resting2 = ca.logic_and(resting, ca.logic_not(fire_lift))

    # --- finish: the flat-load bound, clamps, outputs, touch-down -------------------------------
    xc, Pf, s2, y, est, std, C, H, resting4, lift_b, clamped, td2, not_conv = finish(xl, Pl, s1, th, resting2, td1,
                                                                                      pumping, is_sat)
    cusum2 = ca.if_else(lift_b, 0.0, cusum2)
    rest2 = ca.if_else(resting4, 1.0, 0.0)
    flags = (gated * 1 + fire_c * 2 + ca.logic_or(fire_lift, lift_b) * 4 + clamped * 8 + resting4 * 16
             + not_conv * 32 + ca.logic_or(td1, td2) * 64 + fire_lift * 128 + implausible * 256
             + ca.logic_and(fire_ratio, fire_lift) * 512 + fire_e * 1024)
    # the ratio test holds only until the membrane first leaves rest (ekf.py, FLAT_RATIO_SIGMAS)
    det2 = ca.vertcat(cusum2, lift2, lift_start2, p_lift2, y[4], run, W_floor, excess2,
                      ca.if_else(resting4, ratio_min, 0.0))
    nis = ca.if_else(upd * is_ok, r * r, ca.if_else(gated, nis_gate, 0.0))
    innov = ca.if_else(upd * is_ok, r, 0.0)
    outs = [xc, Pf, s2, y, est, std, C, H, A, rest2, det2, nis, innov, flags, exact]
    return ca.Function("ekf_step", [x, P, sh, u, th, rest, z, kind, det], [ca.densify(e) for e in outs],
                       list(STEP_IN), list(STEP_OUT)), finish


def glue_functions(settings: FilterSettings, bounds: tuple) -> tuple[ca.Function, ca.Function]:
    """(ekf_kind, ekf_out), what :meth:`hbma_ctrl.estimators.ekf.EKF.step` does around the step in a loop
    without Python: the reading's kind code and the z the step takes (as the filter classifies a reading
    within the physical ``bounds``, Pa), and the estimate's h, p, F, its 'resting' flag and the count of
    steps the Python filter would have finished on its reference path (``exact`` = 0, or a no-load
    lift-off it replays)."""
    from hbma_ctrl.estimators.common import classify_expr

    z = ca.SX.sym("z")
    lo, hi = bounds
    _, _, sat, ok = classify_expr(z, settings.sensor_range, lo, hi)
    # NaN (a dropout) and outliers are "none"
    code = ca.if_else(ok, KIND_OK, ca.if_else(sat, KIND_SATURATED, KIND_NONE))
    z_in = ca.if_else(code == KIND_OK, z, 0)
    kind = ca.Function("ekf_kind", [z], [z_in, code], ["z"], ["z_in", "kind"])
    est, flags, exact, x, n_ref = (ca.SX.sym("est", 5), ca.SX.sym("flags"), ca.SX.sym("exact"), ca.SX.sym("x", 5),
                                   ca.SX.sym("n_ref"))

    def has(name):
        return ca.fmod(ca.floor(flags / 2 ** FLAG_BITS.index(name)), 2) == 1

    replay = ca.logic_and(has("lift_off"), x[1] == 0)
    ref = ca.logic_or(exact < 0.5, replay)
    out = ca.Function("ekf_out", [est, flags, exact, x, n_ref],
                      [est[2], est[4], est[3], has("resting"), n_ref + ref],
                      ["est", "flags", "exact", "x", "n_ref"], ["h", "p", "F", "resting", "n_ref_next"])
    return kind, out
