"""The robot's open-loop plant: every chamber simulated under its share of the layers' load (SI).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from hbma_ctrl.core.params import Platform, Pneumatics
from hbma_ctrl.core.settings import Settings, check_range, setting
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.models.fidelity import make_fidelity
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.kinematics import forward_kinematics
from hbma_ctrl.robot.statics import load_sharing
from hbma_ctrl.sim.simulate import Plant
from hbma_ctrl.sim.trial import InputSchedule

W_FLOOR = 1e-3  # N: the smallest load a chamber model is given (a chamber in tension is flagged)


@dataclass(frozen=True)
class RobotPlantSettings(Settings):
    """What the robot's open-loop plant needs (SI).

    design : the robot (:class:`RobotDesign`).
    pneumatics : supply topology, sensor range and pressure limit (:class:`RobotPneumatics`).
    inputs : per-chamber schedules {name: ((t s, speed 0-1, inlet 0-1, outlet 0-1), ...)}; chambers
        not listed keep everything closed.
    """

    WHERE = "robot"

    design: RobotDesign = field(default_factory=RobotDesign)
    pneumatics: RobotPneumatics = field(default_factory=RobotPneumatics)
    inputs: dict = field(default_factory=dict)
    tip_force: tuple = setting((0.0, 0.0, 0.0), unit="N", key="tip_force_n", parts=("fx", "fy", "fz"),
                               doc="force on the tip, world frame")
    tip_moment: tuple = setting((0.0, 0.0, 0.0), unit="N m", key="tip_moment_nm", parts=("mx", "my", "mz"),
                                doc="moment on the tip")
    sync_period: float = setting(0.01, lo=1e-4, hi=1.0, unit="s", user="ms", key="sync_ms",
                                 doc="load-sharing and interlock update period")

    def check_rules(self) -> None:
        self.design.validate()
        self.pneumatics.validate()
        names = self.design.names
        for name, rows in self.inputs.items():
            if name not in names:
                hint = did_you_mean(name, names)
                raise ValueError(f"robot.inputs.{name}: no such chamber{hint}; chambers: {', '.join(names)}")
            InputSchedule(tuple(tuple(r) for r in rows)).validate(f"robot.inputs.{name}")


@dataclass
class RobotRun:
    """Time series of an open-loop robot scene (SI). Arrays are indexed [time, layer, chamber]."""

    t: np.ndarray
    h: np.ndarray
    p: np.ndarray
    m: np.ndarray
    lam: np.ndarray
    F: np.ndarray
    bend: np.ndarray
    direction: np.ndarray
    tip: np.ndarray
    tip_bend: np.ndarray
    rim_gap: np.ndarray
    inputs: np.ndarray
    events: list
    step_s: np.ndarray
    status: str
    wall_s: float
    tension: np.ndarray


def simulate_open_loop(settings: RobotPlantSettings, pneumatics: Pneumatics | None = None, duration: float = 30.0,
                       integrator: str = "rk4", dt: float | None = None) -> RobotRun:
    """Open-loop robot scene: every chamber's gas mass by the single-chamber model, loads shared.

    Each chamber is the ``quasi_static`` fidelity (gas mass state, dead load W, resting /
    lift-off / far-branch jumps handled by :class:`hbma_ctrl.sim.simulate.Plant`), all chambers in one
    batch. Every ``sync_period`` the robot's pose follows from the chamber heights
    (:func:`forward_kinematics`), the load sharing gives each chamber's new load W (floored at
    1 mN; chambers in tension are flagged), and the interlocks close an inlet while its chamber is
    at the pressure limit or the maximum stretch. With topology 'shared' one pump runs at the
    highest speed any open inlet asks for and its flow is split equally among the open inlets
    (each chamber's ``flow_scale`` divided by their number): a simple, documented scheme, not a
    manifold model. Loads lag the heights by at most one sync period (the layers are light, the
    motion slow).
    """
    s = settings.validate()
    pn = (pneumatics or Pneumatics()).validate()
    check_range("robot scene", "duration", duration, 1e-3, 1e5, "s", lo_open=True)
    if integrator not in ("euler", "rk4"):
        raise ValueError(f"sim.integrator = '{integrator}': the robot scene steps a batch plant, allowed euler, rk4")
    d = s.design
    N = d.n_layers
    n = 3 * N
    names = d.names
    fid = make_fidelity("quasi_static", d.chamber.material, str(pn.csv_path))
    ix = {k: i for i, k in enumerate(fid.space.names)}
    theta0 = fid.space.values(d.chamber, pn, Platform(load=1e-3))
    thetas = np.repeat(theta0[:, None], n, 1)
    F0 = load_sharing(d, np.zeros((N, 3)), s.tip_force, s.tip_moment).forces.ravel()
    thetas[ix["W"]] = np.maximum(F0, W_FLOOR)
    plant = Plant(fid, thetas, integrator, dt)
    th = plant.thetas  # the plant's own parameter matrix: loads and flow shares are updated in place
    scheds = [InputSchedule(s.inputs[nm]).validate(f"robot.inputs.{nm}") if nm in s.inputs else InputSchedule()
              for nm in names]
    k_sync = max(1, int(round(s.sync_period / plant.dt)))
    sync = k_sync * plant.dt
    nsync = int(math.ceil(duration / sync - 1e-9))
    pl, lam_max = s.pneumatics.pressure_limit, d.max_stretch
    rows: dict = {k: [] for k in ("t", "h", "p", "m", "lam", "F", "bend", "direction", "tip", "tip_bend", "rim_gap",
                                  "inputs")}
    events: list = []
    blocked = np.zeros(n, dtype=bool)
    saturated = np.zeros(n, dtype=bool)
    tension_any = np.zeros(n, dtype=bool)
    steps = []
    status = "ok"
    wall0 = time.perf_counter()

    def record(Uc, pose=None):
        h = np.maximum(plant.output("h"), 0.0)
        pose = pose or forward_kinematics(d, h.reshape(N, 3))
        now = {"t": plant.t, "h": h, **{k: plant.output(k).copy() for k in ("p", "m", "lam")}, "F": th[ix["W"]].copy(),
               "bend": pose.bend.copy(), "direction": pose.direction.copy(), "tip": pose.tip_position.copy(),
               "tip_bend": pose.tip_bend, "rim_gap": pose.rim_gap(d), "inputs": Uc.copy()}
        for k, v in now.items():
            rows[k].append(v)
        return h

    h = record(np.zeros((3, n)))
    for _ in range(nsync):
        t = plant.t
        Uc = np.column_stack([sc.at(t + 1e-9) for sc in scheds])
        p, lam = plant.output("p"), plant.output("lam")
        block = (p >= pl) | (lam >= lam_max)
        for i in np.nonzero(block & ~blocked)[0]:
            why = "pressure_limit" if p[i] >= pl else "max_stretch"
            events.append((t, names[i], f"inlet_interlock:{why}"))
        blocked = block
        Uc[1] = np.where(block, 0.0, Uc[1])
        if s.pneumatics.topology == "shared":
            open_ = (Uc[1] > 0) & (Uc[0] > 0)
            speed = Uc[0][open_].max() if open_.any() else 0.0
            Uc[0] = np.where(open_, speed, 0.0)
            th[ix["flow_scale"]] = pn.flow_scale / max(int(open_.sum()), 1)
        t0 = time.perf_counter()
        plant.advance(Uc, sync)
        h = np.maximum(plant.output("h"), 0.0)
        ls = load_sharing(d, h.reshape(N, 3), s.tip_force, s.tip_moment)
        F = ls.forces.ravel()
        th[ix["W"]] = np.maximum(F, W_FLOOR)
        steps.append(time.perf_counter() - t0)
        for i in np.nonzero((F < 0) & ~tension_any)[0]:
            events.append((plant.t, names[i], "tension"))
        tension_any |= F < 0
        sat = plant.output("p") >= s.pneumatics.sensor_range
        for i in np.nonzero(sat & ~saturated)[0]:
            events.append((plant.t, names[i], "sensor_saturated"))
        saturated = sat
        record(Uc, ls.pose)
        if not plant.alive.all():
            status = "diverged"
            break
    for i, evs in enumerate(plant.events):
        events += [(float(tt), names[i], nm) for tt, nm in evs]
    events.sort(key=lambda e: e[0])
    out = {k: np.array(v) for k, v in rows.items()}
    for k in ("h", "p", "m", "lam", "F"):  # per chamber: [time, layer, chamber]
        out[k] = out[k].reshape(len(out["t"]), N, 3)
    return RobotRun(**out, events=events, step_s=np.array(steps), status=status, wall_s=time.perf_counter() - wall0,
                    tension=tension_any.reshape(N, 3))
