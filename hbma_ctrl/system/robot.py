"""The robot as a system: ``tick(t, p[n], held[3, n]) -> u[3, n]`` for every chamber of its layers,
layer-pose setpoints and the status a daemon shows (SI).

:class:`RobotSystem` wraps :class:`hbma_ctrl.runtime.robot.RobotLoop` (the EKF bank, load sharing,
targets, NMPC or pressure PID, the supervisor and the burst test) with the same interface as
:class:`hbma_ctrl.system.chamber.ChamberSystem`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.controllers.robot_pid import RobotPIDSettings, RobotPressurePID
from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
from hbma_ctrl.core import units as U
from hbma_ctrl.core.loopgen import LogColumn, LoopSpec, Stage
from hbma_ctrl.core.params import Pneumatics
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings, bank_step_function
from hbma_ctrl.estimators.robot_mhe import RobotMHE
from hbma_ctrl.models.actuation import acting_function, acting_state
from hbma_ctrl.models.bank import ChamberBank, throttled_inputs_function
from hbma_ctrl.robot.kinematics import inverse_kinematics, layer_plane
from hbma_ctrl.robot.plant import W_FLOOR
from hbma_ctrl.robot.plant_step import load_sharing_function
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.runtime.burst import burst_function, burst_state
from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor
from hbma_ctrl.runtime.robot_step import caps_function, net_vents_function, slew_function
from hbma_ctrl.runtime.safety_step import EVENTS, state_parts, state_size, supervisor_function
from hbma_ctrl.system.base import SystemBase
from hbma_ctrl.system.roles import make_model
from hbma_ctrl.system.sections import CONTROLLERS, ROBOT_ESTIMATORS, RobotSettings

__all__ = ["RobotSystem", "robot_system"]


class RobotSystem(SystemBase):
    """The robot under :class:`RobotLoop` (see module doc). ``h_max``: the highest chamber target, m."""

    kind = "robot"

    def __init__(self, loop: RobotLoop, p_limit: float, h_max: float):
        super().__init__(loop, loop.design.names, p_limit)
        self.design = loop.design
        self.h_max = float(h_max)
        self._t = 0.0
        self._bursts_reported = np.zeros(self.n, dtype=bool)

    def clear_faults(self) -> None:
        """Re-arm the runner's own fault tests (a bench that records a fault and goes on): the burst
        latches of the supervisor and the burst test cleared."""
        self.loop.supervisor.burst[:] = False
        if self.loop.burst is not None:
            self.loop.burst.reset()
        self._bursts_reported[:] = False

    def burst_peak(self) -> float | None:
        """The burst test's largest sum over the chambers so far, sigma (its margin to the threshold;
        None without the test)."""
        b = self.loop.burst
        return None if b is None else float(b.peak.max())

    def take_faults(self) -> list[tuple[str, int, str]]:
        """(kind, chamber, cause) faults found since the last call, which the daemon latches: the
        chambers the loop's burst test flagged (:mod:`hbma_ctrl.runtime.burst`)."""
        new = self.loop.supervisor.burst & ~self._bursts_reported
        self._bursts_reported |= new
        why = self.loop.burst.why if self.loop.burst is not None else [""] * self.n
        return [("burst", int(i), f"{self.names[i]}: {why[i] or 'flagged'} (a burst membrane or an outlet stuck open)")
                for i in np.nonzero(new)[0]]

    def tick_timing(self) -> tuple[float, float, float]:
        """The last tick's (step, estimator bank, controller) times, s."""
        return self.loop.last_timing

    def tick_parts(self) -> dict:
        """The last tick's parts (targets, controller, supervisor, valves, s) and the NMPC's report of its
        step (``nmpc data``, ``nmpc solve``, ..., ``nmpc status``)."""
        out = dict(self.loop.last_parts)
        out.update({f"nmpc {k}": v for k, v in (self.loop.controller.last_parts or {}).items()})
        return out

    def controller_report(self) -> dict | None:
        """The controller's report of its last step (the NMPC's; None for the pressure PID)."""
        return self.loop.controller.last_parts

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s) with the readings p (Pa, (n,)) -> U (3, n); ``held`` (3, n): the
        valve inputs the rig reports it held over the period p ends (None: the last ones returned)."""
        self._t = t
        self.loop.tick(t, p, held)
        return self.loop.valve_commands.copy()

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m: what the controller worked to (moving towards
        the setpoint at ``[robot] target_rate_mm_s``)."""
        h = self.loop.href
        return np.asarray(self.loop.chamber_targets(self._t) if h is None else h, dtype=float)

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber from the EKF bank, NaN before the first tick."""
        e = self.loop.estimate
        if e is None:
            return (np.full(self.n, np.nan),) * 3
        return (np.asarray(e["h"], float), np.asarray(e.get("h_std", np.full(self.n, np.nan)), float),
                np.asarray(e["p"], float))

    def layers(self) -> list:
        """The estimated pose of every layer: {"centre" m, "bend" rad, "direction" rad}."""
        h, _, _ = self.estimates()
        if not np.all(np.isfinite(h)):
            return []
        hh = np.maximum(h, 0.0).reshape(-1, 3)
        out = []
        for k in range(self.design.n_layers):
            c, b, d = layer_plane(self.design, hh[k])
            out.append({"centre": c, "bend": b, "direction": d})
        return out

    def _pose_now(self, k: int) -> tuple[float, float, float]:
        rows = self.loop.targets[k]
        cur = rows[0]
        for r in rows:
            if self._t + 1e-9 >= r[0]:
                cur = r
        return float(cur[1]), float(cur[2]), float(cur[3])

    def check_setpoint(self, request: dict) -> dict:
        """Layer poses {k: (centre m, bend rad, direction rad)} -> {"applied", "clipped"}: chamber heights
        from the inverse kinematics clipped to [0, h_max], the pose those heights give reported back. The
        request is a validated :class:`~hbma_ctrl.app.schema.api.SetpointRequest`'s (finite poses, bend in
        [0, 60] deg)."""
        if request.get("heights"):
            raise ValueError("heights_mm: the robot takes layer poses (layers) as setpoints")
        layers = request.get("layers") or {}
        if not layers:
            raise ValueError("no setpoint given: send layers")
        N = self.design.n_layers
        applied, clipped = {}, []
        for k, pose in layers.items():
            k = int(k)
            if not 0 <= k < N:
                raise ValueError(f"layers: layer {k} is out of range [0, {N - 1}]")
            c, b, d = (float(x) for x in pose)
            h = inverse_kinematics(self.design, np.full(N, c), np.full(N, b), np.full(N, d))[k]
            hc = np.clip(h, 0.0, self.h_max)
            if np.any(hc != h):
                c2, b2, d2 = layer_plane(self.design, hc)
                bad = ", ".join(f"{self.names[3 * k + i]} {U.to_mm(h[i]):.2f} mm" for i in range(3) if hc[i] != h[i])
                clipped.append(f"layers.{k}: chamber heights {bad} outside the reachable [0, {U.to_mm(self.h_max):g}] "
                               f"mm; applied centre {U.to_mm(c2):.2f} mm, bend {math.degrees(b2):.2f} deg, "
                               f"direction {math.degrees(d2):.1f} deg")
                c, b, d = float(c2), float(b2), float(d2)
            applied[k] = (c, b, d)
        return {"applied": {"layers": applied}, "clipped": clipped}

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold the applied layer poses from now on; the other layers hold their current targets."""
        new = applied.get("layers") or {}
        targets = {}
        for k in range(self.design.n_layers):
            pose = new.get(k, self._pose_now(k))
            targets[k] = ((0.0, *(float(x) for x in pose)),)
        self.loop.set_targets(targets)

    def to_function(self, t: np.ndarray, p0: np.ndarray) -> LoopSpec:
        """This system's control side as a generated loop (:class:`~hbma_ctrl.core.loopgen.LoopSpec`) over
        the tick times ``t`` (s), every part of :meth:`hbma_ctrl.runtime.robot.RobotLoop.tick` as the casadi
        Function that mirrors it, in the tick's order: ``robot_ekf`` (the command acting through the
        valves' and sensors' delays, the bank's period), ``robot_pre`` (the readings the bank trusted, the
        burst test, the loads, the targets' slew, the supply caps), the NMPC's step Function and
        ``robot_post`` (the plan with a shared pump's budget, the supervisor, a released chamber's filter
        restarted, the short vents netted, the throttled valve inputs, the valves' minimum opening). Reads
        ``t`` and the readings ``p`` (Pa, (n,); the bank starts at rest from the first, p0) and writes
        ``u`` (3 n, the valve inputs, held over the next period: the ``held`` of :meth:`tick`); the
        estimates, targets, commands, solver status and supervisor events are its log columns.
        ValueError naming the setting that cannot be generated."""
        loop = self.loop
        nmpc, bank = loop.controller, loop.bank
        if not isinstance(nmpc, RobotNMPCFunction):
            raise ValueError(f"[robot] controller: {type(nmpc).__name__} has no step Function to generate (only "
                             "'mpc' with the NMPC as one Function, RobotNMPCFunction)")
        if nmpc.s.enforce_budget and nmpc.s.budget > 0:
            raise ValueError("[robot] enforce_budget = true: an enforced wall-time budget depends on the "
                             "machine's clock; set it to false to generate the loop")
        n, N = loop.n, nmpc.s.horizon
        t = np.asarray(t, dtype=float)
        act_hist, act_fill = acting_state(bank._timing, n)
        signals = {
            "t": [0.0], "p": np.asarray(p0, dtype=float), "u": np.zeros(3 * n), "goal": np.zeros(n), "first": [1.0],
            "refresh": [1.0],
            # the bank: it starts at rest from the first readings (ChamberEKFBank.step's first call)
            "w_prev": np.zeros(2 * n), "act_hist": act_hist, "act_fill": act_fill,
            "ekf_X": bank.rest_state(p0).ravel(order="F"),
            "ekf_P": np.repeat(bank._prior_cov().reshape(16, 1, order="F"), n, 1).ravel(order="F"),
            "W": loop.loads, "gated_run": np.zeros(n),
            "h_est": np.zeros(n), "p_est": np.zeros(n), "lam": np.zeros(n), "lost": np.zeros(n), "r": np.zeros(n),
            "outlier": np.zeros(n), "k_std": np.zeros(n), "ekf_reset": np.zeros(n),
            # the tick's middle
            "burst_state": np.zeros(1) if loop.burst is None else burst_state(loop.burst),
            "zs": np.zeros(n), "burst_flagged": np.zeros(n), "href": np.zeros(n),
            "href_N": np.zeros(n * N), "a_max": np.zeros(n), "near_count": [0.0], "peak": loop._peak_p.copy(),
            "x_est": np.zeros(n), "b_est": np.zeros(n), "k_est": np.zeros(n), "c_est": np.zeros(n),
            "sup_state": loop.supervisor.state(2, N), "released": np.zeros(n),
            # the NMPC
            "prev": np.zeros(2 * n), "xbar": np.zeros(n * (N + 1)), "abar": np.zeros(n * N), "obar": np.zeros(n * N),
            "nmpc_first": [1.0], "qp_z": np.zeros(nmpc.nv), "qp_y": np.zeros(nmpc.m_rows),
            "qp_z_new": np.zeros(nmpc.nv), "qp_y_new": np.zeros(nmpc.m_rows), "warm": [0.0],
            "a_dec": np.zeros(n), "o_dec": np.zeros(n), "rti_status": [0.0], "rti_residual": [0.0],
            # after it
            "carry": np.zeros(2 * n), "event_sums": np.zeros(7), "failed": [0.0], "a_sent": np.zeros(n),
            "o_sent": np.zeros(n),
        }
        stages = [
            Stage(_ekf_function(loop), ["p", "w_prev", "act_hist", "act_fill", "ekf_X", "ekf_P", "W", "gated_run"],
                  ["act_hist", "act_fill", "ekf_X", "ekf_P", "gated_run", "h_est", "p_est", "lam", "lost", "r",
                   "outlier", "k_std", "ekf_reset"]),
            Stage(_pre_function(loop), ["t", "first", "refresh", "p", "outlier", "r", "lost", "lam", "h_est", "p_est",
                                        "k_std", "ekf_X", "goal", "href", "peak", "released", "sup_state",
                                        "burst_state"],
                  ["zs", "burst_flagged", "burst_state", "W", "href", "href_N", "a_max", "near_count", "peak", "x_est",
                   "b_est", "k_est", "c_est"]),
            Stage(nmpc.step_function, ["x_est", "b_est", "W", "k_est", "c_est", "a_max", "href_N", "prev", "xbar", "abar", "obar",
                           "nmpc_first", "qp_z", "qp_y", "warm"],
                  ["a_dec", "o_dec", "xbar", "abar", "obar", "qp_z_new", "qp_y_new", "rti_status", "rti_residual"]),
            Stage(_post_function(loop), ["t", "rti_status", "a_dec", "o_dec", "abar", "obar", "zs", "href", "lam",
                                         "lost", "burst_flagged", "sup_state", "ekf_X", "ekf_P", "qp_z_new",
                                         "qp_y_new", "qp_z", "qp_y", "warm", "p_est", "b_est", "h_est", "x_est", "W",
                                         "k_est", "c_est", "carry"],
                  ["u", "w_prev", "sup_state", "released", "ekf_X", "ekf_P", "prev", "qp_z", "qp_y", "warm",
                   "nmpc_first", "carry", "event_sums", "failed", "a_sent", "o_sent"])]
        log = []
        for i, nm in enumerate(self.names):
            log += [LogColumn(f"h_est_{nm}_mm", "h_est", i, 1e3), LogColumn(f"h_ref_{nm}_mm", "href", i, 1e3),
                    LogColumn(f"a_{nm}", "a_sent", i), LogColumn(f"o_{nm}", "o_sent", i),
                    LogColumn(f"speed_{nm}", "u", 3 * i), LogColumn(f"inlet_{nm}", "u", 3 * i + 1),
                    LogColumn(f"outlet_{nm}", "u", 3 * i + 2), LogColumn(f"burst_{nm}", "burst_flagged", i)]
        log += [LogColumn("rti_status", "rti_status"), LogColumn("failed", "failed"),
                LogColumn("cautious", "near_count")]
        log += [LogColumn(f"ev_{e}", "event_sums", j) for j, e in enumerate(EVENTS)]
        k = np.arange(t.size)
        streams = {"t": t[:, None], "goal": np.array([loop.chamber_targets(tk) for tk in t]),
                   "first": (k == 0).astype(float)[:, None], "refresh": (k % 10 == 0).astype(float)[:, None]}
        meta = {"estimator": f"EKF bank over {n} chambers (valve delay {bank.settings.valve_delay * 1e3:g} ms, sensor "
                             f"delay {bank.settings.sensor_delay * 1e3:g} ms)",
                "controller": f"robot RTI NMPC, N = {N}, dt {nmpc.s.dt * 1e3:g} ms, OSQP (casadi's) inside; "
                              f"{loop.model.topology} pump; minimum valve opening "
                              f"{loop.pwm.min_duty * loop._period * 1e3:g} ms"}
        return LoopSpec("robot", loop._period, t.size, signals, streams, stages, log, meta).validate()



def robot_system(settings: RobotSettings, targets: dict, rig_settings: RobotRigSettings, controller: str = "mpc",
                 pneumatics: Pneumatics | None = None, mpc: RobotMPCSettings | None = None,
                 pid: RobotPIDSettings | None = None, model: ChamberBank | None = None,
                 interlock_margin: float = 1e3, cautious=(0.75, 0.03, 0.3), nmpc_class=RobotNMPC,
                 p_max: float | None = None, target_rate: float | None = None, estimator: str = "ekf",
                 window: dict | None = None) -> RobotSystem:
    """The robot system ``settings`` asks for on a rig of ``rig_settings`` (SI): the chambers' EKF bank,
    the NMPC (``mpc``, its class ``nmpc_class``) or the pressure PID (``pid``), the supervisor and the loop.

    targets : {layer: ((t s, centre m, bend rad, direction rad), ...)}.
    interlock_margin : the supply is cut while a reading is within this of the pressure limit, Pa.
    cautious : (pressure fraction, k std, duty) — while a chamber's estimated pressure is above the
        fraction of its estimated peak pressure and its modulus factor's std is above the threshold,
        its supply duty is capped (the NMPC's input bound); None = off.
    p_max : the NMPC's pressure bound, Pa (None = the robot's pressure limit).
    target_rate : the fastest a chamber's target moves, m/s (None = ``settings.target_rate``).
    estimator : 'ekf' (the EKF bank) or 'mhe' (:class:`hbma_ctrl.estimators.robot_mhe.RobotMHE`, a window
        per chamber over the EKF bank; ``window`` its settings: ``horizon`` and
        :class:`~hbma_ctrl.estimators.mhe_settings.MHESettings` fields).
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"robot.controller = '{controller}': allowed {', '.join(CONTROLLERS)}")
    d = settings.design
    rp = settings.pneumatics
    pn = (pneumatics or Pneumatics()).validate()
    rs = rig_settings.validate()
    n = 3 * d.n_layers
    model = model or make_model(d, pn, rp.topology)
    if model.topology != rp.topology:
        raise ValueError("robot_system: the model's topology differs from robot.topology")
    Ts = rs.sample_period
    settings.check_period(Ts)
    if estimator not in ROBOT_ESTIMATORS:
        raise ValueError(f"estimator.kind = '{estimator}': allowed for a robot {', '.join(ROBOT_ESTIMATORS)}")
    es = ChamberEKFSettings(sample_period=Ts, noise_std=max(rs.noise_std, 1.0), sensor_range=rp.sensor_range,
                            valve_delay=settings.valve_delay, sensor_delay=settings.sensor_delay)
    if estimator == "mhe":
        bank = RobotMHE(model, n, es, **(window or {}))
    else:
        bank = ChamberEKFBank(model, n, es)
    if controller == "mpc":
        ms = replace(mpc or RobotMPCSettings(), sample_period=Ts,
                     p_max=rp.pressure_limit if p_max is None else p_max)
        ctrl = nmpc_class(model, n, ms)
    else:
        ctrl = RobotPressurePID(model, n, replace(pid or RobotPIDSettings(), sample_period=Ts))
    sup = robot_supervisor(rp.pressure_limit, n, interlock_margin,
                           plan_period=ctrl.s.dt if controller == "mpc" else None)
    loop = RobotLoop(d, model, bank, ctrl, sup, targets, cautious=cautious if controller == "mpc" else None,
                     target_rate=settings.target_rate if target_rate is None else target_rate,
                     valve_min_on=settings.valve_min_on, burst=settings.burst)
    return RobotSystem(loop, rp.pressure_limit, model.h_table_max)


# --------------------------------------------------------------------------------------------- generated loop
# each part of RobotLoop.tick as the casadi Function that mirrors it (RobotSystem.to_function)
def _ekf_function(loop) -> ca.Function:
    """robot_ekf(z[n], w_prev[2 x n], act_hist, act_fill[n], X[4 x n], P[16 x n], W[n], gated_run[n])
    -> the acting history, the bank's state and its outputs (the bank's step with the command acting)."""
    bank, n = loop.bank, loop.n
    timing = bank._timing
    act = acting_function(timing, "robot_acting").map(n)
    step = bank_step_function(bank, "robot_bank")
    MX = ca.MX
    z, w_prev = MX.sym("z", 1, n), MX.sym("w_prev", 2, n)
    hist, fill = MX.sym("act_hist", act.sparsity_in(1)), MX.sym("act_fill", 1, n)
    X, P, W, run = MX.sym("X", 4, n), MX.sym("P", 16, n), MX.sym("W", 1, n), MX.sym("gated_run", 1, n)
    # the supply as a full-speed inlet duty: the pump's row is 1 (ChamberEKFBank.step on [a, o])
    w = ca.vertcat(MX.ones(1, n), w_prev)
    u, hist_n, fill_n = act(w, hist, fill)
    out = dict(zip(step.name_out(), step(X, P, u, W, z, run)))
    keys = ["X_next", "P_next", "gated_run_next", "h", "p", "lam", "lost", "r", "outlier", "k_std", "reset"]
    return ca.Function("robot_ekf", [z, w_prev, hist, fill, X, P, W, run], [hist_n, fill_n] + [out[k] for k in keys],
                       ["z", "w_prev", "act_hist", "act_fill", "X", "P", "W", "gated_run"],
                       ["act_hist_next", "act_fill_next"] + keys)


def _pre_function(loop) -> ca.Function:
    """robot_pre: the tick's part between the bank and the NMPC (module docstring)."""
    n, N, sup, model = loop.n, loop.controller.s.horizon, loop.supervisor, loop.model
    MX = ca.MX
    t, first, refresh = MX.sym("t"), MX.sym("first"), MX.sym("refresh")
    z, outlier, r, lost, lam, h, p, k_std = (MX.sym(s, n) for s in ("z", "outlier", "r", "lost", "lam", "h", "p",
                                                                     "k_std"))
    X = MX.sym("X", 4, n)
    goal, href_prev, peak, released = (MX.sym(s, n) for s in ("goal", "href_prev", "peak", "released"))
    sst = MX.sym("sup_state", state_size(n, 2, N))
    bst = MX.sym("burst_state", 1 if loop.burst is None else burst_state(loop.burst).size)
    # the interlock sees the readings the bank trusted (an outlier is no pressure)
    zs = ca.if_else(outlier != 0, ca.DM.nan(n, 1), z)
    parts = state_parts(n, 2, N)
    sup_lost, sup_burst = sst[parts["lost"]], sst[parts["burst"]]
    if loop.burst is not None:
        bf = burst_function(loop.burst.settings, n, "robot_burst")
        lost_new = ca.logic_and(lost != 0, ca.logic_not(sup_lost != 0))
        _, flagged, bst_next = bf(t, r, lost_new, released, bst)
    else:
        flagged, bst_next = MX.zeros(n), bst
    share = load_sharing_function(loop.design, "robot_loads")
    W = ca.fmax(share(h, MX.zeros(3), MX.zeros(3))[0], W_FLOOR)
    href = slew_function(n, loop.target_rate, "robot_slew")(goal, href_prev, h, first, loop._period)
    caps = caps_function(model, n, loop.cautious, sup.settings.vent_height, sup.settings.stretch_max, "robot_caps")
    k = X[2, :].T
    a_max, near, peak_next = caps(W, k, p, k_std, href, lam, lost, sup_lost, sup_burst, peak, refresh)
    x, b, c = (X[3, :] * X[0, :] - 1).T, X[1, :].T, X[3, :].T
    return ca.Function(
        "robot_pre", [t, first, refresh, z, outlier, r, lost, lam, h, p, k_std, X, goal, href_prev, peak, released, sst,
                      bst],
        [zs, flagged, bst_next, W, href, ca.repmat(href, 1, N), a_max, ca.sum1(near), peak_next, x, b, k, c],
        ["t", "first", "refresh", "z", "outlier", "r", "lost", "lam", "h", "p", "k_std", "X", "goal", "href_prev",
         "peak", "released", "sup_state", "burst_state"],
        ["zs", "burst_flagged", "burst_state_next", "W", "href", "href_N", "a_max", "near_count", "peak_next", "x", "b", "k",
         "c"])


def _post_function(loop) -> ca.Function:
    """robot_post: the tick's part after the NMPC (module docstring)."""
    nmpc, bank, model, sup = loop.controller, loop.bank, loop.model, loop.supervisor
    n, N, topo = loop.n, nmpc.s.horizon, model.topology
    MX = ca.MX
    t, status = MX.sym("t"), MX.sym("status")
    a_dec, o_dec, zs, href, lam, lost, flagged = (MX.sym(s, n) for s in ("a_dec", "o_dec", "zs", "href", "lam", "lost",
                                                                         "burst_flagged"))
    abar, obar = MX.sym("abar", n, N), MX.sym("obar", n, N)
    sst = MX.sym("sup_state", state_size(n, 2, N))
    X, P = MX.sym("X", 4, n), MX.sym("P", 16, n)
    zq_new, yq_new, zq, yq = (MX.sym(s, m) for s, m in (("qp_z_new", nmpc.nv), ("qp_y_new", nmpc.m_rows),
                                                         ("qp_z", nmpc.nv), ("qp_y", nmpc.m_rows)))
    warm = MX.sym("warm")
    p, b, h, x, W, k, c = (MX.sym(s, n) for s in ("p", "b", "h", "x", "W", "k", "c"))
    carry = MX.sym("carry", 2, n)
    ok = status == 0
    # the plan, rows [row][chamber][supply, outlet], a shared pump's budget on every row (RobotLoop._plan)
    rows = []
    for j in range(N):
        aj, oj = abar[:, j], obar[:, j]
        if topo == "shared":
            s_ = ca.sum1(aj)
            aj = ca.if_else(s_ > 1.0, aj / ca.fmax(s_, 1e-12), aj)
        rows.append(ca.vec(ca.horzcat(aj, oj).T))
    plan = ca.vertcat(*rows)
    command = ca.vec(ca.horzcat(a_dec, o_dec).T)
    supervise = supervisor_function(sup.settings, n, 2, N, "robot_supervisor")
    okv = ca.repmat(ok, n, 1)
    out, sst_next, released, events, failed = supervise(t, command, zs, okv, plan, ok, href, lam, lost, flagged, sst)
    cmd = ca.reshape(out, 2, n)
    a, o = cmd[0, :].T, cmd[1, :].T
    # a released chamber's filter restarts at rest from its reading (ChamberEKFBank.reset)
    lo, hi = bank._bounds
    # a reading out of the physical range (NaN, +-inf too: every comparison is false for NaN) reads as 0
    p0 = ca.if_else(ca.logic_and(zs >= lo, zs <= hi), zs, 0.0)
    X_rest, P_rest = bank.rest_expr(p0.T)
    X_next = ca.if_else(ca.repmat((released != 0).T, 4, 1), X_rest, X)
    P_next = ca.if_else(ca.repmat((released != 0).T, 16, 1), P_rest, P)
    prev = ca.horzcat(a, o).T  # what the NMPC's input-rate terms start from (RobotNMPC.applied)
    if loop.pwm.active:
        nv = net_vents_function(model, n, loop.pwm.min_duty, loop._period, "robot_net_vents")
        a, o, carry_v = nv(a, o, p, b, h - href, x, W, k, c, carry)
    else:
        carry_v = carry
    Uc = throttled_inputs_function(model.pump, n, topo, name="robot_valve_inputs")(a, o, p)
    # the supply as the full-speed inlet duty its flow equals (RobotLoop's _flow_duty)
    supply = ca.fmin(ca.fmax(a, 0.0), 1.0)
    supply = ca.if_else(supply < 1e-4, 0.0, supply)
    if topo == "shared":
        tot = ca.sum1(supply)
        supply = ca.if_else(tot > 1.0, supply / tot, supply)
    if loop.pwm.active:
        Us, carry_n = loop.pwm.function("robot_pwm").map(n)(Uc, carry_v)
        inlet = Uc[1, :].T
        supply = supply * ca.if_else(inlet > 0.0, Us[1, :].T / ca.if_else(inlet > 0.0, inlet, 1.0), 0.0)
        Uc = Us
    else:
        carry_n = carry_v
    w_prev = ca.horzcat(supply, Uc[2, :].T).T
    # this tick's interventions per kind (the Supervisor's counts' increments, summed over the chambers),
    # EVENTS order
    ev_sums = ca.vertcat(*[ca.sum1(events[j * n:(j + 1) * n]) for j in range(len(EVENTS))])
    return ca.Function(
        "robot_post", [t, status, a_dec, o_dec, abar, obar, zs, href, lam, lost, flagged, sst, X, P, zq_new, yq_new, zq,
                       yq, warm, p, b, h, x, W, k, c, carry],
        [Uc, w_prev, sst_next, released, X_next, P_next, prev, ca.if_else(ok, zq_new, zq), ca.if_else(ok, yq_new, yq),
         ca.logic_or(warm != 0, ok), MX(0.0), carry_n, ev_sums, failed, a, o],
        ["t", "status", "a_dec", "o_dec", "abar", "obar", "zs", "href", "lam", "lost", "burst_flagged", "sup_state",
         "X", "P", "qp_z_new", "qp_y_new", "qp_z", "qp_y", "warm", "p", "b", "h", "x", "W", "k", "c", "carry"],
        ["U", "w_prev", "sup_state_next", "released", "X_next", "P_next", "prev", "qp_z_next", "qp_y_next",
         "warm_next", "first_next", "carry_next", "event_sums", "failed", "a_sent", "o_sent"])

