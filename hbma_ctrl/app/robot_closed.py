"""The robot's closed loop: EKF bank + NMPC (or pressure PID) on the robot rig (SI).

per sample: read the 3N pressures, step the EKF bank (one mapped
  call), recompute the loads from the estimated heights (used by the next predict and by this
  period's NMPC: the one-period lag), the controller picks every chamber's supply and outlet,
  a pressure interlock (inlet closed while a reading is within ``interlock_margin`` of the limit,
  counted) guards both controllers, the rig advances one period. The controller does not know
  the tip load (a disturbance). The EKF bank runs in the pressure-PID loop too (the PID ignores
  it; its estimate is logged), so both loops' step times include it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from controllers.robot_pid import RobotPIDSettings, RobotPressurePID
from estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.app.robot_section import CONTROLLERS, RobotSettings
from hbma_ctrl.core.params import Pneumatics, check_range
from hbma_ctrl.core.units import mm
from hbma_ctrl.models.bank import ChamberBank, commands_from_inputs
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.plant import W_FLOOR
from hbma_ctrl.robot.rig import RobotRig, RobotRigSettings
from hbma_ctrl.robot.statics import load_sharing
from hbma_ctrl.robot.targets import chamber_targets, change_times


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


def make_model(design: RobotDesign, pneumatics: Pneumatics, topology: str) -> ChamberBank:
    """The nominal per-chamber model (tables up to 14 mm and 2 N)."""
    return ChamberBank(design.chamber, pneumatics, topology, load_max=2.0, h_table_max=mm(14.0))


def run_closed_loop(settings: RobotSettings, targets: dict, duration: float, controller: str = "mpc",
                    pneumatics: Pneumatics | None = None, rig: RobotRigSettings | None = None,
                    mpc: RobotMPCSettings | None = None, pid: RobotPIDSettings | None = None,
                    model: ChamberBank | None = None, tip_load=(), interlock_margin: float = 1e3,
                    h0=None, cautious=(0.75, 0.03, 0.3)) -> ClosedLoopRun:
    """Run the robot closed loop for ``duration`` s (see module doc); targets from :func:`parse_targets`.

    h0 : must be None (every run starts from rest; kept so a caller's intent fails loudly).
    cautious : (pressure fraction, k std, duty) — while a chamber's estimated pressure is above the
    fraction of its estimated peak pressure and its modulus factor's std is above the threshold,
    its supply duty is capped (the NMPC's input bound); None = off. Counted in ``cautious_steps``.
    """

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
            a, o = ctrl.step(est["x"], est["b"], W_used, href, est["k"], est["c"], a_max)
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
