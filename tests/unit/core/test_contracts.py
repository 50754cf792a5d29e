"""The roles' contracts (:mod:`hbma_ctrl.core.interfaces`): every shipped role satisfies its Protocol, a
role of one's own that subclasses a base and writes ``step`` runs in the loops, and a role that lacks a
member is refused when the loop is built, with the member named."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.controllers.baselines import BangBangController, BangBangSettings, PIDController, PIDSettings
from hbma_ctrl.controllers.dompc_ref import DoMPCController
from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.controllers.robot_pid import RobotPressurePID
from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import (
    SAFE_COMMAND,
    STEP_OK,
    Command,
    Controller,
    ControllerBase,
    ControllerSettings,
    Estimate,
    Estimator,
    EstimatorBase,
    Reference,
    RobotController,
    RobotControllerBase,
    RobotEstimateController,
    RobotReadingsController,
    SolveStatus,
    StepStatus,
    check_role,
    protocol_members,
)
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.estimators.ukf import UKF, UKFSettings
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.runtime.chamber import ChamberLoop, chamber_supervisor
from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor
from hbma_ctrl.system.roles import make_model

ACT, PN = Actuator(), Pneumatics()


@pytest.fixture(scope="module")
def model():
    return PredictionModel(ACT, PN, membrane="cap")


@pytest.fixture(scope="module")
def robot():
    d = RobotDesign(n_layers=1).validate()
    return d, make_model(d, Pneumatics(), "per_chamber")


def _bank(model, n=3):
    return ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=0.01, sensor_range=60e3))


class Flat(EstimatorBase):
    """An estimator of one's own: the reading as the pressure, the membrane flat."""

    def step(self, t, measurement, applied_command):
        return Estimate(t=t, h1=0.0, h2=0.0, h=0.0, F=0.0, p=float(measurement))


class Pump(ControllerBase):
    """A controller of one's own: only ``step`` (pump below the target, vent above)."""

    def step(self, t, estimate, reference, preview=None):
        return Command(1.0, 1.0, 0.0) if estimate.p < 10e3 else Command(0.0, 0.0, 1.0)


# --- every shipped role is an instance of its Protocol ----------------------------------------------
def test_shipped_chamber_controllers_satisfy_the_controller_contract(model):
    ctrls = [NMPC(ACT, PN, MPCSettings(variant="rti_osqp", codegen=False), model=model),
             PIDController(settings=PIDSettings()), BangBangController(ACT, PN, BangBangSettings(), model=model)]
    for c in ctrls:
        assert isinstance(c, Controller), type(c).__name__
        assert isinstance(c.settings, ControllerSettings), type(c).__name__
    nmpc, pid, bang = ctrls
    assert nmpc.reports_failures and nmpc.accepts_preview and nmpc.step_status == STEP_OK
    for c in (pid, bang):  # the base's defaults: no plan, never failed, no preview
        assert c.plan is None and not c.reports_failures and not c.accepts_preview and c.step_status.ok
        assert c.applied(SAFE_COMMAND) is None
    # the PID's settings have no height bounds: the optional settings members' defaults
    assert (pid.settings.h_min, pid.settings.h_max, pid.settings.fallback_plan_steps) == (0.0, U.mm(20.0), 10)
    # do-mpc is an optional extra: its class carries the contract's defaults
    assert issubclass(DoMPCController, ControllerBase) and DoMPCController.accepts_preview


def test_shipped_estimators_satisfy_the_estimator_contract():
    for est in (EKF(ACT, PN, EKFSettings(compile=False)), UKF(ACT, PN, UKFSettings(compile=False))):
        assert isinstance(est, Estimator), type(est).__name__
        assert est.state_names and est.last_nis is None and est.last_innovation is None
        assert est.attach(object()) is None


def test_the_bench_filterpy_baseline_satisfies_the_estimator_contract():
    pytest.importorskip("filterpy")
    from hbma_ctrl.app.scenes.evaluate import FilterpyEKF
    from hbma_ctrl.estimators.common import FilterSettings

    f = FilterpyEKF(ACT, PN, FilterSettings())
    assert isinstance(f, Estimator) and f.last_innovation is None


def test_shipped_robot_controllers_satisfy_the_robot_contract(robot):
    d, model = robot
    nmpc = RobotNMPC(model, 3, RobotMPCSettings())
    pid = RobotPressurePID(model, 3)
    assert isinstance(nmpc, RobotEstimateController) and nmpc.feedback == "estimate"
    assert isinstance(pid, RobotReadingsController) and pid.feedback == "readings"
    assert isinstance(pid, RobotController)
    assert not pid.failed and not pid.overran and pid.plan is None and pid.late_plan is None
    assert (pid.inaccurate, pid.overruns) == (0, 0)


def test_protocol_members_lists_the_declared_members_with_the_bases():
    assert protocol_members(Controller) == ("settings", "step_status", "plan", "reports_failures",
                                            "accepts_preview", "step", "applied", "stats")
    assert set(protocol_members(RobotController)) < set(protocol_members(RobotEstimateController))
    assert {"step", "prime"} <= set(protocol_members(RobotEstimateController))


# --- a step's outcome ---------------------------------------------------------------------------------
def test_step_status_text_is_what_the_logs_carry():
    assert str(STEP_OK) == "ok" and STEP_OK.ok
    assert str(StepStatus(SolveStatus.FAILED, "qp infeasible")) == "failed: qp infeasible"
    assert str(StepStatus(SolveStatus.OVERRUN)) == "overrun"
    assert not StepStatus(SolveStatus.OVERRUN, "time limit").ok


def test_nmpc_reports_a_failed_step_as_a_typed_status(model):
    c = NMPC(ACT, PN, MPCSettings(variant="rti_osqp", codegen=False, fail_window=(0.0, 1.0)), model=model)
    e = Estimate(t=0.0, h1=2e-3, h2=0.0, h=2e-3, F=0.0, p=8e3)
    assert c.step(0.5, e, Reference(3e-3)) == SAFE_COMMAND
    assert c.step_status.kind is SolveStatus.FAILED and "injected failure" in c.step_status.detail
    assert c.last["status"] == str(c.step_status) and c.plan is None


# --- a role of one's own -------------------------------------------------------------------------------
def test_a_controller_that_only_writes_step_runs_in_the_chamber_loop():
    loop = ChamberLoop(Flat(), Pump(), chamber_supervisor(PIDSettings()), reference=3e-3)
    sent = [loop.tick(0.02 * k, p) for k, p in enumerate((0.0, 5e3, 12e3, 8e3))]
    assert [c.as_array().tolist() for c in sent] == [[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0],
                                                     [1.0, 1.0, 0.0]]
    st = loop.stats()
    assert st["steps"] == 4 and st["fallbacks"] == 0 and "fallback_detail" not in st


def test_a_controller_with_its_own_settings_gets_its_supervisor_from_them():
    class Limited(Pump):
        settings = PIDSettings(p_max=20e3, guard_margin=2e3)

    loop = ChamberLoop(Flat(), Limited(), reference=3e-3)
    assert loop.supervisor.settings.p_max == 20e3 and loop.supervisor.settings.fallback_plan_steps == 10
    assert loop.tick(0.0, 19e3).as_array().tolist() == [0.0, 0.0, 1.0]  # the guard vents near its p_max


@pytest.mark.parametrize("kind, cause", [(SolveStatus.FAILED, "solver_failed"), (SolveStatus.OVERRUN, "overrun")])
def test_a_step_status_not_ok_makes_the_supervisor_fall_back(kind, cause):
    class Failing(Pump):
        reports_failures = True

        def step(self, t, estimate, reference, preview=None):
            self.step_status = StepStatus(kind, "drill") if t > 0.01 else STEP_OK
            return super().step(t, estimate, reference)

    ctrl = Failing()
    loop = ChamberLoop(Flat(), ctrl, chamber_supervisor(PIDSettings()), reference=3e-3)
    for k in range(3):
        loop.tick(0.02 * k, 5e3)
    st = loop.stats()
    assert st["fallbacks"] == 2 and st["fallback_detail"][cause] == 2
    assert loop.command == SAFE_COMMAND  # no plan to replay


def test_a_readings_controller_of_ones_own_runs_in_the_robot_loop(robot):
    d, model = robot

    class Hold(RobotControllerBase):
        feedback = "readings"

        def step(self, p_meas, W, h_ref):
            return np.full(3, 0.2), np.zeros(3)

    loop = RobotLoop(d, model, _bank(model), Hold(), robot_supervisor(45e3, 3), {0: ((0.0, U.mm(4.0), 0.0, 0.0),)})
    for k in range(3):
        a, o = loop.tick(0.01 * k, np.zeros(3))
    assert np.allclose(a, 0.2) and np.all(o == 0.0)
    st = loop.stats()
    assert st["fallbacks"] == 0 and st["qp_not_solved"] == 0 and st["overruns"] == 0


# --- a role that lacks a member is refused, the member named -------------------------------------------
def test_a_duck_typed_controller_is_refused_naming_what_it_lacks():
    class OnlyStep:
        settings = PIDSettings()

        def step(self, t, estimate, reference):
            return SAFE_COMMAND

    with pytest.raises(TypeError, match=r"ChamberLoop: controller: OnlyStep lacks step_status, plan, "
                                        r"reports_failures, accepts_preview, applied, stats .*ControllerBase"):
        ChamberLoop(Flat(), OnlyStep())


def test_an_estimator_without_its_diagnostics_is_refused():
    class Bare:
        def step(self, t, measurement, applied_command):
            return Estimate(t=t, h1=0.0, h2=0.0, h=0.0, F=0.0, p=0.0)

    with pytest.raises(TypeError, match=r"ChamberLoop: estimator: Bare lacks settings, state_names, .*attach"):
        ChamberLoop(Bare(), Pump(), chamber_supervisor(PIDSettings()))
    ChamberLoop(None, Pump(), chamber_supervisor(PIDSettings()))  # none: the caller hands control() the estimate


def test_a_controller_without_settings_needs_a_supervisor_and_no_preview_unless_it_accepts_one():
    with pytest.raises(ValueError, match=r"Pump.settings is None: pass the supervisor"):
        ChamberLoop(Flat(), Pump())
    with pytest.raises(ValueError, match=r"preview_steps = 5 .*Pump.accepts_preview is False"):
        ChamberLoop(Flat(), Pump(), chamber_supervisor(PIDSettings()), preview_steps=5, preview_period=0.02)


def test_settings_without_the_supervisors_members_are_refused():
    class Partial:
        p_max, guard_margin = 35e3, 1e3

    with pytest.raises(TypeError, match=r"chamber_supervisor: controller settings: Partial lacks "
                                        r"fallback_plan_steps, h_min, h_max .*ControllerSettingsDefaults"):
        chamber_supervisor(Partial())


def test_a_robot_controller_without_feedback_or_with_an_unknown_one_is_refused(robot):
    d, model = robot
    targets = {0: ((0.0, U.mm(4.0), 0.0, 0.0),)}

    class NoFeedback(RobotControllerBase):
        def step(self, p_meas, W, h_ref):
            return np.zeros(3), np.zeros(3)

    with pytest.raises(TypeError, match=r"RobotLoop: controller: NoFeedback lacks feedback of "):
        RobotLoop(d, model, _bank(model), NoFeedback(), robot_supervisor(45e3, 3), targets)

    class Sideways(NoFeedback):
        feedback = "sideways"

    with pytest.raises(ValueError, match=r"controller.feedback = 'sideways': allowed 'estimate', 'readings'"):
        RobotLoop(d, model, _bank(model), Sideways(), robot_supervisor(45e3, 3), targets)

    class NoStep(RobotControllerBase):
        feedback = "readings"

    with pytest.raises(TypeError, match=r"NoStep lacks step of .*RobotReadingsController$"):
        RobotLoop(d, model, _bank(model), NoStep(), robot_supervisor(45e3, 3), targets)


def test_check_role_passes_a_role_that_satisfies_its_protocol():
    check_role(Pump(), Controller, "caller")
    check_role(Flat(), Estimator, "caller")
    check_role(PIDSettings(), ControllerSettings, "caller")
    check_role(MPCSettings(), ControllerSettings, "caller")
