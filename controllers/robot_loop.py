"""Closed-loop control of the robot on a mismatched rig: EKF bank + NMPC (or pressure PID) (SI).

Pieces
------
- :class:`RobotRig` — the "truth": every chamber of the robot is the lead's ``platform`` fidelity
  (the chamber's share of the layers as a moving mass with damping; ``quasi_static``, a dead load,
  as a setting) (gas mass, resting / lift-off / far branch handled by
  :class:`hbma_ctrl.simulate.Plant`), all chambers in ONE batch, with mismatched parameters
  (:func:`hbma_ctrl.rig.mismatched`: pump flow x0.9, dead volume x1.2; the modulus is +15 % and -15 %
  on alternate chambers, so both signs of the error are present). Every sample (10 ms) each
  chamber's load W is its share of the weight and of the tip load from
  :func:`hbma_ctrl.robot.load_sharing` of the TRUE heights. The sensors: 0.2 kPa noise, saturation
  at the robot's sensor range (50 kPa). Shared compressor: the pump's flow is split among the open
  inlets by their duties; if the duties sum to more than 1 each chamber gets its duty / sum (the
  manifold model the NMPC's coupling row respects).
- targets per layer (centre height, bend angle, bend direction at times) -> chamber heights by
  :func:`hbma_ctrl.robot.inverse_kinematics` (a negative bend is the opposite direction).
- :func:`run_closed_loop` — per sample: read the 3N pressures, step the EKF bank (one mapped
  call), recompute the loads from the estimated heights (used by the next predict and by this
  period's NMPC: the one-period lag), the controller picks every chamber's supply and outlet,
  a pressure interlock (inlet closed while a reading is within ``interlock_margin`` of the limit,
  counted) guards both controllers, the rig advances one period. The controller does not know
  the tip load (a disturbance). The EKF bank runs in the pressure-PID loop too (the PID ignores
  it; its estimate is logged), so both loops' step times include it.
- :func:`closed_loop_metrics`, plots, :func:`bench_robot` (1..6 layers).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hbma_ctrl import units as U
from hbma_ctrl.params import Platform, Pneumatics, check_range
from hbma_ctrl.robot import (LETTERS, W_FLOOR, RobotDesign, RobotSettings, forward_kinematics,
                             inverse_kinematics, load_sharing)

from .robot_model import ChamberModel, commands_from_inputs
from .robot_mpc import RobotMPCSettings, RobotNMPC
from .robot_pid import RobotPIDSettings, RobotPressurePID

__all__ = ["RobotRigSettings", "RobotRig", "parse_targets", "chamber_targets", "run_closed_loop",
           "closed_loop_metrics", "bench_robot", "run_closed_loop_scene", "CONTROLLERS"]

CONTROLLERS = ("mpc", "pressure_pid")
H_TARGET_MAX = 13e-3  # m: the per-chamber tables reach 14 mm
M_MIN = 5e-3  # kg: smallest moving mass a platform-fidelity rig chamber carries


# ---------------------------------------------------------------------------------------------
# the rig
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RobotRigSettings:
    """Mismatch, dynamics and sensors of the robot rig (SI). fidelity: 'platform' (default: each
    chamber carries its share of the layers as a moving mass with damping ``damping`` N s/m, the
    higher-fidelity truth) or 'quasi_static' (dead load, as the controller assumes). modulus_spread: chambers alternate modulus
    x(1 + spread), x(1 - spread); flow_scale, V0_scale: as :class:`hbma_ctrl.rig.RigSettings`;
    noise_std Pa; sample_period s; seed; dt: internal rk4 step (s)."""

    fidelity: str = "platform"
    damping: float = 0.5
    modulus_spread: float = 0.15
    flow_scale: float = 0.9
    V0_scale: float = 1.2
    noise_std: float = 200.0
    sample_period: float = 0.01
    seed: int = 0
    dt: float | None = None

    def validate(self) -> "RobotRigSettings":
        if self.fidelity not in ("platform", "quasi_static"):
            raise ValueError(f"robot rig.fidelity = {self.fidelity!r}: allowed platform, quasi_static")
        check_range("robot rig", "damping", self.damping, 0.0, 1e3, "N s/m")
        check_range("robot rig", "modulus_spread", self.modulus_spread, 0.0, 0.8)
        check_range("robot rig", "flow_scale", self.flow_scale, 0.1, 5.0)
        check_range("robot rig", "V0_scale", self.V0_scale, 0.2, 5.0)
        check_range("robot rig", "noise_std", self.noise_std, 0.0, 1e4, "Pa")
        check_range("robot rig", "sample_period", self.sample_period, 1e-3, 1.0, "s")
        if self.dt is not None:
            check_range("robot rig", "dt", self.dt, 1e-5, self.sample_period, "s")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"robot rig.seed = {self.seed!r} must be an integer >= 0")
        return self

    @classmethod
    def from_rig_section(cls, raw: dict | None) -> "RobotRigSettings":
        """Take a scenario's ``[rig]`` table (see :func:`hbma_ctrl.rig.parse_rig_section`): its
        modulus_scale m becomes the spread |m - 1| (alternating signs), the rest is used as is (its
        fidelity too); the sensor range is the robot's."""
        if not raw:
            return cls()
        from hbma_ctrl.rig import parse_rig_section

        r = parse_rig_section(dict(raw))
        return cls(fidelity=r.fidelity, modulus_spread=abs(r.modulus_scale - 1.0), flow_scale=r.flow_scale,
                   V0_scale=r.V0_scale, noise_std=r.noise_std, sample_period=r.sample_period,
                   seed=r.seed).validate()


class RobotRig:
    """All chambers of the robot as one mismatched batch plant with pressure sensors (module doc)."""

    def __init__(self, design: RobotDesign, pneumatics: Pneumatics, sensor_range: float, topology: str,
                 settings: RobotRigSettings | None = None, tip_load=()):
        from hbma_ctrl.model import make_fidelity
        from hbma_ctrl.rig import RigSettings, mismatched
        from hbma_ctrl.simulate import Plant

        self.s = (settings or RobotRigSettings()).validate()
        self.design = design
        self.n = 3 * design.n_layers
        self.topology = topology
        self.sensor_range = sensor_range
        self.tip_load = tuple(tip_load)
        thetas = []
        fid = None
        for i in range(self.n):
            sign = 1.0 if i % 2 == 0 else -1.0
            rs = RigSettings(fidelity=self.s.fidelity, modulus_scale=1.0 + sign * self.s.modulus_spread,
                             flow_scale=self.s.flow_scale, V0_scale=self.s.V0_scale)
            act, pn = mismatched(design.chamber, pneumatics, rs)
            if fid is None:
                fid = make_fidelity(self.s.fidelity, act.material, str(pn.csv_path))
            thetas.append(fid.space.values(act, pn, Platform(load=1e-3, damping=self.s.damping)))
        self.modulus_scales = np.array([1.0 + (1 if i % 2 == 0 else -1) * self.s.modulus_spread
                                        for i in range(self.n)])
        self.flow_scale0 = float(thetas[0][fid.space.names.index("flow_scale")])
        dt = self.s.dt if self.s.dt is not None else (1e-3 if self.s.fidelity == "platform" else 5e-3)
        self.plant = Plant(fid, np.column_stack(thetas), "rk4", dt)
        self._rng = np.random.default_rng(self.s.seed)
        self.design_g = 9.80665
        self._update_loads()

    @property
    def t(self) -> float:
        return self.plant.t

    def tip_force(self, t: float) -> np.ndarray:
        """Tip force (N, world) at time t from the (t, fx, fy, fz) rows (held from each row's time)."""
        f = np.zeros(3)
        for row in self.tip_load:
            if t + 1e-9 >= row[0]:
                f = np.asarray(row[1:4], dtype=float)
        return f

    def _update_loads(self) -> None:
        h = np.maximum(self.plant.output("h"), 0.0)
        F = load_sharing(self.design, h.reshape(-1, 3), self.tip_force(self.plant.t)).forces.ravel()
        W = np.maximum(F, W_FLOOR)
        self.plant.set_param("W", W)
        if self.plant.fid.name == "platform":
            # the moving mass each chamber carries: its share of the layers' weight (and tip load),
            # at least M_MIN so a nearly unloaded chamber stays a slow enough oscillator for RK4
            self.plant.set_param("M", np.maximum(W / self.design_g, M_MIN))
        self.loads = F

    def apply(self, Ucmd: np.ndarray) -> None:
        """Hold the inputs (3 x n) for one sample period, then update the loads from the true heights."""
        Ucmd = np.array(Ucmd, dtype=float).reshape(3, self.n)
        if self.topology == "shared":
            tot = Ucmd[1].sum()
            if tot > 1.0:
                Ucmd[1] = Ucmd[1] / tot
        self.plant.advance(Ucmd, self.s.sample_period)
        self._update_loads()

    def measure(self) -> np.ndarray:
        """Pressure readings (n,), Pa: truth + noise, saturated at the sensor range."""
        p = self.plant.output("p") + self.s.noise_std * self._rng.standard_normal(self.n)
        return np.minimum(p, self.sensor_range)

    def truth(self) -> dict:
        return {k: self.plant.output(k).copy() for k in ("h", "p", "lam", "m")}


# ---------------------------------------------------------------------------------------------
# targets
# ---------------------------------------------------------------------------------------------
def parse_targets(raw: dict, design: RobotDesign) -> dict:
    """``[robot.targets]`` {layer letter or "all": [[t_s, height_mm, bend_deg, direction_deg], ...]}
    -> {layer index: ((t s, centre m, bend rad >= 0, direction rad), ...)} (SI, sorted by time).

    A negative bend means the opposite direction. Every layer needs rows (from "all" or its
    letter). Each pose's chamber heights (inverse kinematics) must lie in [0, 13] mm (heights down
    to -0.05 mm count as 0: rounded table numbers for a flat chamber).
    """
    if not isinstance(raw, dict) or not raw:
        raise ValueError("robot.targets must be a table {A = [[t_s, height_mm, bend_deg, direction_deg], ...], ...} "
                         "(or all = [...])")
    N = design.n_layers
    letters = list(LETTERS[:N])
    out: dict = {}
    for key, rows in raw.items():
        if key != "all" and key not in letters:
            raise ValueError(f"robot.targets.{key}: no such layer; allowed: all, {', '.join(letters)}")
        if not isinstance(rows, list) or not rows or not all(isinstance(r, list) and len(r) == 4 for r in rows):
            raise ValueError(f"robot.targets.{key} must be a list of [t_s, height_mm, bend_deg, direction_deg]")
        parsed = []
        for j, r in enumerate(rows):
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in r):
                raise ValueError(f"robot.targets.{key}[{j}] must hold 4 finite numbers")
            check_range(f"robot.targets.{key}[{j}]", "t_s", r[0], 0.0, 1e5, "s")
            check_range(f"robot.targets.{key}[{j}]", "height_mm", r[1], 0.0, U.to_mm(H_TARGET_MAX), "mm")
            check_range(f"robot.targets.{key}[{j}]", "bend_deg", r[2], -60.0, 60.0, "deg")
            th = math.radians(float(r[2]))
            ps = math.radians(float(r[3])) + (math.pi if th < 0 else 0.0)
            parsed.append((float(r[0]), U.mm(float(r[1])), abs(th), math.atan2(math.sin(ps), math.cos(ps))))
        parsed.sort(key=lambda x: x[0])
        for k in (range(N) if key == "all" else [letters.index(key)]):
            if key == "all" and k in out:
                continue
            out[k] = tuple(parsed)
    for k in range(N):
        if k not in out:
            raise ValueError(f"robot.targets: layer {letters[k]} has no rows (give robot.targets.all or "
                             f"robot.targets.{letters[k]})")
        for j, (t, c, th, ps) in enumerate(out[k]):
            h = inverse_kinematics(design.with_(n_layers=1), c, th, ps)[0]
            if h.min() < -5e-5 or h.max() > H_TARGET_MAX + 1e-9:  # 0.05 mm: rounding of the table's numbers
                raise ValueError(f"robot.targets: layer {letters[k]} at t = {t:g} s needs chamber heights "
                                 f"{np.round(U.to_mm(h), 2).tolist()} mm; each must lie in [0, "
                                 f"{U.to_mm(H_TARGET_MAX):g}] mm (raise height_mm or lower bend_deg)")
    return out


def _layer_pose(rows, t: float) -> tuple:
    cur = rows[0]
    for r in rows:
        if t + 1e-9 >= r[0]:
            cur = r
    return cur


def chamber_targets(design: RobotDesign, targets: dict, t: float, cache: dict | None = None) -> np.ndarray:
    """Target chamber heights (3N,), m, at time t (``cache``: a dict reused between calls)."""
    N = design.n_layers
    if cache is not None:
        key = tuple(sum(1 for r in targets[k] if t + 1e-9 >= r[0]) for k in range(N))
        if key not in cache:
            cache[key] = chamber_targets(design, targets, t)
        return cache[key]
    c, th, ps = np.zeros(N), np.zeros(N), np.zeros(N)
    for k in range(N):
        _, c[k], th[k], ps[k] = _layer_pose(targets[k], t)
    return np.maximum(inverse_kinematics(design, c, th, ps).ravel(), 0.0)


def change_times(targets: dict) -> np.ndarray:
    """Sorted times at which any layer's target changes, s (0 included)."""
    ts = {0.0}
    for rows in targets.values():
        ts |= {r[0] for r in rows}
    return np.array(sorted(ts))


# ---------------------------------------------------------------------------------------------
# the loop
# ---------------------------------------------------------------------------------------------
@dataclass
class ClosedLoopRun:
    """Time series of a closed-loop robot run (SI); chamber arrays are (T, n)."""

    controller: str
    t: np.ndarray
    h: np.ndarray
    h_ref: np.ndarray
    h_est: np.ndarray
    p: np.ndarray
    p_meas: np.ndarray
    lam: np.ndarray
    a: np.ndarray
    o: np.ndarray
    loads: np.ndarray
    step_s: np.ndarray
    ekf_s: np.ndarray
    ctrl_s: np.ndarray
    interlocks: int
    fallbacks: int
    inaccurate: int
    status: str
    wall_s: float
    changes: np.ndarray
    b_est: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cautious_steps: int = 0


def make_model(design: RobotDesign, pneumatics: Pneumatics, topology: str) -> ChamberModel:
    """The nominal per-chamber model (tables up to 14 mm and 2 N)."""
    return ChamberModel(design.chamber, pneumatics, topology, load_max=2.0, h_table_max=14e-3)


def run_closed_loop(settings: RobotSettings, targets: dict, duration: float, controller: str = "mpc",
                    pneumatics: Pneumatics | None = None, rig: RobotRigSettings | None = None,
                    mpc: RobotMPCSettings | None = None, pid: RobotPIDSettings | None = None,
                    model: ChamberModel | None = None, tip_load=(), interlock_margin: float = 1e3,
                    h0=None, cautious=(0.75, 0.03, 0.3)) -> ClosedLoopRun:
    """Run the robot closed loop for ``duration`` s (see module doc); targets from :func:`parse_targets`.

    h0 : must be None (every run starts from rest; kept so a caller's intent fails loudly).
    cautious : (pressure fraction, k std, duty) — while a chamber's estimated pressure is above the
    fraction of its estimated peak pressure and its modulus factor's std is above the threshold,
    its supply duty is capped (the NMPC's input bound); None = off. Counted in ``cautious_steps``.
    """
    from estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings

    if controller not in CONTROLLERS:
        raise ValueError(f"robot.controller = '{controller}': allowed {', '.join(CONTROLLERS)}")
    if h0 is not None:
        raise ValueError("run_closed_loop: h0 is not supported; every run starts from rest")
    check_range("robot closed loop", "duration", duration, 1e-2, 1e4, "s")
    d = settings.design
    rp = settings.pneumatics
    pn = (pneumatics or Pneumatics()).validate()
    rs = (rig or RobotRigSettings()).validate()
    n = 3 * d.n_layers
    model = model or make_model(d, pn, rp.topology)
    if model.topology != rp.topology:
        raise ValueError("run_closed_loop: the model's topology differs from robot.topology")
    Ts = rs.sample_period
    plant = RobotRig(d, pn, rp.sensor_range, rp.topology, rs, tip_load)
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=Ts, noise_std=max(rs.noise_std, 1.0),
                                                        sensor_range=rp.sensor_range))
    if controller == "mpc":
        ms = replace(mpc or RobotMPCSettings(), sample_period=Ts, p_max=rp.pressure_limit)
        ctrl = RobotNMPC(model, n, ms)
    else:
        ctrl = RobotPressurePID(model, n, replace(pid or RobotPIDSettings(), sample_period=Ts))
    steps = int(round(duration / Ts))
    T = steps + 1
    H, HR, HE, P, PM, LM, A, O, LD, BE = (np.zeros((T, n)) for _ in range(10))
    tt = np.zeros(T)
    st, se, sc = np.zeros(steps), np.zeros(steps), np.zeros(steps)
    w_prev = np.zeros((2, n))
    W_used = np.maximum(load_sharing(d, np.zeros((d.n_layers, 3))).forces.ravel(), W_FLOOR)
    interlocks = 0
    status = "ok"
    wall0 = time.perf_counter()
    plim = rp.pressure_limit
    tcache: dict = {}
    cautious_steps = 0
    peak_p = np.array([model.peak(w)[1] for w in model.clip_load(W_used)])

    def rec(j, z, est):
        tr = plant.truth()
        tt[j] = round(plant.t, 9)
        H[j], P[j], LM[j] = np.maximum(tr["h"], 0.0), tr["p"], tr["lam"]
        HR[j] = chamber_targets(d, targets, plant.t, tcache)
        PM[j] = z
        HE[j] = est["h"] if est else 0.0
        BE[j] = est["b"] if est else 1.0
        LD[j] = plant.loads

    rec(0, plant.measure(), None)
    for j in range(steps):
        t = plant.t
        z = plant.measure()
        t0 = time.perf_counter()
        est = bank.step(z, w_prev, W_used)
        t1 = time.perf_counter()
        W_used = np.maximum(load_sharing(d, est["h"].reshape(-1, 3)).forces.ravel(), W_FLOOR)
        if controller == "mpc" and cautious is not None and j % 10 == 0:
            peak_p = np.array([model.peak(w)[1] for w in model.clip_load(W_used / est["k"])])
        # a zero target height means "lower the layer onto its stop": vent, no dithering about
        # ambient pressure (where the model has nothing to track); such chambers get no supply in
        # the NMPC either (else they take a share of a shared pump's duty budget)
        vent = chamber_targets(d, targets, t, tcache) <= 5e-5
        if controller == "mpc":
            # no preview: the NMPC sees the current target only (as the PID does); a preview would
            # start each move up to one horizon early
            href = chamber_targets(d, targets, t, tcache)
            a_max = np.where(vent, 0.0, 1.0)
            if cautious is not None:
                # cautious approach of the limit point: while a chamber's modulus factor is still
                # uncertain, pass its peak slowly, so that its filter can tell the far branch
                # (pressure falls, k lower) from the near branch (less gas) — see robot_ekf
                near = (est["p"] > cautious[0] * est["k"] * peak_p) & (est["k_std"] > cautious[1])
                a_max = np.where(near, np.minimum(a_max, cautious[2]), a_max)
                cautious_steps += int(near.sum())
            a, o = ctrl.step(est["x"], est["b"], W_used, href, est["k"], est["v"], a_max)
        else:
            a, o = ctrl.step(z, W_used, chamber_targets(d, targets, t, tcache))
        a = np.where(vent, 0.0, a)
        o = np.where(vent, 1.0, o)
        guard = np.isfinite(z) & (z >= plim - interlock_margin) & (a > 0)
        if guard.any():
            interlocks += int(guard.sum())
            a = np.where(guard, 0.0, a)
        Uc = commands_from_inputs(a, o, rp.topology)
        t2 = time.perf_counter()
        st[j], se[j], sc[j] = t2 - t0, t1 - t0, t2 - t1
        w_prev = Uc[1:].copy()
        plant.apply(Uc)
        A[j + 1], O[j + 1] = a, o
        rec(j + 1, z, est)
        if not plant.plant.alive.all():
            status = "diverged"
            T = j + 2
            break
    sl = slice(0, T)
    return ClosedLoopRun(controller, tt[sl], H[sl], HR[sl], HE[sl], P[sl], PM[sl], LM[sl], A[sl], O[sl], LD[sl],
                         st[:T - 1], se[:T - 1], sc[:T - 1], interlocks, int(getattr(ctrl, "fallbacks", 0)),
                         int(getattr(ctrl, "inaccurate", 0)), status, time.perf_counter() - wall0,
                         np.unique(np.concatenate([change_times(targets), [r[0] for r in tip_load]])),
                         BE[sl], cautious_steps)


# ---------------------------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------------------------
def _normals(design: RobotDesign, H: np.ndarray, rim: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample layer normals relative to the layer below (T, N, 3) and tip positions (T, 3);
    appends each sample's rim gaps (N,) to ``rim`` if given."""
    T = H.shape[0]
    N = design.n_layers
    nrm = np.zeros((T, N, 3))
    tip = np.zeros((T, 3))
    for j in range(T):
        pose = forward_kinematics(design, np.maximum(H[j], 0.0).reshape(N, 3))
        th, ps = pose.bend, pose.direction
        nrm[j] = np.column_stack([np.sin(th) * np.cos(ps), np.sin(th) * np.sin(ps), np.cos(th)])
        tip[j] = pose.tip_position
        if rim is not None:
            rim.append(pose.rim_gap(design))
    return nrm, tip


def closed_loop_metrics(design: RobotDesign, run: ClosedLoopRun, pressure_limit: float, settle_time: float = 2.0,
                        h_tol: float = 0.5e-3, bend_tol: float = math.radians(2.0), model=None) -> dict:
    """The "robot" metrics of a closed-loop run (edge units), on the TRUE shape.

    RMSEs are over the settled windows: samples at least ``settle_time`` after the last target
    change or tip-load change (the transients of a step are not tracking errors). Per target segment: the errors at
    its end (mean over its last 0.5 s), whether it settled within ``h_tol`` (every chamber) and
    ``bend_tol`` (every layer), and the settling time (first time from which both stay inside).
    """
    rim: list = []
    nt, tt = _normals(design, run.h, rim)
    nr, tr = _normals(design, run.h_ref)
    bend_err = np.degrees(np.arccos(np.clip((nt * nr).sum(-1), -1.0, 1.0)))  # (T, N)
    h_err = np.abs(run.h - run.h_ref) * 1e3  # mm
    tip_err = np.linalg.norm(tt - tr, axis=1) * 1e3
    ch = run.changes
    last_change = ch[np.searchsorted(ch, run.t + 1e-9, side="right") - 1]
    settled = run.t - last_change >= settle_time
    rm = lambda e: float(np.sqrt(np.mean(e[settled] ** 2))) if settled.any() else None  # noqa: E731
    segs = []
    bounds = list(ch) + [run.t[-1] + 1e-9]
    for s0, s1 in zip(bounds[:-1], bounds[1:]):
        m = (run.t >= s0) & (run.t < s1)
        if m.sum() < 2:
            continue
        end = m & (run.t >= s1 - 0.5)
        inside = (h_err.max(1) <= h_tol * 1e3) & (bend_err.max(1) <= math.degrees(bend_tol))
        idx = np.nonzero(m)[0]
        ok = inside[idx]
        t_set = None
        if ok[-1]:
            bad = np.nonzero(~ok)[0]
            first = idx[bad[-1] + 1] if bad.size else idx[0]
            t_set = float(run.t[first] - s0)
        segs.append({"t_start_s": float(s0), "t_end_s": float(min(s1, run.t[-1])),
                     "final_height_err_mm": float(h_err[end].mean(0).max()) if end.any() else None,
                     "peak_height_err_mm": float(h_err[m].max()),
                     "peak_bend_err_deg": float(bend_err[m].max()),
                     "final_bend_err_deg": float(bend_err[end].mean(0).max()) if end.any() else None,
                     "settled": bool(ok[-1]), "settle_time_s": t_set,
                     "target_heights_mm": np.round(run.h_ref[idx[-1]] * 1e3, 2).tolist()})
    names = design.names
    peak_h = None
    if model is not None:
        peak_h = np.array([model.peak(max(w, 1e-3))[0] for w in run.loads[-1]])
    far = [nm for i, nm in enumerate(names) if peak_h is not None and run.h[:, i].max() > peak_h[i] + 1e-4]
    out = {
        "mode": "closed_loop",
        "controller": run.controller,
        "chamber_height_rmse_mm": rm(h_err),
        "bend_angle_rmse_deg": rm(bend_err),
        "tip_position_rmse_mm": rm(tip_err),
        "step_ms_median": float(np.median(run.step_s) * 1e3),
        "step_ms_p99": float(np.percentile(run.step_s, 99) * 1e3),
        "step_ms_max": float(run.step_s.max() * 1e3),
        "ekf_ms_median": float(np.median(run.ekf_s) * 1e3),
        "controller_ms_median": float(np.median(run.ctrl_s) * 1e3),
        "chamber_height_rmse_all_mm": float(np.sqrt(np.mean(h_err ** 2))),
        "estimate_height_rmse_mm": float(np.sqrt(np.mean((run.h_est[1:] - run.h[1:]) ** 2)) * 1e3),
        "max_pressure_kpa": U.to_kpa(float(run.p.max())),
        "max_pressure_measured_kpa": U.to_kpa(float(np.nanmax(run.p_meas))),
        "pressure_limit_kpa": U.to_kpa(pressure_limit),
        "pressure_limit_exceeded": bool(run.p.max() > pressure_limit),
        "max_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, run.h.max(0))},
        "far_branch_chambers": far,
        "max_stretch": float(run.lam.max()),
        # < 0: the rigid three-point pose would overlap the layer below at the rim (a real layer
        # rocks on its rim there; see hbma_ctrl.robot.RobotPose.rim_gap)
        "min_rim_gap_mm": {LETTERS[k]: float(np.min(np.array(rim)[:, k]) * 1e3) for k in range(design.n_layers)},
        "stretch_exceeded_chambers": [nm for i, nm in enumerate(names) if run.lam[:, i].max() > design.max_stretch],
        "segments": segs,
        "all_segments_settled": bool(all(s["settled"] for s in segs)),
        "interlocks": run.interlocks,
        "cautious_steps": run.cautious_steps,
        "fallbacks": run.fallbacks,
        "qp_not_solved": run.inaccurate,
        "status": run.status,
        "sim_time_s": float(run.t[-1]),
        "wall_s": run.wall_s,
        "settle_time_s": settle_time,
        "tolerances": {"height_mm": h_tol * 1e3, "bend_deg": math.degrees(bend_tol)},
    }
    return out


# ---------------------------------------------------------------------------------------------
# plots and CSV
# ---------------------------------------------------------------------------------------------
def write_closed_csv(design: RobotDesign, run: ClosedLoopRun, path) -> None:
    import csv

    names = design.names
    cols = ["t_s"] + [f"{k}_{nm}_{u}" for k, u in (("h", "mm"), ("h_ref", "mm"), ("h_est", "mm"), ("p", "kpa"),
                                                     ("p_meas", "kpa"), ("supply", "1"), ("outlet", "1"))
                      for nm in names]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for j in range(run.t.size):
            row = [run.t[j]] + list(run.h[j] * 1e3) + list(run.h_ref[j] * 1e3) + list(run.h_est[j] * 1e3) + \
                list(run.p[j] / 1e3) + list(run.p_meas[j] / 1e3) + list(run.a[j]) + list(run.o[j])
            w.writerow([f"{v:.6g}" for v in row])


def plot_closed_loop(design: RobotDesign, runs: list, path, pressure_limit: float, title: str = "") -> None:
    """Signals: per chamber height (truth, target, estimate), pressures with the limit, layer bends."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    N = design.n_layers
    fig, axs = plt.subplots(N + 2, len(runs), figsize=(6.5 * len(runs), 2.4 * (N + 2)), squeeze=False,
                            sharex=True)
    cols = ["C0", "C1", "C2"]
    for c, run in enumerate(runs):
        for k in range(N):
            ax = axs[k, c]
            for i in range(3):
                j = 3 * k + i
                ax.plot(run.t, run.h[:, j] * 1e3, cols[i], lw=1.2, label=f"{design.names[j]} true")
                ax.plot(run.t, run.h_ref[:, j] * 1e3, cols[i], ls="--", lw=0.9)
                ax.plot(run.t, run.h_est[:, j] * 1e3, cols[i], ls=":", lw=0.9)
            ax.set_ylabel(f"layer {LETTERS[k]} h / mm")
            ax.legend(fontsize=6, loc="upper left", ncol=3)
        ax = axs[N, c]
        ax.plot(run.t, run.p / 1e3, lw=0.8)
        ax.axhline(pressure_limit / 1e3, color="r", ls="--", lw=1)
        ax.set_ylabel("p / kPa (limit dashed)")
        nt, _ = _normals(design, run.h[::5])
        nr, _ = _normals(design, run.h_ref[::5])
        ax = axs[N + 1, c]
        for k in range(N):
            ax.plot(run.t[::5], np.degrees(np.arctan2(nt[:, k, 0], nt[:, k, 2])), f"C{k}", lw=1.2,
                    label=f"{LETTERS[k]} x-tilt")
            ax.plot(run.t[::5], np.degrees(np.arctan2(nt[:, k, 1], nt[:, k, 2])), f"C{k}", lw=1.0, ls="-.",
                    label=f"{LETTERS[k]} y-tilt")
            ax.plot(run.t[::5], np.degrees(np.arctan2(nr[:, k, 0], nr[:, k, 2])), "k", ls="--", lw=0.7)
            ax.plot(run.t[::5], np.degrees(np.arctan2(nr[:, k, 1], nr[:, k, 2])), "k", ls=":", lw=0.7)
        ax.set_ylabel("layer tilt / deg")
        ax.set_xlabel("t / s")
        ax.legend(fontsize=6, ncol=3)
        axs[0, c].set_title(f"{title} {run.controller} (solid true, dashed target, dotted estimate)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# scene and bench
# ---------------------------------------------------------------------------------------------
def run_closed_loop_scene(scn, settings: RobotSettings, out_dir) -> dict:
    """The closed-loop ``[robot]`` scene: metrics {"robot": {...}} (+ the baseline's beside it)."""
    from hbma_ctrl.robot import plot_shapes

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = settings
    d = s.design
    rig = RobotRigSettings.from_rig_section(scn.sections.get("rig"))
    model = make_model(d, scn.pneumatics, s.pneumatics.topology)
    mpc = RobotMPCSettings(horizon=s.mpc_horizon, dt=s.mpc_dt)
    kinds = [s.controller]
    if s.compare_baseline:
        kinds.append("pressure_pid" if s.controller == "mpc" else "mpc")
    runs, mets = [], []
    for kind in kinds:
        run = run_closed_loop(s, s.targets, scn.duration, kind, scn.pneumatics, rig, mpc, model=model,
                              tip_load=s.tip_load)
        runs.append(run)
        mets.append(closed_loop_metrics(d, run, s.pneumatics.pressure_limit, s.settle_time, model=model))
        write_closed_csv(d, run, out / f"robot_{kind}_log.csv")
    metrics = dict(mets[0])
    metrics["topology"] = s.pneumatics.topology
    metrics["n_layers"] = d.n_layers
    if len(mets) > 1:
        metrics["baseline"] = {k: mets[1][k] for k in (
            "controller", "chamber_height_rmse_mm", "bend_angle_rmse_deg", "tip_position_rmse_mm",
            "chamber_height_rmse_all_mm", "max_pressure_kpa", "pressure_limit_exceeded", "all_segments_settled",
            "far_branch_chambers", "max_stretch", "stretch_exceeded_chambers", "interlocks", "step_ms_median", "step_ms_p99", "segments", "status")}
    plot_closed_loop(d, runs, out / "robot_series.png", s.pneumatics.pressure_limit, scn.name)
    r0 = runs[0]
    idx = np.unique(np.concatenate([np.searchsorted(r0.t, np.append(r0.changes[1:], r0.t[-1] + 1)) - 1]))
    idx = idx[(idx > 0) & (idx < r0.t.size)]
    if idx.size:
        plot_shapes(d, [r0.h[i].reshape(-1, 3) for i in idx], out / "robot_shape.png",
                    labels=[f"t = {r0.t[i]:.1f} s" for i in idx], title=f"{scn.name}: {r0.controller} shape over time")
    (out / "robot_segments.json").write_text(json.dumps({k: m["segments"] for k, m in zip(kinds, mets)}, indent=1))
    return {"robot": metrics}


def bench_robot(layers=(1, 2, 3, 4, 5, 6), duration: float = 3.0, topology: str = "per_chamber",
                horizon: int = 15, pneumatics: Pneumatics | None = None, model: ChamberModel | None = None
                ) -> list[dict]:
    """Step time of the whole robot (EKF bank + load sharing + NMPC) per layer count, on a closed-loop
    run of ``duration`` s (straight 6 mm, then bend 15 deg at t = duration / 2). Returns table rows."""
    from hbma_ctrl.robot import RobotPneumatics

    pn = (pneumatics or Pneumatics()).validate()
    rows = []
    for N in layers:
        d = RobotDesign(n_layers=int(N)).validate()
        s = RobotSettings(design=d, pneumatics=RobotPneumatics(topology=topology)).validate()
        model = model or make_model(d, pn, topology)
        tg = parse_targets({"all": [[0.0, 6.0, 0.0, 0.0], [duration / 2, 7.0, 15.0, 0.0]]}, d)
        run = run_closed_loop(s, tg, duration, "mpc", pn, mpc=RobotMPCSettings(horizon=horizon), model=model)
        st = run.step_s[5:] * 1e3  # the first periods include casadi/OSQP setup
        rows.append({"layers": int(N), "chambers": 3 * int(N), "qp_variables": (3 * horizon + 1) * 3 * int(N),
                     "step_ms_median": float(np.median(st)), "step_ms_p99": float(np.percentile(st, 99)),
                     "step_ms_max": float(st.max()), "ekf_ms_median": float(np.median(run.ekf_s[5:] * 1e3)),
                     "mpc_ms_median": float(np.median(run.ctrl_s[5:] * 1e3)), "steps": int(st.size),
                     "fallbacks": run.fallbacks, "max_pressure_kpa": float(run.p.max() / 1e3)})
    return rows
