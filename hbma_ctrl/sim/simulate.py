"""Simulator: integrate a fidelity of the plant over a batch of trials, with events.

Integrators (``SimSettings.integrator``), a speed/robustness ladder:

- ``euler``: explicit Euler, the paper's Simulink ode1. Cheapest per step; needs small steps.
- ``rk4``: classical Runge-Kutta, 4 evaluations a step; the default (accurate at 2 ms).
- ``radau``: adaptive implicit Runge-Kutta (scipy Radau, casadi Jacobians), error-controlled; the
  reference every benchmark compares against. One trial at a time, slowest.

The fixed-step integrators advance a whole batch of trials at once (the casadi Functions are
``map``-ped over the batch), so the 150-trial protocol costs a few thousand Function calls.
After each step the algebraic part of the state is projected back onto its constraints
(:meth:`Fidelity.project`) and the hybrid events are handled between steps: lift-off, touch-down,
snap-through (a jump to the far branch for the quasi-static model, a fast transient with the
platform model), platform airborne/landing, sensor saturation. Nothing diverges silently: a
non-finite state stops that trial with status ``diverged``.
"""

from __future__ import annotations

import math
from typing import Callable

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import FastFunction, compiled

from hbma_ctrl.models.fidelity import MODE_MOVING, MODE_REST, OUTPUTS, Fidelity, make_fidelity
from hbma_ctrl.models.fidelity_exact import make_exact
from hbma_ctrl.models.shape import ShapeSolver

__all__ = ["InputSchedule", "Trial", "SimSettings", "Log", "Plant", "period_plant", "simulate", "INTEGRATORS", "DEFAULT_DT"]

import time

from hbma_ctrl.sim.trial import (
    DEFAULT_DT,
    INTEGRATORS,
    InputSchedule,
    Log,
    SimSettings,
    Trial,
)

#: outputs whose peak over every integration step each log keeps (``Log.peaks``)
PEAK_OUTPUTS = ("h", "p", "F")

#: a gauge pressure no pneumatic HBMA reaches (10 MPa, 100 bar), Pa: a finite state past it means the
#: fixed step went unstable (e.g. a stiff membrane, E = 1e300), so the trial is diverged, not "ok"
P_DIVERGED = 1e7


# ---------------------------------------------------------------------------------------------
class _Batch:
    """Numeric helpers for one fidelity over a batch of n trials (casadi Functions mapped)."""

    def __init__(self, fid: Fidelity, thetas: np.ndarray):
        self.fid = fid
        self.theta = thetas  # (ntheta, n)
        self.n = thetas.shape[1]
        self.out = fid.mapped(fid.out, self.n)
        self.proj = fid.mapped(fid.project, self.n)
        self.idx = {k: i for i, k in enumerate(fid.space.names)}

    def th(self, name: str) -> np.ndarray:
        return self.theta[self.idx[name]]

    def y(self, X, U, mode):
        return np.asarray(self.out(X, U, self.theta, mode[None, :]))


def _far_branch(fid: Fidelity, theta: np.ndarray, m: float, h_now: float, up: bool):
    """Quasi-static snap-through: equilibrium (h1, h2) on the far branch at gas mass m.

    Walks the constant-load path h -> (h1, h2) with F = W, finds where G(h) = m R T again beyond
    the current height in the direction of motion. Returns None if there is none (deflating past
    the lowest point: the platform touches down).
    """
    ix = {k: i for i, k in enumerate(fid.space.names)}
    r1, W = theta[ix["r1"]], theta[ix["W"]]
    rt = theta[ix["R"]] * theta[ix["T"]]
    hs = np.linspace(0.0, 6 * r1, 1200)
    solver = ShapeSolver(fid.space, theta)
    h1, h2 = solver.contact(hs, W, 20 * r1)
    y = solver.eval(h1, h2)
    G = (y["p"] + theta[ix["p_env"]]) * y["V"] - m * rt
    cross = np.nonzero(np.sign(G[:-1]) != np.sign(G[1:]))[0]
    cand = [c for c in cross if (hs[c] > h_now if up else hs[c + 1] < h_now)]
    if not cand:
        return None
    c = min(cand, key=lambda c: abs(hs[c] - h_now))
    w = G[c] / (G[c] - G[c + 1])
    return (hs[c] + w * (hs[c + 1] - hs[c]) + h2[c] + w * (h2[c + 1] - h2[c]), h2[c] + w * (h2[c + 1] - h2[c]))


def _events_and_modes(fid: Fidelity, batch: _Batch, X, mode, t, U, events, y=None):
    """Hybrid transitions between steps (vectorised); returns the new (X, mode)."""
    if y is None:
        y = batch.y(X, U, mode)
    p = y[OUTPUTS.index("p")]
    r1 = batch.th("r1")
    W = batch.th("W")
    name = fid.name
    if name != "free":
        lift = (mode == MODE_REST) & (math.pi * r1**2 * p > W)
        if name == "quasi_static":
            h = X[1] - X[2]
            down = (mode == MODE_MOVING) & (h <= 0)
        else:
            down = (mode == MODE_MOVING) & (X[2] <= 0) & (X[3] <= 0)
        for i in np.nonzero(lift)[0]:
            events[i].append((t, "lift_off"))
        for i in np.nonzero(down)[0]:
            events[i].append((t, "touch_down"))
        if lift.any() or down.any():
            X = X.copy()
            mode = np.where(lift, MODE_MOVING, np.where(down, MODE_REST, mode))
            if name == "platform":
                X[2] = np.where(down, 0.0, X[2])
                X[3] = np.where(down, 0.0, X[3])
            # leaving rest: start from the flat membrane that carries the current pressure
            flat = np.asarray(batch.proj(X, batch.theta, np.zeros((1, batch.n))))
            X = np.where(lift[None, :], flat, X)
            X = np.asarray(batch.proj(X, batch.theta, mode[None, :]))
    return X, mode


_COMPILED: dict = {}
#: plant-steps (trials x steps) from which the fixed-step simulator compiles its step
COMPILE_STEPS = 20_000


def compiled_once(fun: ca.Function) -> ca.Function:
    """``fun`` compiled to C once per process (:func:`hbma_ctrl.core.codegen.compiled`; itself
    without a compiler)."""
    key = id(fun)
    if key not in _COMPILED:
        _COMPILED[key] = (fun, compiled(fun))  # fun kept alive: its id stays unique
    return _COMPILED[key][1]


class Plant:
    """A steppable batch of plants for closed-loop use (fixed-step euler/rk4), SI throughout.

    ``advance(U, duration)`` holds the inputs U (3 x n: speed, inlet, outlet, each 0-1) for
    ``duration`` seconds (a whole number of internal steps) and handles the hybrid events after
    every internal step. ``y`` is the output matrix (:data:`OUTPUTS` x n) at the current time;
    ``output(name)`` one row. A rig daemon or a closed-loop scene calls ``advance`` once per control
    period; the open-loop simulator drives it from the input schedules. ``compile``: the step
    generated as C and compiled once per machine (for long runs such as the rig's; a few seconds
    the first time for each fidelity, integrator and step).
    """

    def __init__(self, fid: Fidelity, thetas: np.ndarray, integrator: str = "rk4", dt: float | None = None,
                 compile: bool = False):
        if integrator not in ("euler", "rk4"):
            raise ValueError(f"Plant.integrator = '{integrator}': allowed euler, rk4")
        self.fid = fid
        self.thetas = np.asarray(thetas, dtype=float).reshape(fid.space.size, -1)
        self.n = self.thetas.shape[1]
        self.batch = _Batch(fid, self.thetas)
        self.dt = dt if dt is not None else DEFAULT_DT[(integrator, fid.name)]
        step = fid.step_function(integrator, self.dt)
        # compile: the one-plant step as C (cached on disk, the same source for any batch size),
        # mapped over the batch: half the time of casadi's virtual machine, the same numbers
        self._step = compiled_once(step).map(self.n) if compile else fid.mapped(step, self.n)
        # compiled: called through preallocated buffers (no numpy <-> DM conversion per step)
        self._fast = FastFunction(self._step, compile=False) if compile else None
        X0 = [fid.initial_state(self.thetas[:, i]) for i in range(self.n)]
        self.X = np.column_stack([x for x, _ in X0])
        self.mode = np.array([m for _, m in X0], dtype=float)
        self.mass_in = np.zeros(self.n)
        self.events: list = [[] for _ in range(self.n)]
        self.alive = np.ones(self.n, dtype=bool)
        self.t = 0.0
        self.k = 0
        self.U = np.zeros((3, self.n))
        self.X, self.mode = _events_and_modes(fid, self.batch, self.X, self.mode, 0.0, self.U, self.events)
        self.y = self.batch.y(self.X, self.U, self.mode)

    def output(self, name: str) -> np.ndarray:
        return self.y[OUTPUTS.index(name)]

    def set_inputs(self, U: np.ndarray) -> None:
        """Change the held inputs (3 x n) now; outputs that depend on them (flows) are refreshed."""
        U = np.asarray(U, dtype=float).reshape(3, self.n)
        if not np.all(np.isfinite(U)) or U.min() < 0 or U.max() > 1:
            raise ValueError("plant inputs: speed, inlet, outlet must be finite and in [0, 1]")
        if not np.array_equal(U, self.U):
            self.U = U.copy()
            self.y = self.batch.y(self.X, self.U, self.mode)

    def set_param(self, name: str, values) -> None:
        """Change one parameter (a theta entry, SI; e.g. 'W' the carried weight in N) for every
        plant of the batch (scalar or one value per plant), from the next step on."""
        names = self.fid.space.names
        if name not in names:
            raise ValueError(f"Plant.set_param: unknown parameter '{name}'; allowed: {', '.join(names)}")
        vals = np.broadcast_to(np.asarray(values, dtype=float), (self.n,))
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"Plant.set_param: {name} must be finite")
        # in place: the mapped Functions read this very array
        self.thetas[names.index(name)] = vals
        self.y = self.batch.y(self.X, self.U, self.mode)

    def advance(self, U: np.ndarray | None = None, duration: float | None = None) -> np.ndarray:
        """Hold inputs U for ``duration`` s (default one internal step); return the outputs."""
        if U is not None:
            self.set_inputs(U)
        nsteps = 1 if duration is None else max(1, int(round(duration / self.dt)))
        for _ in range(nsteps):
            self._one()
        return self.y

    def _one(self) -> None:
        fid, det_i = self.fid, OUTPUTS.index("det")
        t = self.t + self.dt
        Xprev, yprev, mode = self.X, self.y, self.mode
        if self._fast is not None:
            Xn, dm, y = self._fast(Xprev, self.U, self.thetas, mode)
            X, y, dm = Xn.reshape(self.n, -1).T.copy(), y.reshape(self.n, -1).T.copy(), dm.copy()
        else:
            Xn, dm, y = self._step(Xprev, self.U, self.thetas, mode[None, :])
            X, y = np.asarray(Xn), np.asarray(y)
        self.mass_in = self.mass_in + np.asarray(dm).ravel()
        changed = False
        if fid.name == "quasi_static":
            X, changed = _qs_snap_check(fid, self.batch, X, Xprev, mode, yprev[det_i], y[det_i], t, self.events)
        X, new_mode = _events_and_modes(fid, self.batch, X, mode, t, self.U, self.events, y=None if changed else y)
        if changed or np.any(new_mode != mode):
            y = self.batch.y(X, self.U, new_mode)
        if fid.name == "platform":
            _platform_flags(X, Xprev, new_mode, yprev[det_i], y[det_i], t, self.events)
        p = y[OUTPUTS.index("p")]
        bad = (~np.all(np.isfinite(X), axis=0) | ~(np.abs(p) < P_DIVERGED)) & self.alive  # nan p fails '<' too
        for i in np.nonzero(bad)[0]:
            self.events[i].append((t, "diverged"))
            self.alive[i] = False
        if not self.alive.all():
            X[:, ~self.alive] = Xprev[:, ~self.alive]
            y[:, ~self.alive] = yprev[:, ~self.alive]
        self.X, self.y, self.mode, self.t = X, y, new_mode, t
        self.k += 1


def period_plant(fid: Fidelity, thetas: np.ndarray, integrator: str, period: float, dt: float | None = None,
                 compile: bool = False) -> Plant:
    """A :class:`Plant` whose internal step divides ``period`` (s): the fewest steps of at most ``dt`` s
    (default the fidelity's, :data:`DEFAULT_DT`)."""
    dt = DEFAULT_DT[(integrator, fid.name)] if dt is None else dt
    return Plant(fid, thetas, integrator, period / max(1, int(math.ceil(period / dt - 1e-9))), compile=compile)


def _fixed_step(fid: Fidelity, trials: list[Trial], s: SimSettings, on_progress=None):
    """Euler/RK4 over the batch, driven by each trial's input schedule; ``on_progress(t)`` (simulated
    time, s) about 200 times over the run."""
    thetas = np.column_stack([fid.space.values(tr.actuator, tr.pneumatics, tr.platform) for tr in trials])
    dt = s.step_for(fid.name)
    T = max(tr.duration for tr in trials)
    # a long batch pays the one-off compile of the step (seconds, then cached on disk) back many times
    plant = Plant(fid, thetas, s.integrator, dt, compile=len(trials) * T / dt >= COMPILE_STEPS)
    dt = plant.dt
    nsteps = int(math.ceil(T / dt - 1e-9))
    every = max(1, int(round(s.log_dt / dt)))
    switch_steps = {int(round(ts / dt)) for tr in trials for ts in tr.schedule.times}
    rows = []
    durations = np.array([tr.duration for tr in trials])
    rows_peak = [OUTPUTS.index(n) for n in PEAK_OUTPUTS]
    peaks = np.full((len(rows_peak), len(trials)), -np.inf)
    report = max(1, nsteps // 200)
    for k in range(nsteps + 1):
        if on_progress is not None and k % report == 0:
            on_progress(k * dt)
        if k in switch_steps:
            plant.set_inputs(np.column_stack([tr.schedule.at((k + 0.5) * dt) for tr in trials]))
        # peaks from every step, each trial only up to its own end (a batch runs to the longest)
        within = k * dt <= durations + 1e-9
        peaks = np.where(within, np.fmax(peaks, np.asarray(plant.y)[rows_peak]), peaks)
        if k % every == 0:
            rows.append((k * dt, plant.U.copy(), plant.y, plant.mode.copy(), plant.mass_in.copy()))
        if k == nsteps:
            break
        plant._one()
    return rows, plant.events, plant.alive, peaks


def _qs_snap_check(fid, batch, X, Xprev, mode, det0, det1, t, events):
    """Quasi-static: a fold of the load path (det changes sign, or the step left the chart).

    Returns the corrected state and whether anything changed.
    """
    moving = mode == MODE_MOVING
    finite = np.all(np.isfinite(X), axis=0)
    bad = moving & (~finite | (np.sign(det1) != np.sign(det0)) | (X[2] < -1e-9))
    # a state below the flat membrane (h1 < h2) is a touch-down, not a fold
    bad &= ~(finite & (X[1] - X[2] <= 0) & (np.sign(det1) == np.sign(det0)))
    if not bad.any():
        return X, False
    X = X.copy()
    for i in np.nonzero(bad)[0]:
        m = X[0, i]
        up = X[0, i] > Xprev[0, i]
        h_now = Xprev[1, i] - Xprev[2, i]
        fb = _far_branch(fid, batch.theta[:, i], m, h_now, up=up)
        if fb is None:
            X[:, i] = [m, -1e-12, 0.0]  # no branch below: the event loop flags the touch-down
        else:
            X[:, i] = [m, fb[0], fb[1]]
            events[i].append((t, "snap_through"))
    return X, True


def _platform_flags(X, Xprev, mode, d0, d1, t, events):
    """Platform model: airborne / landing on the membrane, and fold crossings (snap-through)."""
    was_air = (Xprev[1] <= Xprev[2]) & (mode == MODE_MOVING)
    air = (X[1] <= X[2]) & (mode == MODE_MOVING)
    for i in np.nonzero(air & ~was_air)[0]:
        events[i].append((t, "airborne"))
    for i in np.nonzero(~air & was_air)[0]:
        events[i].append((t, "landed"))
    for i in np.nonzero((mode == MODE_MOVING) & (np.sign(d0) != np.sign(d1)) & ~air & ~was_air)[0]:
        events[i].append((t, "snap_through"))


#: most mode segments (integrations between events) one adaptive trial may take
MAX_SEGMENTS = 10000


def _solve_ivp():
    """scipy's solve_ivp, imported when the Radau reference runs (scipy.integrate takes 0.3 s to load,
    which every fixed-step run, the protocol's included, would pay)."""
    from scipy.integrate import solve_ivp

    return solve_ivp


def _adaptive(fid: Fidelity, trial: Trial, s: SimSettings):
    """Reference: scipy Radau per mode segment, events located to tolerance.

    Returns (rows, events, ok, theta, peaks); peaks: the largest of :data:`PEAK_OUTPUTS` over every
    accepted solver step; ok is True, False (diverged) or "incomplete" (more than
    :data:`MAX_SEGMENTS` mode segments: the run stopped early and says so).
    """
    theta = fid.space.values(trial.actuator, trial.pneumatics, trial.platform)
    batch = _Batch(fid, theta[:, None])
    f = fid.f
    xs = ca.SX.sym("x", fid.nx)
    us = ca.SX.sym("u", 3)
    ms = ca.SX.sym("mode")
    th = ca.DM(theta)
    jac = ca.Function("J", [xs, us, ms], [ca.jacobian(f(xs, us, th, ms), xs)])
    qf = ca.Function("q", [xs, us, ms], [fid.out(xs, us, th, ms)[OUTPUTS.index("q")]])
    fx = ca.Function("fx", [xs, us, ms], [f(xs, us, th, ms)])
    x, mode = fid.initial_state(theta)
    events: list = [[]]
    t = 0.0
    T = trial.duration
    log_t = np.arange(0.0, T + 1e-12, s.log_dt)
    rows = []
    mass_in = 0.0
    breaks = sorted(set(list(trial.schedule.times[1:]) + [T]))
    xa, mode_a = _events_and_modes(fid, batch, x[:, None], np.array([mode]), 0.0, trial.schedule.at(0.0)[:, None],
                                   events)
    x, mode = xa[:, 0], float(mode_a[0])
    # typical magnitude of each state (gas mass ~1e-5 kg, lengths ~1e-2 m, speeds ~1e-2 m/s)
    scale = np.array([1e-5 if n == "m" else 1e-2 for n in fid.state_names])
    next_log = 0
    r1 = theta[fid.space.names.index("r1")]
    W = theta[fid.space.names.index("W")]
    segments = 0
    peaks = [-math.inf] * len(PEAK_OUTPUTS)
    while t < T - 1e-12:
        if segments >= MAX_SEGMENTS:  # chattering between modes: stop, and say the run is incomplete
            events[0].append((t, "segment_cap"))
            return rows, events, "incomplete", theta, peaks
        t_end = min(b for b in breaks if b > t + 1e-12)
        u = trial.schedule.at(t + 1e-9)

        def rhs(tt, z):
            xdot = np.asarray(fx(z[:-1], u, mode)).ravel()
            return np.append(xdot, float(qf(z[:-1], u, mode)))

        def jacf(tt, z):
            J = np.zeros((z.size, z.size))
            J[:-1, :-1] = np.asarray(jac(z[:-1], u, mode))
            return J

        evs = []
        if fid.name != "free":
            def ev_switch(tt, z):
                y = np.asarray(fid.out(z[:-1], u, th, mode)).ravel()
                if mode == MODE_REST:
                    return math.pi * r1**2 * y[OUTPUTS.index("p")] - W
                return (z[1] - z[2]) if fid.name == "quasi_static" else z[2] + 1e-12
            ev_switch.terminal = True
            ev_switch.direction = 1 if mode == MODE_REST else -1
            evs.append(ev_switch)
            if fid.name == "quasi_static" and mode == MODE_MOVING:
                def ev_fold(tt, z):
                    return float(fid.out(z[:-1], u, th, mode)[OUTPUTS.index("det")])
                ev_fold.terminal = True
                evs.append(ev_fold)
        z0 = np.append(x, mass_in)
        atol = s.atol * np.append(scale, 1e-5)
        sol = _solve_ivp()(rhs, (t, t_end), z0, method="Radau", jac=jacf, rtol=s.rtol, atol=atol,
                        events=evs or None, dense_output=True, max_step=0.05)
        segments += 1
        if sol.status == -1:  # the step size fell below what Radau can take
            events[0].append((float(sol.t[-1]), "solver_failed"))
            return rows, events, "diverged", theta, peaks
        t_stop = sol.t[-1]
        for tt, zz in zip(sol.t, sol.y.T):  # peaks over every accepted solver step, not only the log rows
            yy = np.asarray(fid.out(zz[:-1], u, th, mode)).ravel()
            for q, n in enumerate(PEAK_OUTPUTS):
                peaks[q] = max(peaks[q], float(yy[OUTPUTS.index(n)]))
        while next_log < len(log_t) and log_t[next_log] <= t_stop + 1e-12:
            zz = sol.sol(log_t[next_log])
            rows.append((log_t[next_log], zz[:-1], u, mode, zz[-1]))
            next_log += 1
        z = sol.y[:, -1]
        x, mass_in = z[:-1].copy(), z[-1]
        if not np.all(np.isfinite(x)):
            events[0].append((t_stop, "diverged"))
            return rows, events, False, theta, peaks
        fired = sol.status == 1
        if fired and fid.name == "quasi_static" and mode == MODE_MOVING and len(sol.t_events) > 1 and sol.t_events[1].size:
            fb = _far_branch(fid, theta, x[0], x[1] - x[2], up=float(qf(x, u, mode)) > 0)
            events[0].append((t_stop, "snap_through"))
            if fb is None:
                x[1] = x[2] = 0.0
                x = np.asarray(fid.project(x, th, MODE_REST)).ravel()
                mode = MODE_REST
                events[0].append((t_stop, "touch_down"))
            else:
                x[1], x[2] = fb
            t = t_stop + 1e-9
            continue
        if fired:
            if mode == MODE_REST:
                x = np.asarray(fid.project(x, th, MODE_REST)).ravel()
                mode = MODE_MOVING
                events[0].append((t_stop, "lift_off"))
            else:
                mode = MODE_REST
                events[0].append((t_stop, "touch_down"))
                if fid.name == "platform":
                    x[2] = x[3] = 0.0
            x = np.asarray(fid.project(x, th, mode)).ravel()
            t = t_stop + 1e-9
            continue
        x = np.asarray(fid.project(x, th, mode)).ravel() if fid.name != "free" else x
        t = t_end
    return rows, events, True, theta, peaks


def simulate(trials: list[Trial], settings: SimSettings | None = None, fidelity: str | None = None,
             on_progress: Callable[[float], None] | None = None) -> list[Log]:
    """Simulate trials (one fidelity for all; None = each trial's default, grouped) -> logs.
    ``fidelity`` 'exact': the exact membrane (docs/concepts/model.md §9), the platform model for loaded trials and
    free inflation without a load (:func:`hbma_ctrl.models.fidelity_exact.make_exact`); its logs say 'exact'.
    ``on_progress(t)``: called with the simulated time (s) of the current batch as it advances
    (fixed-step integrators; adaptive runs report at the end of each trial)."""

    s = (settings or SimSettings()).validate()
    for tr in trials:
        tr.validate()
    groups: dict = {}
    for i, tr in enumerate(trials):
        fname = fidelity or tr.default_fidelity()
        # the exact rung's tables depend on the material's parameters (their shape), not only its family
        mat_key = repr(tr.actuator.material.as_dict()) if fname == "exact" else ""
        key = (fname, type(tr.actuator.material), mat_key, tr.platform.mass > 0, str(tr.pneumatics.csv_path))
        groups.setdefault(key, []).append(i)
    logs: list = [None] * len(trials)
    for (fname, _, _, loaded, csvp), idx in groups.items():
        sub = [trials[i] for i in idx]
        if fname == "exact":
            fid = make_exact(loaded, sub[0].actuator.material, csvp)
        else:
            fid = make_fidelity(fname, sub[0].actuator.material, csvp)
        if fid.needs_platform and any(tr.platform.mass <= 0 for tr in sub):
            raise ValueError(f"fidelity '{fname}' needs a load: platform.load must be > 0 kg")
        if s.integrator == "radau":
            for i, tr in zip(idx, sub):
                t0 = time.perf_counter()
                rows, events, ok, theta, peaks = _adaptive(fid, tr, s)
                if on_progress is not None:
                    on_progress(tr.duration)
                logs[i] = _rows_to_log_single(fid, tr, rows, events[0], ok, theta, s.sensor_range)
                logs[i].wall_s = time.perf_counter() - t0
                logs[i].peaks = dict(zip(PEAK_OUTPUTS, peaks))
        else:
            t0 = time.perf_counter()
            rows, events, alive, peaks = _fixed_step(fid, sub, s, on_progress)
            wall = (time.perf_counter() - t0) / len(sub)
            stack = _stack_rows(rows)
            for j, (i, tr) in enumerate(zip(idx, sub)):
                logs[i] = _rows_to_log_batch(fid, tr, stack, j, events[j], bool(alive[j]), s.sensor_range)
                logs[i].wall_s = wall
                logs[i].peaks = {n: float(peaks[q, j]) for q, n in enumerate(PEAK_OUTPUTS)}
        if fname == "exact":
            for i in idx:
                logs[i].fidelity = "exact"
    return logs


def _saturation_events(t: np.ndarray, p: np.ndarray, limit: float) -> list:
    """Sensor saturation entering/leaving, from the pressure series (the sensor is not the plant)."""
    sat = p >= limit
    out = []
    for i in np.nonzero(np.diff(sat.astype(int)) != 0)[0] + 1:
        out.append((float(t[i]), "sensor_saturated" if sat[i] else "sensor_recovered"))
    if sat.size and sat[0]:
        out.append((float(t[0]), "sensor_saturated"))
    return out


def _limit_point_events(data: dict, fidelity: str) -> list:
    """Crossings of the pressure-control limit point (det_p changes sign while the membrane moves).

    Under mass control the membrane passes it stably; a pressure-controlled actuator would snap
    there, and the paper's model (eqs. 13-15 with dp/dt given) is singular there.
    """
    d = data["det_p"]
    moving = data["mode"] > 0.5 if fidelity != "free" else np.ones_like(d, dtype=bool)
    sgn = np.sign(d)
    idx = np.nonzero((sgn[1:] != sgn[:-1]) & moving[1:] & moving[:-1] & (sgn[1:] != 0) & (sgn[:-1] != 0))[0] + 1
    return [(float(data["t"][i]), "limit_point") for i in idx]


def _finish(fid, tr, data, events, ok, sensor_range: float = 35e3) -> Log:
    status = ok if isinstance(ok, str) else ("ok" if ok else "diverged")
    ok = status == "ok"
    events = ([(float(t), n) for t, n in events] + _saturation_events(data["t"], data["p"], sensor_range)
              + _limit_point_events(data, fid.name))
    if ok and fid.needs_platform and not any(n == "lift_off" for _, n in events):
        status = "resting"
        events.append((0.0, "never_lifted"))  # the load exceeds what the pump can lift
    return Log(tr.name, fid.name, data, sorted(events, key=lambda e: e[0]), status)


def _stack_rows(rows) -> tuple:
    """A batch's logged rows (t, inputs 3 x n, outputs k x n, mode n, mass_in n) as arrays with time
    first: stacked once for the whole batch, each trial's log is then a column of them."""
    return (np.array([r[0] for r in rows], dtype=float), np.stack([np.asarray(r[1], dtype=float) for r in rows]),
            np.stack([np.asarray(r[2], dtype=float) for r in rows]),
            np.stack([np.asarray(r[3], dtype=float) for r in rows]),
            np.stack([np.asarray(r[4], dtype=float) for r in rows]))


def _rows_to_log_batch(fid, tr, stack, j, events, ok, sensor_range) -> Log:
    """Trial j's log from the batch's stacked rows (:func:`_stack_rows`), cut at its own duration."""
    t, u, y, mode, mass_in = stack
    keep = t <= tr.duration + 1e-9
    data = {"t": t[keep]}
    for k, name in enumerate(("speed", "inlet", "outlet")):
        data[name] = u[keep, k, j]
    for k, name in enumerate(OUTPUTS):
        data[name] = y[keep, k, j]
    data["mode"] = mode[keep, j]
    data["mass_in"] = mass_in[keep, j]
    return _finish(fid, tr, data, events, ok, sensor_range)


def _rows_to_log_single(fid, tr, rows, events, ok, theta, sensor_range) -> Log:
    """An adaptive trial's log from its rows (t, state, inputs, mode, mass_in): a batch of one."""
    th = ca.DM(theta)
    t = np.array([r[0] for r in rows], dtype=float)
    u = np.array([r[2] for r in rows], dtype=float).reshape(-1, 3, 1)
    y = np.array([np.asarray(fid.out(r[1], r[2], th, r[3])).ravel() for r in rows]).reshape(-1, len(OUTPUTS), 1)
    mode, mass_in = (np.array([r[i] for r in rows], dtype=float).reshape(-1, 1) for i in (3, 4))
    return _rows_to_log_batch(fid, tr, (t, u, y, mode, mass_in), 0, events, ok, sensor_range)
