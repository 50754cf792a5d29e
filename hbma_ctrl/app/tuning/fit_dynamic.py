"""Fit the chamber model to a recorded run: the dynamic part of ``hbma-ctrl fit`` (SI inside).

A recorded run is a CSV with a time column ``t_s``, the pressure reading, the commands (compressor
speed, inlet and outlet duty) and optionally the height and the load. The files the package writes
are accepted as they are (:data:`hbma_ctrl.app.tuning.run_data.COLUMN_ALIASES`, first match wins; the file is
read and checked by :func:`hbma_ctrl.app.tuning.run_data.parse_run`):

- ``hbma-ctrl run`` of a single-chamber closed-loop scene (``closed_loop.csv``): ``p_meas_kpa``,
  ``h_true_mm``, ``load_g``, ``speed``, ``inlet``, ``outlet`` (duties 0-1);
- ``hbma-ctrl protocol`` trials (``trials/<name>.csv``) and open-loop ``run`` logs (``log.csv``):
  ``p_kpa``, ``h_mm``, ``speed_pct``, ``inlet_duty``, ``outlet_duty`` (no load column: the load is
  given with ``load_kg`` / ``--load-g``);
- a daemon run log (``run_0001.csv``, or its run directory for every part): one chamber's
  ``p_<name>_kpa``, ``speed_<name>_1``, ``inlet_<name>_1``, ``outlet_<name>_1``, chosen by its name (its
  ``h_est`` column is the filter's estimate, not a measurement, and is not fitted to).

The recorded commands are replayed (held from one row to the next) through the package's one chamber
model at the fastest adequate rung of the fidelity ladder (``free`` without a load, ``quasi_static``
with one; rk4 at the simulator's default step) with the cap's membrane law or, with ``fidelity =
"exact"``, the exact membrane's tables (the rig's and the roles' default law,
:func:`hbma_ctrl.models.fidelity_exact.make_exact`'s rungs), from a vented chamber, for a batch of parameter sets
at once (one batched :class:`hbma_ctrl.sim.simulate.Plant`), and the parameters are fitted by
``scipy.optimize.least_squares`` on the pressure (and the height when recorded), each channel divided
by its span, on a log scale, from several starts (nominal and the corners of a factor 1.5 around
it screened in one batched simulation, the best two refined); the Jacobian is central differences, all columns in
one batched simulation. Parameters (:data:`DYN_PARAMS`), with the rig's meanings
(:mod:`hbma_ctrl.sim.rig`):

- ``modulus_scale``: every modulus of the material times this (or, with ``fit_material``, the
  material parameters themselves: with the exact law ``nh`` only, whose one modulus is a scale);
- ``V0``: the dead volume, m^3;
- ``flow_scale``: the compressor map times this;
- ``C_out``: the outlet valve's sonic conductance (ISO 6358), m^3/(s Pa).

Readings at the sensor's range (saturated) are left out; isolated missing readings (dropouts) are
skipped, longer runs of them refused. Intervals (95 %) come from the Jacobian at the optimum with
the residual variance and a t quantile (they assume equal, independent noise on every point of a
channel relative to its span); weak directions are named by :func:`hbma_ctrl.core.identify.weak_directions`.
Only :func:`write_dynamic_fit` touches files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.app.tuning.fit import (FIT_KEYS, FitReport, check_exact_material, check_options, param_names, split_fix,
                                      unflatten)
from hbma_ctrl.app.tuning.fit_output import toml_head, write_fit
from hbma_ctrl.app.metrics import nrmsd
from hbma_ctrl.app.tuning.run_data import COLUMN_ALIASES, RunData, is_dynamic, parse_run
from hbma_ctrl.core import units as U
from hbma_ctrl.core.identify import BAD_RESIDUAL, Coordinates, central_jacobian, finite_residuals, identify, summary
from hbma_ctrl.core.materials import MATERIALS, make_material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.actuation import check_delays
from hbma_ctrl.models.fidelity import OUTPUTS, make_fidelity
from hbma_ctrl.models.fidelity_exact import make_exact_free, make_exact_loaded
from hbma_ctrl.sim.simulate import Plant
from hbma_ctrl.sim.trial import DEFAULT_DT

__all__ = [
    "COLUMN_ALIASES",
    "DYN_PARAMS",
    "MAX_POINTS",
    "MAX_REPLAY_S",
    "check_replay",
    "RunData",
    "DynamicFitResult",
    "is_dynamic",
    "parse_run",
    "dynamic_param_names",
    "simulate_run",
    "delayed_commands",
    "fit_dynamic",
    "dynamic_params_toml",
    "write_dynamic_fit",
    "DYNAMIC_FIT_KEYS",
    "STRUCTURED_RATIO",
    "PRIOR_STD_MIN",
    "estimator_prior_lines",
]

#: fit.json of a recorded run: the static keys plus ``model_error`` (see :meth:`DynamicFitResult.model_error`)
DYNAMIC_FIT_KEYS = FIT_KEYS + ("model_error",)
#: residual RMS above this many times the white sensor noise = a structured residual (model-form error)
STRUCTURED_RATIO = 1.3

#: the fitted chamber parameters besides the material (SI)
DYN_PARAMS = ("modulus_scale", "V0", "flow_scale", "C_out")
#: at most this many points per channel enter the least squares (evenly thinned)
MAX_POINTS = 1500
#: log-scale bounds of each parameter around its nominal value
_LOG_BOUND = math.log(20.0)
#: candidate starts: nominal and every corner of +-this log offset (a factor 1.5 either way) are
#: simulated in one batch; the best :data:`_N_REFINE` are refined by least squares
_START_OFFSET = math.log(1.5)
_N_REFINE = 2
#: least-squares evaluations per refined start
_MAX_NFEV = 30
#: the longest run a fit replays unless told (s of rig time, ``--max-replay-s``): a fit's time grows with
#: the run's (a 5 s recording: about 15 s on one core)
MAX_REPLAY_S = 300.0
#: relative step of the central differences (log units)
_FD_STEP = 1e-3
#: the smallest prior sigma params.toml gives the filter's factors: the fit's own interval counts
#: the noise only, and on the default rig it misses the dead volume by 6 % (docs/how-to/fit.md); the
#: protocol with this prior: EKF height NRMSD 0.019-0.020 over noise seeds 0-2, 0.020-0.021 at 0.08
PRIOR_STD_MIN = 0.05


@dataclass(kw_only=True)
class DynamicFitResult(FitReport):
    """A dynamic fit (SI): the report (the pressure's NRMSD in ``nrmsd``), the load, the model's name
    and the times and heights of the series for the plot."""

    load: float
    fidelity: str
    nrmsd_h: float | None = None
    law: str = "cap"
    V0_nominal: float = 3e-6
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    h_data: np.ndarray | None = None
    h_model: np.ndarray | None = None

    def model_error(self) -> dict:
        """How much of the pressure residual is not sensor noise (kPa): ``residual_rms_kpa``, the
        ``white_noise_kpa`` estimated from successive differences of the residual (white noise
        survives differencing, a smooth model-form error does not), their ``ratio``, and
        ``structured`` (ratio > :data:`STRUCTURED_RATIO`): the model's form differs from the rig's,
        its error is in ``nrmsd`` and part of it is absorbed by the parameters."""
        r = np.asarray(self.p_model, dtype=float) - np.asarray(self.p_data, dtype=float)
        r = r[np.isfinite(r)]
        if r.size < 3:
            return {"residual_rms_kpa": None, "white_noise_kpa": None, "ratio": None, "structured": False}
        rms = float(np.sqrt(np.mean(r**2)))
        white = float(np.std(np.diff(r)) / math.sqrt(2.0))
        ratio = rms / white if white > 0 else math.inf
        return {"residual_rms_kpa": U.to_kpa(rms), "white_noise_kpa": U.to_kpa(white),
                "ratio": ratio if math.isfinite(ratio) else None, "structured": bool(ratio > STRUCTURED_RATIO)}

    def notes(self) -> list[str]:
        """The unidentified directions and, when the residual is structured, a sentence saying so."""
        me = self.model_error()
        extra = []
        if me["structured"]:
            extra.append(f"the residual is structured: RMS {me['residual_rms_kpa']:.3g} kPa against "
                         f"{me['white_noise_kpa']:.3g} kPa of white sensor noise; the {self.fidelity} model's "
                         "form differs from the rig's, so its error is in nrmsd and the parameters absorb part "
                         "of it (read them as effective values)")
        return list(self.unidentifiable) + extra

    def as_json(self) -> dict:
        """fit.json content: :data:`DYNAMIC_FIT_KEYS` (the pressure's NRMSD in ``nrmsd``)."""
        return {**super().as_json(), "model_error": self.model_error()}


# ---------------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------------
def dynamic_param_names(material: str, fit_material: bool = False) -> list[str]:
    """Fitted parameter names: :data:`DYN_PARAMS`, with the material's own parameters in place of
    ``modulus_scale`` when ``fit_material``."""
    if not fit_material:
        return list(DYN_PARAMS)
    return param_names(material) + list(DYN_PARAMS[1:])


class _RunModel:
    """The recorded commands replayed through the chamber model for columns of parameters."""

    def __init__(self, run: RunData, material: str, r1: float, t0: float, V0: float, fit_material: bool,
                 fidelity: str = "cap", valve_delay: float = 0.0, sensor_delay: float = 0.0,
                 max_replay: float | None = None):
        mat = make_material(material)
        act = Actuator(r1=r1, t0=t0, V0=V0, material=mat).validate()
        pn = Pneumatics().validate()
        plat = Platform(load=run.load).validate()
        loaded = plat.mass > 0
        if fidelity == "exact":
            # its tables hold the material's shape; the modulus scale (or nh's E) enters through theta
            self.fid = make_exact_free(mat, str(pn.csv_path)) if not loaded else \
                make_exact_loaded("quasi_static", mat, str(pn.csv_path))
        else:
            self.fid = make_fidelity("quasi_static" if loaded else "free", mat, str(pn.csv_path))
        self.theta0 = self.fid.space.values(act, pn, plat)
        names = self.fid.space.names
        self.ix = {n: i for i, n in enumerate(names)}
        dimless = set(MATERIALS[material].dimensionless)
        mat_names = param_names(material)
        self.mat_names = mat_names
        self.mod_idx = [self.ix[n] for n in mat_names if n.rstrip("0123456789") not in dimless]
        self.names = dynamic_param_names(material, fit_material)
        # log scale for positive parameters; signed material terms (higher Yeoh) on a linear one
        self.nominal = np.array([1.0 if n in ("modulus_scale", "flow_scale") else self.theta0[self.ix[n]]
                                 for n in self.names])
        self.coords = Coordinates.about(self.nominal)
        dt_data = float(np.median(np.diff(run.t))) if run.t.size > 1 else 1.0
        self.dt = min(DEFAULT_DT[("rk4", self.fid.name)], dt_data)
        self.K = int(math.ceil(run.t[-1] / self.dt - 1e-9))
        if max_replay is not None:
            check_replay(run, self.K, self.dt, DEFAULT_DT[("rk4", self.fid.name)], max_replay)
        #: called after each replay (a batch of parameter sets through the whole run)
        self.on_replay = None
        # the command held over each grid step: the row in force at the step's middle
        if valve_delay > 0.0 or sensor_delay > 0.0:
            # the valves act valve + sensor delay late, the pump's speed the sensor's (the roles' dead
            # times, hbma_ctrl.models.actuation): each step's command is the delayed one's average
            self.ugrid = delayed_commands(run.t, run.u, self.K, self.dt,
                                          (sensor_delay, valve_delay + sensor_delay, valve_delay + sensor_delay))
        else:
            rows = np.searchsorted(run.t, (np.arange(self.K) + 0.5) * self.dt, side="right") - 1
            self.ugrid = run.u[np.clip(rows, 0, len(run.t) - 1)]
        self.grid_of_row = np.clip(np.rint(run.t / self.dt).astype(int), 0, self.K)

    def values(self, Z: np.ndarray) -> np.ndarray:
        """Parameter values (SI) of columns Z (n_params x n) of log / scaled offsets from nominal."""
        return self.coords.values(np.asarray(Z, dtype=float).reshape(len(self.names), -1))

    def thetas(self, Z: np.ndarray) -> np.ndarray:
        V = self.values(Z)
        th = np.repeat(self.theta0[:, None], V.shape[1], axis=1)
        for k, n in enumerate(self.names):
            if n == "modulus_scale":
                th[self.mod_idx] = self.theta0[self.mod_idx, None] * V[k][None, :]
            else:
                th[self.ix[n]] = V[k]
        return th

    def simulate(self, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Model pressure (Pa) and height (m) at every data row, (rows x n), and which columns stayed finite."""
        th = self.thetas(Z)
        n = th.shape[1]
        plant = Plant(self.fid, th, "rk4", self.dt)
        ip, ih = OUTPUTS.index("p"), OUTPUTS.index("h")
        P = np.empty((self.K + 1, n))
        H = np.empty((self.K + 1, n))
        for k in range(self.K + 1):
            P[k], H[k] = plant.y[ip], plant.y[ih]
            if k == self.K:
                break
            plant.set_inputs(np.repeat(self.ugrid[k][:, None], n, axis=1))
            plant.advance()
        if self.on_replay is not None:
            self.on_replay()
        return P[self.grid_of_row], H[self.grid_of_row], plant.alive.copy()


def check_replay(run: RunData, K: int, dt: float, dt_model: float, max_replay: float) -> None:
    """ValueError naming ``--max-replay-s`` when the run is longer than ``max_replay`` s of rig time or
    its replay takes more than ``max_replay / dt_model`` steps (rows closer than the model's step
    ``dt_model`` shorten the step to ``dt``, s; the fit's time grows with the steps)."""
    k_max = int(math.ceil(max_replay / dt_model))
    fix = "cut the run (a recording of a few pump / hold / vent cycles determines the parameters) or raise it"
    if run.t[-1] > max_replay:
        raise ValueError(f"data: the run is {run.t[-1]:g} s long ({run.t.size} rows); a fit replays at most "
                         f"--max-replay-s {max_replay:g} s: {fix}")
    if K > k_max:
        raise ValueError(f"data: rows {dt:g} s apart make the replay {K} steps of {dt:g} s; a fit replays at most "
                         f"{k_max} (--max-replay-s {max_replay:g} at the model's {dt_model:g} s step): resample the "
                         f"run to the model's step, {fix}")


def delayed_commands(t: np.ndarray, u: np.ndarray, K: int, dt: float, delays) -> np.ndarray:
    """The commands acting over each of K steps of dt (s) from t = 0, averaged over the step, when
    command column j acts ``delays[j]`` s after it was sent; ``u[i]`` holds from ``t[i]`` to ``t[i + 1]``
    (the last to the end, the first also before the record). (K, 3), each entry between the commands
    it averages."""
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    edges = np.arange(K + 1) * dt
    out = np.empty((K, u.shape[1]))
    # the held commands' running integral is piecewise linear in time: exact averages by interpolation
    tt = np.concatenate([t, [max(t[-1], edges[-1]) + 1.0]])
    for j in range(u.shape[1]):
        cum = np.concatenate([[0.0], np.cumsum(u[:, j] * np.diff(tt))])
        a = edges - delays[j]
        before = np.minimum(a - tt[0], 0.0) * u[0, j]  # before the record: the first command held
        c = np.interp(np.maximum(a, tt[0]), tt, cum) + before
        out[:, j] = np.clip(np.diff(c) / dt, u[:, j].min(), u[:, j].max())
    return out


def simulate_run(run: RunData, material: str, params: dict, r1: float, t0: float, fidelity: str = "cap",
                 valve_delay: float = 0.0, sensor_delay: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Model pressure (Pa) and height (m) at the run's rows for parameters named as in
    :func:`dynamic_param_names` (SI; ``modulus_scale`` or the material parameters), r1, t0 in m,
    with the cap's or the exact membrane's law (``fidelity``) and the commands replayed with the
    dead times a fit takes (s)."""
    check_delays("fit", valve_delay, sensor_delay)
    fit_material = "modulus_scale" not in params
    model = _RunModel(run, material, r1, t0, float(params["V0"]), fit_material, fidelity, valve_delay, sensor_delay)
    v = np.array([params[n] for n in model.names], dtype=float)
    P, H, _ = model.simulate(model.coords.coordinates(v)[:, None])
    return P[:, 0], H[:, 0]


def _thin(mask: np.ndarray, cap: int) -> np.ndarray:
    idx = np.flatnonzero(mask)
    if idx.size > cap:
        idx = idx[np.linspace(0, idx.size - 1, cap).round().astype(int)]
    return idx


def fit_dynamic(run: RunData, material: str, r1: float, t0: float, V0: float = 3e-6, fix: dict | None = None,
                fit_material: bool = False, sensor_range: float = 35e3, use_height: bool = True,
                fidelity: str = "cap", contact: str | None = None, source: str = "", valve_delay: float = 0.0,
                sensor_delay: float = 0.0, max_replay: float = MAX_REPLAY_S, progress=None) -> DynamicFitResult:
    """Least-squares fit of the chamber parameters (SI) to a recorded run; r1, t0 (m), V0 the
    nominal dead volume (m^3, the start), ``sensor_range`` (Pa) above which readings are saturated
    and left out. ``fix`` holds parameters at SI values. ``fidelity``: the membrane law, 'cap' or
    'exact' (with ``fit_material``, ``nh`` only). ``valve_delay``, ``sensor_delay`` (s, [0, 0.1]):
    the commands replayed as the roles' dead times (:mod:`hbma_ctrl.models.actuation`; 0: acting at
    once). ``max_replay`` (s): the longest run replayed (:func:`check_replay`). ``progress(done, total)``:
    called after each replay with an upper bound of their number (the least squares may stop early).
    ValueError for unavailable options, too few points, a flat or too long record."""
    check_delays("fit", valve_delay, sensor_delay)
    check_options(material, contact, fidelity)
    if contact == "bonded":
        raise ValueError("--contact bonded: static points only (h_mm, p_kpa and F_n or load_g); a recorded run is "
                         "replayed through a chamber model without a glued disk")
    if fidelity == "exact" and fit_material:
        check_exact_material(material, "--fit-material with --fidelity exact")
    if contact == "free" and run.load > 0:
        raise ValueError("--contact free: the run carries a load; drop --contact (a load rests on a flat plate)")
    model = _RunModel(run, material, r1, t0, V0, fit_material, fidelity, valve_delay, sensor_delay, max_replay)
    names = model.names
    fixed, free = split_fix(fix, names, "this fit", model.mat_names, " (the material's parameters are fitted with "
                            "--fit-material; without it, one modulus_scale)")
    for k, v in fixed.items():
        i = names.index(k)
        if model.coords.log[i] and not (v > 0 and abs(math.log(v / model.nominal[i])) <= _LOG_BOUND):
            raise ValueError(f"--fix {k}={v:g}: outside [{model.nominal[i] / 20:g}, {model.nominal[i] * 20:g}] (SI)")
    ifree = [names.index(n) for n in free]
    z_fixed = model.coords.coordinates([fixed.get(n, model.nominal[i]) for i, n in enumerate(names)])
    p_ok = np.isfinite(run.p) & (run.p < sensor_range - 50.0)
    ip = _thin(p_ok, MAX_POINTS)
    if ip.size == 0:
        raise ValueError(f"data: column '{run.columns['p']}': every reading is missing or saturated")
    span_p = float(run.p[ip].max() - run.p[ip].min())
    if not span_p > 0:
        raise ValueError(f"data: column '{run.columns['p']}' has one value in every row; nothing to fit")
    ih = np.zeros(0, dtype=int)
    span_h = 0.0
    if use_height and run.h is not None:
        ih = _thin(np.isfinite(run.h), MAX_POINTS)
        span_h = float(run.h[ih].max() - run.h[ih].min()) if ih.size else 0.0
        if not span_h > 0:
            ih = np.zeros(0, dtype=int)  # a height that never moves (resting load) carries no information
    n_pts = ip.size + ih.size
    if n_pts <= len(free):
        raise ValueError(f"data: {n_pts} usable points for {len(free)} free parameters ({', '.join(free)}); "
                         "record a longer run or --fix some")

    def full(zc: np.ndarray) -> np.ndarray:
        Z = np.repeat(z_fixed[:, None], zc.shape[1], axis=1)
        Z[ifree] = zc
        return Z

    def residuals(zc: np.ndarray) -> np.ndarray:
        P, H, alive = model.simulate(full(zc))
        r = (P[ip] - run.p[ip, None]) / span_p
        if ih.size:
            r = np.vstack([r, (H[ih] - run.h[ih, None]) / span_h])
        r[:, ~alive] = BAD_RESIDUAL
        return finite_residuals(r)

    def fun(z: np.ndarray) -> np.ndarray:
        return residuals(z[:, None])[:, 0]

    def jac(z: np.ndarray) -> np.ndarray:
        return central_jacobian(residuals, z, _FD_STEP)

    if progress is not None:
        # the screen, at most max_nfev residual and Jacobian replays per refined start, the estimate at
        # the optimum, the final replay
        total, done = 4 + 2 * _MAX_NFEV * _N_REFINE, [0]

        def replayed() -> None:
            done[0] = min(done[0] + 1, total)
            progress(done[0], total)
        model.on_replay = replayed
    log = model.coords.log[ifree]
    bounds = (np.where(log, -_LOG_BOUND, -10.0), np.where(log, _LOG_BOUND, 10.0))
    corners = np.array(np.meshgrid(*[(-1.0, 1.0)] * len(free), indexing="ij")).reshape(len(free), -1)
    cand = np.hstack([np.zeros((len(free), 1)), _START_OFFSET * corners])
    cost = np.sum(residuals(cand) ** 2, axis=0)
    est = identify(fun, [cand[:, j] for j in np.argsort(cost)[:_N_REFINE]], bounds, jac=jac, method="trf",
                   x_scale=1.0, xtol=1e-7, ftol=1e-9, max_nfev=_MAX_NFEV)
    z = est.x
    vals = model.values(full(z[:, None]))[:, 0]
    params = {n: float(vals[i]) for i, n in enumerate(names)}
    # the linear-scale columns of J are per nominal value; the log ones per fitted value
    ci, correlation, weak = summary(est, Coordinates.about(model.nominal[ifree]), vals[ifree], free, "this run",
                                    "fix one with --fix or record a run that moves them differently (vary the "
                                    "speed, hold with the valves shut, vent)")
    ci.update({k: [v, v] for k, v in fixed.items()})
    if "modulus_scale" in params:
        for n in model.mat_names:
            i = model.ix[n]
            scaled = i in model.mod_idx
            base = float(model.theta0[i])
            params[n] = base * params["modulus_scale"] if scaled else base
            lo_s, hi_s = ci["modulus_scale"]
            ci[n] = [base * lo_s, base * hi_s] if scaled else [base, base]
    P, H, _ = model.simulate(full(z[:, None]))
    pm, hm = P[:, 0], H[:, 0]
    if progress is not None:
        progress(total, total)
    keep = p_ok
    res = DynamicFitResult(
        material=material, params=params, ci95={k: ci[k] for k in params}, nrmsd=nrmsd(pm[keep], run.p[keep]),
        n_points=int(n_pts), unidentifiable=weak, correlation=correlation, r1=r1, t0=t0, load=run.load,
        fidelity=model.fid.name + (", exact membrane" if fidelity == "exact" else ""), fixed=fixed, source=source,
        t=run.t.copy(), p_data=run.p.copy(), p_model=pm, law=fidelity, V0_nominal=V0)
    if run.h is not None:
        hk = np.isfinite(run.h)
        res.h_data, res.h_model = run.h.copy(), hm
        res.nrmsd_h = nrmsd(hm[hk], run.h[hk]) if hk.any() else None
    return res


# ---------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------
def dynamic_params_toml(result: DynamicFitResult) -> str:
    """A parameter file for a scenario (edge units where the scenario's keys have them)."""
    title = (f" (dynamic): {result.material}, {result.n_points} points, fidelity {result.fidelity}, "
             f"pressure NRMSD {result.nrmsd:.4f}")
    lines = toml_head(result, title, result.law, f", load_g = {U.to_grams(result.load):g}",
                      (f"V0_cm3 = {U.to_cm3(result.params['V0']):.6g}",))
    lines += ["", "[pneumatics]", f"flow_scale = {result.params['flow_scale']:.6g}",
              f"C_out = {result.params['C_out']:.6g}  # the outlet's sonic conductance, m^3/(s Pa)"]
    lines += [""] + estimator_prior_lines(result)
    return "\n".join(lines) + "\n"


def estimator_prior_lines(result: DynamicFitResult) -> list[str]:
    """The ``[estimator]`` table that makes the fit the filter's prior (docs/concepts/estimation.md,
    "A calibrated filter"), written commented out: it is for an estimator without the closed loop's
    start-up calibration, whose own pulse is the better prior there (``bench loop``). With the fitted
    [actuator] and [pneumatics] values as the nominal chamber the factors start at 1, each with one
    sigma max(its 95 % half-width / 1.96, :data:`PRIOR_STD_MIN`); the factors for a scenario that
    keeps another nominal chamber follow."""
    p, ci = result.params, result.ci95
    names = (("flow_factor", "flow_scale"), ("modulus", "modulus_scale"), ("dead_volume", "V0"))
    lines = ["# The fit as the filter's prior (docs/concepts/estimation.md#a-calibrated-filter): uncomment for an",
             "# estimator that runs without the closed loop's start-up calibration (the protocol's EKF). In the",
             "# closed loop the calibration's own pulse is the better prior (measured: docs/results/ekf.md and",
             "# docs/results/loop.md).",
             "# Each sigma is at least "
             f"{PRIOR_STD_MIN:g}: the fit's model-form error on a rig of another structure, not its noise.",
             "# [estimator]"]
    means = []
    for key, fitted in names:
        if fitted in p and fitted in ci and ci[fitted][0] is not None and p[fitted] > 0:
            half = 0.5 * (math.log(ci[fitted][1]) - math.log(ci[fitted][0])) if ci[fitted][0] > 0 else math.inf
            sd = min(max(half / 1.96, PRIOR_STD_MIN), 10.0)  # (10: the key's bound; an open interval)
        else:
            sd = PRIOR_STD_MIN
        lines.append(f"# {key}_init_std = {sd:.3g}")
        v = p.get(fitted)
        if v is not None and key == "dead_volume":
            v = v / result.V0_nominal
        means.append(f"{key}_init = {v:.4g}" if v is not None else None)
    if all(means):
        lines += ["# with the factors starting at 1 on the nominal chamber above; or, keeping another nominal",
                  f"# chamber (the material's defaults, V0_cm3 = {U.to_cm3(result.V0_nominal):g}, flow_scale = 1), "
                  "these as the prior's means:"]
        lines += [f"# {m}" for m in means]
    return lines


def _plot(result: DynamicFitResult, path: Path) -> None:
    rows = 3 if result.h_data is not None else 2
    fig = Figure(figsize=(9, 2.6 * rows + 0.6))
    ax = fig.subplots(rows, 1, sharex=True)
    t = result.t
    ax[0].plot(t, U.to_kpa(result.p_data), ".", color="0.6", ms=2, label="data")
    ax[0].plot(t, U.to_kpa(result.p_model), "C0", lw=1.2, label=f"fit ({result.material}, {result.fidelity})")
    ax[0].set_ylabel("p (kPa)")
    ax[0].set_title(f"pressure NRMSD {result.nrmsd:.4f}")
    ax[0].legend(loc="best", fontsize=8)
    ax[1].axhline(0.0, color="0.6", lw=0.8)
    ax[1].plot(t, U.to_kpa(result.p_model - result.p_data), ".", ms=2)
    ax[1].set_ylabel("p residual, fit minus data (kPa)")
    if result.h_data is not None:
        ax[2].plot(t, U.to_mm(result.h_data), ".", color="0.6", ms=2, label="data")
        ax[2].plot(t, U.to_mm(result.h_model), "C1", lw=1.2, label="fit")
        ax[2].set_ylabel("h (mm)")
        ax[2].legend(loc="best", fontsize=8)
    ax[-1].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def write_dynamic_fit(result: DynamicFitResult, folder: Path | str) -> list[Path]:
    """Write fit.json, params.toml and residuals.png into ``folder``; returns their paths."""
    return write_fit(result, folder, dynamic_params_toml(result), _plot)
