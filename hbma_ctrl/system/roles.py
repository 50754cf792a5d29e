"""Role assembly: the estimator, controller, valve shaping, start-up calibration and robot model a
scenario's sections ask for (SI). The scenes, the daemon, code generation and tuning all build their
roles here, so each of them runs the same objects.
"""

from __future__ import annotations

from hbma_ctrl.controllers.baselines import BangBangController, PIDController
from hbma_ctrl.controllers.lqi import LQIController
from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Estimator
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.estimators.mhe import MHE
from hbma_ctrl.estimators.ukf import UKF
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.runtime.calibrate import CalibrationSettings, StartupCalibration
from hbma_ctrl.runtime.pwm import MinOnTime
from hbma_ctrl.sim.rig import RigSettings
from hbma_ctrl.system.sections import ControllerSection, check_min_on, filter_settings_for

__all__ = ["make_controller", "default_estimator", "estimator_from_scenario", "make_pwm", "make_calibration",
           "calibration_summary", "controller_settings_of", "make_model"]


def make_controller(section: ControllerSection, actuator: Actuator, pneumatics: Pneumatics,
                    model: PredictionModel | None = None):
    """The controller the section asks for (NMPC, PIDController, BangBangController or LQIController)."""
    if section.kind == "mpc":
        return NMPC(actuator, pneumatics, section.mpc, model=model)
    if section.kind == "pid":
        return PIDController(actuator, pneumatics, section.pid)
    if section.kind == "lqi":
        return LQIController(actuator, pneumatics, section.lqi, model=model)
    return BangBangController(actuator, pneumatics, section.bang_bang, model=model)


def default_estimator(actuator: Actuator, pneumatics: Pneumatics, rig_settings: RigSettings) -> EKF:
    """The chamber EKF on the nominal actuator with the rig's sample period, sensor range and noise (the
    scene's and the daemon's default filter)."""
    return EKF(actuator, pneumatics, EKFSettings(sample_period=rig_settings.sample_period,
                                                 noise_std=max(rig_settings.noise_std, 1.0),
                                                 sensor_range=rig_settings.sensor_range))


def make_pwm(section: ControllerSection, period: float) -> MinOnTime | None:
    """The valves' minimum on-time shaping of a controller section for a PWM period (s), None when
    ``valve_min_on`` is 0. ValueError naming ``[controller] valve_min_on_ms`` when it is longer than
    the period."""
    if section.valve_min_on <= 0.0:
        return None
    check_min_on("controller", section.valve_min_on, period)
    return MinOnTime(period, section.valve_min_on)


def make_calibration(actuator: Actuator, pneumatics: Pneumatics, platform: Platform, section: ControllerSection,
                     rs: RigSettings, estimator: Estimator) -> StartupCalibration:
    """The start-up calibration of a controller section on a rig of settings ``rs`` (its pulse stops at
    min(17 kPa, p_max / 2)); the estimator (when it has ``state_names``) tracks it, and gets the factors
    as its prior when it has factor states. With :class:`~hbma_ctrl.estimators.common.FilterSettings` (the
    filters), the fit takes the estimator's membrane law, valve and sensor delays and factor prior. The
    scenes and the daemon both build it here."""
    # a filter's fit models the chamber as the filter does: its membrane law, valve and sensor delays,
    # and starts from its prior on the factors (nominal, or a fit's values: [estimator] *_init)
    fs = estimator.settings
    timing = {}
    if isinstance(fs, FilterSettings):
        timing = {"valve_delay": fs.valve_delay, "sensor_delay": fs.sensor_delay, "membrane": fs.membrane,
                  "prior_mean": (fs.flow_factor_init, fs.modulus_init, fs.dead_volume_init),
                  "prior_std": (fs.flow_factor_init_std, fs.modulus_init_std, fs.dead_volume_init_std)}
    cs = CalibrationSettings(p_max=section.p_max, p_stop=min(CalibrationSettings.p_stop, 0.5 * section.p_max),
                             sample_period=rs.sample_period, noise_std=max(rs.noise_std, 1.0),
                             sensor_range=rs.sensor_range, handover_std_floor=section.calibration_std_floor,
                             **timing)
    # an estimator with a state layout runs over the excitation (and takes the factors if it has them)
    return StartupCalibration(actuator, pneumatics, cs, platform,
                              estimator=estimator if estimator.state_names else None)


def calibration_summary(cal: StartupCalibration, duration: float) -> dict:
    """The calibration's outcome in edge units: status, duration_s, peak_kpa, and when it fitted the
    factors flow_factor, modulus_factor, dead_volume_factor with their one-sigma *_std and the
    residual RMS (kPa)."""
    out: dict = {"status": cal.status, "duration_s": float(duration)}
    r = cal.result
    if r is not None:
        std = r.std
        out.update({"flow_factor": r.b, "modulus_factor": r.k, "dead_volume_factor": r.c,
                    "flow_factor_std": float(std[0]), "modulus_factor_std": float(std[1]),
                    "dead_volume_factor_std": float(std[2]), "residual_rms_kpa": U.to_kpa(r.residual_rms),
                    "peak_kpa": U.to_kpa(r.p_peak)})
    return out


def controller_settings_of(section: ControllerSection):
    """The chosen controller's settings (p_max, guard_margin, ...) for a controller whose ``settings`` is None."""
    return section.chosen


def estimator_from_scenario(scn, rig_settings):
    """The estimator the scenario's [estimator] section names (EKF, UKF or MHE, its tuning), or the EKF
    with the rig's sample period, sensor range and noise when there is no such section."""
    sec = scn.role("estimator")
    if sec is None:
        return None  # closed_loop builds the default EKF
    fs = filter_settings_for(sec, rig_settings)
    if sec.filter == "ukf":
        return UKF(scn.actuator, scn.pneumatics, fs)
    if sec.filter == "mhe":
        return MHE(scn.actuator, scn.pneumatics, fs)
    return EKF(scn.actuator, scn.pneumatics, fs)


def make_model(design: RobotDesign, pneumatics: Pneumatics, topology: str) -> ChamberBank:
    """The nominal per-chamber model (tables up to 14 mm and 2 N)."""
    return ChamberBank(design.chamber, pneumatics, topology, load_max=2.0, h_table_max=U.mm(14.0))
