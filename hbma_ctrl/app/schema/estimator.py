"""The [estimator] table: which filter, the Monte-Carlo setup, load steps and the filter tuning.

The tuning keys are :class:`~hbma_ctrl.estimators.common.FilterSettings`' own declarations in the
user's units. Only the tuning keys the user writes override the filter's defaults (the sample
period, sensor range and noise otherwise come from the rig).
"""

from __future__ import annotations

from typing import Literal

from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.app.schema.fields import (
    LOAD_STEPS_SHAPE,
    LoadSteps,
    choice,
    flag,
    integer,
    load_steps_si,
    settings_table,
    shaped,
)
from hbma_ctrl.system.sections import EstimatorSection, filter_settings_for
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["EstimatorTable"]

_KEYS = settings_table(
    "EstimatorTuning",
    (FilterSettings, ("noise_std", "model_rel_std", "flow_rel_std", "flow_factor_std", "modulus_std",
                      "flow_factor_init", "flow_factor_init_std", "modulus_init", "modulus_init_std",
                      "dead_volume_init", "dead_volume_init_std", "change_threshold", "load_std", "integrator",
                      "nsub", "newton", "compile", "load_prior", "load_prior_rel_std", "membrane", "valve_delay",
                      "sensor_delay")),
    defaults={"noise_std": None})  # the rig's


class EstimatorTable(_KEYS):
    """[estimator] in the user's units; :meth:`to_section` gives the SI EstimatorSection."""

    filter: Literal["ekf", "ukf"] = choice("ekf", "the filter")
    compare_ukf: bool = flag(False, "also run the UKF on the same rig runs")
    load_steps_g: LoadSteps = shaped(None, "rig load from t_s on (kind 'single')", LOAD_STEPS_SHAPE,
                                     default_factory=list)
    workers: int = integer(2, 1, 64, "worker processes for a protocol", "processes")
    seeds: int = integer(1, 1, 100, "Monte-Carlo repetitions with different noise seeds", "runs")

    def to_section(self) -> EstimatorSection:
        """The SI section; the tuning is checked against a default rig here, before any run."""
        sec = EstimatorSection(filter=self.filter, compare_ukf=self.compare_ukf,
                               load_steps=load_steps_si(self.load_steps_g), workers=self.workers,
                               seeds=self.seeds, tuning=self.si(FilterSettings))
        filter_settings_for(sec, RigSettings())
        return sec
