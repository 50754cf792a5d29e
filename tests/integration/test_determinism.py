"""A simulation's results do not depend on the wall clock; the rig daemon's NMPC budgets still act.

Every test here runs without depending on the machine's load: a fake ``time.perf_counter``
(:class:`LoadedClock`) stands for a machine so loaded that every reading finds a second gone, far past
any budget. A scene run on it must give the bits of the same scene run on the real clock; with the
budget enforced (``[controller] enforce_budget``, ``[robot] enforce_budget``, the daemon) the
same clock must make steps overrun, which shows that the switch, not luck, keeps the wall clock out.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from hbma_ctrl.app.daemon.build import DAEMON_MPC_BUDGET, build_runner, make_rig
from hbma_ctrl.app.daemon.config import load_config
from hbma_ctrl.app.scenes.robot_loop import run_closed_loop
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.app.scenes.controller import closed_loop
from hbma_ctrl.system.roles import make_controller
from hbma_ctrl.app.scenes.robot_closed import scene_parts
from hbma_ctrl.app.schema.document import parse_role
from hbma_ctrl.controllers.mpc_solvers import OSQP_NO_TIME_LIMIT
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.sim.rig import RigSettings
from checkout import ROOT

# whole closed loops and systems built from the scenario files: seconds each
pytestmark = pytest.mark.slow

ACT, PN = Actuator(), Pneumatics()
#: a short scene: 2 mm, then 5 mm after 0.4 s, 400 g (a controller step every 20 ms)
SCENE = {"kind": "mpc", "variant": "rti_c_osqp", "horizon": 20, "sample_ms": 20.0, "calibrate": False,
         "targets_mm": [[0.0, 2.0], [0.4, 5.0]]}
DURATION = 0.8


class LoadedClock:
    """A ``time.perf_counter`` on a machine so loaded that each reading finds ``step`` s gone."""

    def __init__(self, step: float = 1.0):
        self.now, self.step, self.calls = 0.0, float(step), 0

    def __call__(self) -> float:
        self.calls += 1
        self.now += self.step
        return self.now


@pytest.fixture(scope="module")
def model():
    return PredictionModel(ACT, PN, load_max=10.0)


def _chamber_scene(model, **keys):
    """(log, controller) of the short chamber scene with the given [controller] keys."""
    section = parse_role("controller", {**SCENE, **keys})
    ctrl = make_controller(section, ACT, PN, model)
    log = closed_loop(ACT, PN, Platform(load=0.4), section, DURATION, RigSettings(seed=1), controller=ctrl,
                      calibrate=False)
    return log, ctrl


def _same_chamber_run(a, b) -> None:
    for name in ("u", "h_true", "h_est", "p_true", "p_est", "p_meas"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.supervisor_events == b.supervisor_events
    assert a.stats["fallbacks"] == b.stats["fallbacks"]
    assert a.stats["fallback_detail"] == b.stats["fallback_detail"]


def test_a_chamber_scene_on_a_loaded_clock_gives_the_bits_of_one_on_the_real_clock(model, monkeypatch):
    idle, ctrl = _chamber_scene(model)
    assert not ctrl.settings.enforce_budget  # a scene's default
    assert ctrl.backend.solver.settings.time_limit == OSQP_NO_TIME_LIMIT  # no wall-clock limit for OSQP
    clock = LoadedClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    loaded, _ = _chamber_scene(model)
    monkeypatch.undo()
    assert clock.calls > len(loaded.t)  # the estimator, the controller and the loop read it every step
    assert loaded.stats["solve_ms_median"] >= 1e3  # the timing statistics measured the fake load...
    _same_chamber_run(idle, loaded)  # ...and no decision saw it
    assert loaded.stats["fallback_detail"]["overrun"] == 0


def test_enforce_budget_from_the_scenario_key_makes_the_same_loaded_clock_overrun(model, monkeypatch):
    idle, _ = _chamber_scene(model)
    clock = LoadedClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    loaded, ctrl = _chamber_scene(model, enforce_budget=True, budget_ms=15.0)
    monkeypatch.undo()
    assert ctrl.settings.enforce_budget and ctrl.backend.solver.settings.time_limit == pytest.approx(0.015)
    detail = loaded.stats["fallback_detail"]
    # every warm step overran (the first step and the one after each fallback chain's cold start are exempt)
    assert detail["overrun"] > 0.5 * loaded.stats["steps"], detail
    assert any(e.detail == "overrun" for e in loaded.supervisor_events)  # the fallback says why
    assert not np.array_equal(idle.u, loaded.u)


ROBOT_SCENE = """
[scenario]
name = "robot_determinism"
duration_s = 5.0  # the run itself is 0.3 s (_robot_scene)

[rig]
noise_std_kpa = 0.2
sample_period_ms = 10.0
seed = 1

[robot]
mode = "closed_loop"
layers = 1
topology = "per_chamber"
controller = "mpc"
compare_baseline = false
mpc_budget = 0.8
{extra}

[robot.targets]
all = [[0.0, 5.0, 0.0, 0.0]]
"""


def _robot_scene(tmp_path: Path, extra: str = ""):
    """The closed-loop run of a one-layer robot scene for 0.3 s ([robot] mpc_budget = 0.8 and ``extra``)."""
    path = tmp_path / "robot.toml"
    path.write_text(ROBOT_SCENE.format(extra=extra))
    scn = load_scenario(path)
    s = scn.role("robot")
    rig, model, mpc = scene_parts(scn, s)
    return run_closed_loop(s, s.targets, 0.3, "mpc", scn.pneumatics, rig, mpc, model=model), mpc


def test_a_robot_scene_with_a_budget_on_a_loaded_clock_gives_the_bits_of_one_on_the_real_clock(tmp_path, monkeypatch):
    idle, mpc = _robot_scene(tmp_path)
    assert mpc.budget == 0.8 and not mpc.enforce_budget
    clock = LoadedClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    loaded, _ = _robot_scene(tmp_path)
    monkeypatch.undo()
    assert clock.calls > len(loaded.t)
    for name in ("a", "o", "h", "h_est", "p", "p_meas"):
        assert np.array_equal(getattr(idle, name), getattr(loaded, name)), name
    assert idle.events == loaded.events and loaded.fallbacks == idle.fallbacks


def test_mpc_enforce_budget_from_the_scenario_key_makes_the_same_loaded_clock_overrun(tmp_path, monkeypatch):
    idle, _ = _robot_scene(tmp_path)
    clock = LoadedClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    loaded, mpc = _robot_scene(tmp_path, "enforce_budget = true")
    monkeypatch.undo()
    assert mpc.enforce_budget
    assert any(e.detail == "overrun" for e in loaded.events)
    assert loaded.fallbacks > 0.5 * (len(loaded.t) - 1)  # every warm step overran
    assert not np.array_equal(idle.a, loaded.a)


def test_the_daemon_enforces_the_budgets_even_where_the_file_turns_them_off(tmp_path, monkeypatch):
    """The daemon is a real-time loop: its NMPCs always work to their budgets (the chamber's with
    ``[controller] enforce_budget = false`` in the file, the robot's at the daemon's default), and
    the loaded clock makes their warm steps overruns the supervisor covers."""
    text = (ROOT / "scenarios" / "daemon_chamber.toml").read_text()
    chamber = tmp_path / "daemon_chamber.toml"
    chamber.write_text(text.replace("[controller]\n", "[controller]\ncalibrate = false\nenforce_budget = false\n", 1))
    robot = tmp_path / "daemon_robot.toml"
    robot.write_text((ROOT / "scenarios" / "daemon_robot.toml").read_text().replace("mpc_budget = 0.8", ""))
    runners = []
    for path in (chamber, robot):
        cfg = load_config(path, {"--rig": "sim"})
        runner = build_runner(cfg)
        runners.append((cfg, runner, make_rig(cfg, runner)))
    (_, ch, _), (_, rb, _) = runners
    assert ch.loop.controller.settings.enforce_budget
    assert rb.loop.controller.s.enforce_budget and rb.loop.controller.s.budget == DAEMON_MPC_BUDGET
    clock = LoadedClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    for cfg, runner, rig in runners:
        for k in range(6):
            r = rig.read()
            rig.write(runner.tick(k * cfg.period, r.p))
    monkeypatch.undo()
    assert ch.loop.supervisor.failure_causes.get("overrun", 0) >= 1, ch.loop.supervisor.failure_causes
    assert rb.loop.controller.overruns >= 1
    assert rb.loop.supervisor.failure_causes.get("overrun", 0) >= 1, rb.loop.supervisor.failure_causes


def test_a_daemons_nmpc_budget_can_be_lifted_for_a_replay(model, monkeypatch):
    """``set_enforce_budget(False)`` (what a soak replay does to the daemon's chamber NMPC) takes the
    budget off the next steps and OSQP's time limit with it; on again, both come back."""
    from hbma_ctrl.controllers.mpc import NMPC
    from hbma_ctrl.controllers.mpc_settings import MPCSettings
    from hbma_ctrl.core.interfaces import Estimate, Reference

    ctrl = NMPC(ACT, PN, MPCSettings(enforce_budget=True), model=model)
    est = Estimate(t=0.0, h1=2e-3, h2=0.0, h=2e-3, F=3.9, p=11.7e3)
    monkeypatch.setattr(time, "perf_counter", LoadedClock())
    ctrl.step(0.0, est, Reference(5e-3))  # the cold start: exempt
    ctrl.step(0.02, est, Reference(5e-3))
    assert ctrl.last["status"] == "overrun"
    ctrl.set_enforce_budget(False)
    assert ctrl.backend.s is ctrl.settings and not ctrl.settings.enforce_budget
    assert ctrl.backend.solver.settings.time_limit == OSQP_NO_TIME_LIMIT
    ctrl.step(0.04, est, Reference(5e-3))
    assert ctrl.last["status"] == "ok"
    ctrl.set_enforce_budget(True)
    assert ctrl.backend.solver.settings.time_limit == pytest.approx(ctrl.settings.budget)
    ctrl.step(0.06, est, Reference(5e-3))
    assert ctrl.last["status"] == "overrun"
