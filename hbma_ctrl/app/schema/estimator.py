"""The [estimator] table: which filter, the Monte-Carlo setup, load steps and the filter tuning.

Bounds are those of ``FilterSettings.validate``, in the
user's units. Only the tuning keys the user writes override the filter's defaults (the sample
period, sensor range and noise otherwise come from the rig).
"""

from __future__ import annotations

from typing import Literal

from hbma_ctrl.estimators.common import FACTOR_RANGE, FilterSettings
from hbma_ctrl.app.schema.fields import (
    LOAD_STEPS_SHAPE,
    LoadSteps,
    Table,
    as_is,
    choice,
    flag,
    integer,
    load_steps_si,
    num,
    shaped,
)
from hbma_ctrl.system.sections import EstimatorSection, filter_settings_for
from hbma_ctrl.core import units as U
from hbma_ctrl.models.actuation import DELAY_MAX
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE, DEFAULT_SENSOR_DELAY, DEFAULT_VALVE_DELAY
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["EstimatorTable"]


class EstimatorTable(Table):
    """[estimator] in the user's units; :meth:`to_section` gives the SI EstimatorSection."""

    filter: Literal["ekf", "ukf"] = choice("ekf", "the filter")
    compare_ukf: bool = flag(False, "also run the UKF on the same rig runs")
    load_steps_g: LoadSteps = shaped(None, "rig load from t_s on (kind 'single')", LOAD_STEPS_SHAPE,
                                     default_factory=list)
    workers: int = integer(2, 1, 64, "worker processes for a protocol", "processes")
    seeds: int = integer(1, 1, 100, "Monte-Carlo repetitions with different noise seeds", "runs")
    noise_std_kpa: float | None = num(None, 0.0, 10.0, "kPa", "filter's sensor sigma; default: the rig's",
                                      lo_open=True)
    model_rel_std: float = num(0.05, 0.0, 1.0, "-", "relative error of the model's pressure law")
    flow_rel_std: float = num(0.15, 0.0, 1.0, "-", "relative error of the model's mass flow")
    flow_factor_std: float = num(0.02, 0.0, 10.0, "1/sqrt(s)", "random walk of the pump-flow factor")
    modulus_std: float = num(0.002, 0.0, 10.0, "1/sqrt(s)", "random walk of the modulus factor")
    flow_factor_init: float = num(FilterSettings.flow_factor_init, *FACTOR_RANGE, "-", "the pump-flow factor's start (a fit's flow_scale)")
    flow_factor_init_std: float = num(FilterSettings.flow_factor_init_std, 0.0, 10.0, "-", "its one sigma")
    modulus_init: float = num(FilterSettings.modulus_init, *FACTOR_RANGE, "-", "the modulus factor's start (a fit's modulus_scale)")
    modulus_init_std: float = num(FilterSettings.modulus_init_std, 0.0, 10.0, "-", "its one sigma")
    dead_volume_init: float = num(FilterSettings.dead_volume_init, *FACTOR_RANGE, "-",
                                  "the dead-volume factor's start (a fit's V0 over [actuator] V0_cm3)")
    dead_volume_init_std: float = num(FilterSettings.dead_volume_init_std, 0.0, 10.0, "-", "its one sigma")
    change_threshold: float = num(20.0, 0.0, 1e6, "-", "CUSUM threshold of a load change", lo_open=True)
    load_std_n: float = num(0.05, 0.0, 100.0, "N/sqrt(s)", "load random walk")
    integrator: Literal["rk4", "euler"] = choice("rk4", "the filter model's scheme")
    nsub: int = integer(1, 1, 50, "integrator sub-steps per sample", "steps")
    newton: int = integer(3, 1, 10, "Newton iterations of the shape projection", "iterations")
    compile: bool = flag(True, "compile the filter model to C")
    load_prior: Literal["unknown", "nominal"] = choice("unknown", "learn the load or start at the nominal")
    load_prior_rel_std: float = num(0.1, 0.0, 10.0, "-", "relative sigma of the nominal load prior")
    membrane: Literal["cap", "exact"] = choice(DEFAULT_MEMBRANE,
                                               "the filter model's membrane law (README Model §9)")
    valve_delay_ms: float = num(U.to_ms(DEFAULT_VALVE_DELAY), 0.0, U.to_ms(DELAY_MAX), "ms",
                                "the valves act this long after their command (datasheet)")
    sensor_delay_ms: float = num(U.to_ms(DEFAULT_SENSOR_DELAY), 0.0, U.to_ms(DELAY_MAX), "ms",
                                 "the pressure sensor reads this long late")

    def to_section(self) -> EstimatorSection:
        """The SI section; the tuning is checked against a default rig here, before any run."""
        tuning = {name: conv(getattr(self, key)) for key, (name, conv) in _TUNING.items()
                  if key in self.model_fields_set and getattr(self, key) is not None}
        sec = EstimatorSection(filter=self.filter, compare_ukf=self.compare_ukf,
                               load_steps=load_steps_si(self.load_steps_g), workers=self.workers,
                               seeds=self.seeds, tuning=tuning)
        try:
            filter_settings_for(sec, RigSettings())
        except ValueError as exc:  # a bound the table could not state (kept as a last guard)
            raise ValueError(f"[estimator] {exc}") from None
        return sec


#: table key -> (FilterSettings field, conversion from the user's unit)
_TUNING = {
    "noise_std_kpa": ("noise_std", U.kpa),
    "model_rel_std": ("model_rel_std", float),
    "flow_rel_std": ("flow_rel_std", float),
    "flow_factor_std": ("flow_factor_std", float),
    "modulus_std": ("modulus_std", float),
    "flow_factor_init": ("flow_factor_init", float),
    "flow_factor_init_std": ("flow_factor_init_std", float),
    "modulus_init": ("modulus_init", float),
    "modulus_init_std": ("modulus_init_std", float),
    "dead_volume_init": ("dead_volume_init", float),
    "dead_volume_init_std": ("dead_volume_init_std", float),
    "change_threshold": ("change_threshold", float),
    "load_std_n": ("load_std", float),
    "integrator": ("integrator", as_is),
    "nsub": ("nsub", as_is),
    "newton": ("newton", as_is),
    "compile": ("compile", as_is),
    "load_prior": ("load_prior", as_is),
    "load_prior_rel_std": ("load_prior_rel_std", float),
    "membrane": ("membrane", as_is),
    "valve_delay_ms": ("valve_delay", U.ms),
    "sensor_delay_ms": ("sensor_delay", U.ms),
}
