"""The robot's closed loop on the robot rig: rig -> :class:`hbma_ctrl.runtime.robot.RobotLoop` -> rig (SI).

Per sample: read the 3N pressures, ``RobotLoop.tick`` (EKF bank, load sharing, targets, NMPC or
pressure PID, the supervisor's fallback, vent rule and pressure interlock), the rig advances one
period, and the run is logged. The EKF bank runs in the pressure-PID loop too (the PID ignores it;
its estimate is logged), so both loops' step times include it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.controllers.robot_pid import RobotPIDSettings
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core.params import Pneumatics, check_range
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.robot.targets import change_times
from hbma_ctrl.system.robot import RobotSystem, robot_system
from hbma_ctrl.system.run import run_lockstep
from hbma_ctrl.system.sim_rig import SimRig


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
    events: list = field(default_factory=list)  # the supervisor's interventions (SupervisorEvent)
    stretch_interlocks: int = 0  # the stretch interlock's supply cuts (chamber steps)
    lost_estimate_steps: int = 0  # chamber steps vented for a lost estimate
    bursts: list = field(default_factory=list)  # chambers the burst test flagged (indices)
    burst_peak_sigma: float = 0.0  # the burst test's largest sum, sigma (0 without the test)
    estimator_stats: dict = field(default_factory=dict)  # the estimator's counts (its ``stats()``)


def build_closed_loop(settings: RobotSettings, targets: dict, controller: str = "mpc",
                      pneumatics: Pneumatics | None = None, rig: RobotRigSettings | None = None,
                      mpc: RobotMPCSettings | None = None, pid: RobotPIDSettings | None = None,
                      model: ChamberBank | None = None, tip_load=(), interlock_margin: float = 1e3,
                      cautious=(0.75, 0.03, 0.3), nmpc_class=RobotNMPC, estimator: str = "ekf",
                      window: dict | None = None) -> tuple[SimRig, RobotSystem]:
    """The simulated robot rig and the system that drives it (:func:`run_closed_loop`'s arguments;
    ``nmpc_class`` the NMPC's class, :class:`RobotNMPC` or one with its interface). A generated loop is
    built from the same objects (:mod:`hbma_ctrl.app.codegen.robot`). ``estimator``, ``window``: as
    :func:`~hbma_ctrl.system.robot.robot_system`'s."""
    rs = (rig or RobotRigSettings()).validate()
    system = robot_system(settings, targets, rs, controller, pneumatics, mpc, pid, model, interlock_margin,
                          cautious, nmpc_class, estimator=estimator, window=window)
    return SimRig.robot(settings, rs, pneumatics, tip_load), system


def run_closed_loop(settings: RobotSettings, targets: dict, duration: float, controller: str = "mpc",
                    pneumatics: Pneumatics | None = None, rig: RobotRigSettings | None = None,
                    mpc: RobotMPCSettings | None = None, pid: RobotPIDSettings | None = None,
                    model: ChamberBank | None = None, tip_load=(), interlock_margin: float = 1e3,
                    cautious=(0.75, 0.03, 0.3), nmpc_class=RobotNMPC, estimator: str = "ekf",
                    window: dict | None = None) -> ClosedLoopRun:
    """Run the robot closed loop for ``duration`` s from rest (see module doc).

    targets : {layer: ((t s, centre m, bend rad, direction rad), ...)}.
    interlock_margin : the supply is cut while a reading is within this of the pressure limit, Pa.
    cautious : (pressure fraction, k std, duty) — while a chamber's estimated pressure is above the
    fraction of its estimated peak pressure and its modulus factor's std is above the threshold,
    its supply duty is capped (the NMPC's input bound); None = off. Counted in ``cautious_steps``.
    The fastest a chamber's target height moves, the valves' shortest opening and the delays the
    chambers' filters take are ``settings``' (``target_rate`` m/s, None or 0: targets step;
    ``valve_min_on``, ``valve_delay``, ``sensor_delay``, s). ``nmpc_class``: the NMPC's class
    (:class:`hbma_ctrl.controllers.robot_rti_step.RobotNMPCFunction` runs the generated loop's step).
    ``estimator``: 'ekf' (the EKF bank) or 'mhe' (its windows' settings ``window``; see
    :func:`~hbma_ctrl.system.robot.robot_system`).
    """
    check_range("robot closed loop", "duration", duration, 1e-2, 1e4, "s")
    sim, system = build_closed_loop(settings, targets, controller, pneumatics, rig, mpc, pid, model, tip_load,
                                    interlock_margin, cautious, nmpc_class, estimator, window)
    plant, loop = sim.rig, system.loop
    n = loop.n
    ctrl, sup = loop.controller, loop.supervisor
    steps = int(round(duration / sim.sample_period))
    T = steps + 1
    H, HR, HE, P, PM, LM, A, O, LD, BE = (np.zeros((T, n)) for _ in range(10))
    tt = np.zeros(T)
    st, se, sc = np.zeros(steps), np.zeros(steps), np.zeros(steps)
    status = "ok"
    wall0 = time.perf_counter()

    def rec(j, z, est):
        tr = plant.truth()
        tt[j] = round(plant.t, 9)
        H[j], P[j], LM[j] = np.maximum(tr["h"], 0.0), tr["p"], tr["lam"]
        HR[j] = loop.chamber_targets(plant.t)
        PM[j] = z
        HE[j] = est["h"] if est else 0.0
        BE[j] = est["b"] if est else 1.0
        LD[j] = plant.loads

    def ticked(j: int, r, u: np.ndarray) -> None:
        st[j], se[j], sc[j] = loop.last_timing

    def advanced(j: int, r, u: np.ndarray) -> bool:
        nonlocal status, T
        A[j + 1], O[j + 1] = loop.decision
        rec(j + 1, r.p, loop.estimate)
        if not plant.plant.alive.all():
            status, T = "diverged", j + 2
            return True
        return False

    # the first row is the rig at rest, with a reading of its own
    rec(0, plant.measure(), None)
    # ticked on the robot plant's own clock (its sub-steps sum it), on which its loads and tip load run
    run_lockstep(system, sim, duration, ticked=ticked, advanced=advanced, clock=lambda r: plant.t)
    sl = slice(0, T)
    ls = loop.stats()
    return ClosedLoopRun(controller, tt[sl], H[sl], HR[sl], HE[sl], P[sl], PM[sl], LM[sl], A[sl], O[sl], LD[sl],
                         st[:T - 1], se[:T - 1], sc[:T - 1], sup.counts["guard"], sup.failed_steps,
                         int(ctrl.inaccurate), status, time.perf_counter() - wall0,
                         np.unique(np.concatenate([change_times(targets), [r[0] for r in tip_load]])),
                         BE[sl], loop.cautious_steps, list(sup.events), sup.counts["stretch_guard"],
                         sup.counts["lost_estimate"], ls["bursts"], ls["burst_peak_sigma"], ls["estimator"])
