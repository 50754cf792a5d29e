"""The [estimator] table: which filter, the Monte-Carlo setup, load steps and the filter tuning.

The tuning keys are :class:`~hbma_ctrl.estimators.common.FilterSettings`' own declarations in the
user's units. Only the tuning keys the user writes override the filter's defaults (the sample
period, sensor range and noise otherwise come from the rig).
"""

from __future__ import annotations

from typing import Literal

from pydantic import model_validator

from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.mhe import MHESettings
from hbma_ctrl.app.schema.fields import (
    LOAD_STEPS_SHAPE,
    LoadSteps,
    RuleError,
    choice,
    flag,
    integer,
    load_steps_si,
    settings_table,
    shaped,
)
from hbma_ctrl.system.sections import EstimatorSection, filter_settings_for
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["EstimatorTable", "MHE_KEYS"]

#: the moving-horizon estimator's own keys (read only with kind = "mhe")
MHE_KEYS = ("horizon", "solver", "qp_solver", "relinearise", "huber", "companion_ekf", "reseed_cost", "ipopt_iter")

_KEYS = settings_table(
    "EstimatorTuning",
    (FilterSettings, ("noise_std", "model_rel_std", "flow_rel_std", "flow_factor_std", "modulus_std",
                      "flow_factor_init", "flow_factor_init_std", "modulus_init", "modulus_init_std",
                      "dead_volume_init", "dead_volume_init_std", "change_threshold", "load_std", "integrator",
                      "nsub", "newton", "compile", "load_prior", "load_prior_rel_std", "membrane", "valve_delay",
                      "sensor_delay")),
    (MHESettings, MHE_KEYS),
    defaults={"noise_std": None})  # the rig's


class EstimatorTable(_KEYS):
    """[estimator] in the user's units; :meth:`to_section` gives the SI EstimatorSection."""

    filter: Literal["ekf", "ukf", "mhe"] = choice("ekf", "the estimator (the same as kind)")
    kind: Literal["ekf", "ukf", "mhe"] | None = choice(None, "the estimator: ekf, ukf or mhe (moving horizon); "
                                                             "default: filter's")
    compare_ukf: bool = flag(False, "also run the UKF on the same rig runs")
    load_steps_g: LoadSteps = shaped(None, "rig load from t_s on (kind 'single')", LOAD_STEPS_SHAPE,
                                     default_factory=list)
    workers: int = integer(2, 1, 64, "worker processes for a protocol", "processes")
    seeds: int = integer(1, 1, 100, "Monte-Carlo repetitions with different noise seeds", "runs")

    @model_validator(mode="after")
    def _kind(self) -> EstimatorTable:
        given = self.model_fields_set
        if "kind" in given and "filter" in given and self.kind != self.filter:
            raise RuleError(f"kind = {self.kind!r} and filter = {self.filter!r} name the estimator twice: "
                            "write kind only")
        which = self.kind or self.filter
        if which != "mhe":
            mhe = [key for key, (cls, _, _) in self.settings_keys.items() if cls is MHESettings and key in given]
            if mhe:
                raise RuleError(f"{mhe[0]} is a key of the moving-horizon estimator: it needs kind = \"mhe\" "
                                f"(kind is {which!r})")
        return self

    def to_section(self) -> EstimatorSection:
        """The SI section; the tuning is checked against a default rig here, before any run."""
        tuning = self.si(FilterSettings)
        tuning.update(self.si(MHESettings))
        sec = EstimatorSection(filter=self.kind or self.filter, compare_ukf=self.compare_ukf,
                               load_steps=load_steps_si(self.load_steps_g), workers=self.workers,
                               seeds=self.seeds, tuning=tuning)
        filter_settings_for(sec, RigSettings())
        return sec
