"""The robot as a system: ``tick(t, p[n], held[3, n]) -> u[3, n]`` for every chamber of its layers,
layer-pose setpoints and the status a daemon shows (SI).

:class:`RobotSystem` wraps :class:`hbma_ctrl.runtime.robot.RobotLoop` (the EKF bank, load sharing,
targets, NMPC or pressure PID, the supervisor and the burst test) with the same interface as
:class:`hbma_ctrl.system.chamber.ChamberSystem`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.controllers.robot_pid import RobotPIDSettings, RobotPressurePID
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Pneumatics
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.robot.kinematics import inverse_kinematics, layer_plane
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor
from hbma_ctrl.system.base import SystemBase
from hbma_ctrl.system.chamber import SupervisorEpisodes
from hbma_ctrl.system.roles import make_model
from hbma_ctrl.system.sections import CONTROLLERS, RobotSettings

__all__ = ["RobotSystem", "robot_system"]


class RobotSystem(SystemBase):
    """The robot under :class:`RobotLoop` (see module doc). ``h_max``: the highest chamber target, m."""

    kind = "robot"

    def __init__(self, loop: RobotLoop, p_limit: float, h_max: float):
        self.loop = loop
        self.design = loop.design
        self.n = loop.n
        self.names = tuple(self.design.names)
        self.p_limit = float(p_limit)
        self.h_max = float(h_max)
        self._t = 0.0
        self._episodes = SupervisorEpisodes(loop.supervisor, self.names)
        self._bursts_reported = np.zeros(self.n, dtype=bool)

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call: the supervisor's interventions
        (:class:`SupervisorEpisodes`: interlocks, vents, a lost estimate, fallbacks)."""
        return self._episodes.take()

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
        from the inverse kinematics clipped to [0, h_max], the pose those heights give reported back."""
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
            if not all(math.isfinite(x) for x in (c, b, d)):
                raise ValueError(f"layers.{k}: centre, bend and direction must be finite")
            if not 0.0 <= b < math.pi / 2:
                raise ValueError(f"layers.{k}: bend_deg = {math.degrees(b):g} is out of range [0, 90) deg")
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

    def stats(self) -> dict:
        """The loop's statistics (ms, counts)."""
        return self.loop.stats()


def robot_system(settings: RobotSettings, targets: dict, rig_settings: RobotRigSettings, controller: str = "mpc",
                 pneumatics: Pneumatics | None = None, mpc: RobotMPCSettings | None = None,
                 pid: RobotPIDSettings | None = None, model: ChamberBank | None = None,
                 interlock_margin: float = 1e3, cautious=(0.75, 0.03, 0.3), nmpc_class=RobotNMPC,
                 p_max: float | None = None, target_rate: float | None = None) -> RobotSystem:
    """The robot system ``settings`` asks for on a rig of ``rig_settings`` (SI): the chambers' EKF bank,
    the NMPC (``mpc``, its class ``nmpc_class``) or the pressure PID (``pid``), the supervisor and the loop.

    targets : {layer: ((t s, centre m, bend rad, direction rad), ...)}.
    interlock_margin : the supply is cut while a reading is within this of the pressure limit, Pa.
    cautious : (pressure fraction, k std, duty) — while a chamber's estimated pressure is above the
        fraction of its estimated peak pressure and its modulus factor's std is above the threshold,
        its supply duty is capped (the NMPC's input bound); None = off.
    p_max : the NMPC's pressure bound, Pa (None = the robot's pressure limit).
    target_rate : the fastest a chamber's target moves, m/s (None = ``settings.target_rate``).
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
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=Ts, noise_std=max(rs.noise_std, 1.0),
                                                        sensor_range=rp.sensor_range,
                                                        valve_delay=settings.valve_delay,
                                                        sensor_delay=settings.sensor_delay))
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
