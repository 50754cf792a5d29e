"""The [rig] table: the simulated rig's mismatch and sensor, in the user's units (kPa, ms).

The keys are :class:`~hbma_ctrl.sim.rig.RigSettings`' declarations in the user's units. The same
table also sets up the robot's rig (:meth:`RigTable.to_robot_rig`).
"""

from __future__ import annotations

from pydantic import model_validator

from hbma_ctrl.app.schema.fields import RuleError, settings_table
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["RigTable"]

#: the RigSettings a robot's rig takes (:meth:`RigTable.to_robot_rig`)
_ROBOT_RIG = ("fidelity", "modulus_scale", "flow_scale", "V0_scale", "noise_std", "sample_period", "seed",
              "valve_delay", "valve_min_on", "compressor_tilt", "sensor_tau")

_KEYS = settings_table("RigKeys", (RigSettings, ("fidelity", "membrane", "modulus_scale", "flow_scale", "V0_scale",
                                                 "C_out_scale",
                                                 "noise_std", "sensor_range", "sample_period", "dropout_prob", "seed",
                                                 "integrator", "dt", "valve_delay", "valve_min_on", "compressor_tilt",
                                                 "sensor_tau")))
#: their [rig] keys
ROBOT_RIG_KEYS = tuple(k for k, (_, name, _) in _KEYS.settings_keys.items() if name in _ROBOT_RIG)


class RigTable(_KEYS):
    """[rig] in the user's units; :meth:`to_settings` gives the SI RigSettings."""

    @model_validator(mode="after")
    def _dt(self) -> RigTable:
        if self.dt_ms is not None and self.dt_ms > self.sample_period_ms:
            lo = type(self).settings_keys["dt_ms"][2].user_bounds()[0]
            raise RuleError(f"dt_ms = {self.dt_ms!r} is out of range ({lo:g}, {self.sample_period_ms:g}] ms "
                            "(at most sample_period_ms)")
        return self

    def to_settings(self) -> RigSettings:
        """SI rig settings (Pa, s); keys not written keep RigSettings' defaults."""
        try:
            return RigSettings(**self.si(RigSettings)).validate()
        except ValueError as exc:  # a bound the table could not state (kept as a last guard)
            raise ValueError(f"[rig] {exc}") from None

    def not_for_a_robot(self) -> str | None:
        """The first key written that a robot's rig does not take, as an error text naming it and the
        keys it takes; None when there is none."""
        extra = [k for k in type(self).model_fields if k in self.model_fields_set and k not in ROBOT_RIG_KEYS]
        if not extra:
            return None
        return (f"{extra[0]}: a robot's rig does not take it (its chambers are the cap, with the sensors' range "
                f"of [robot]); a robot's [rig] takes {', '.join(ROBOT_RIG_KEYS)}")

    def to_robot_rig(self) -> RobotRigSettings:
        """The robot's rig: modulus_scale m becomes the spread |m - 1|, the rest as written; the
        structural mismatches (valve timing, pump tilt, sensor lag) not written keep
        :class:`RobotRigSettings`' defaults, a chamber rig's values. A key the robot's rig does not have
        (its chambers are the cap: no membrane law, range or dropouts of its own) is refused, not ignored."""
        if not self.model_fields_set:
            return RobotRigSettings()
        why = self.not_for_a_robot()
        if why:  # a scenario file is refused at load (ScenarioFile); this guards a table built alone
            raise ValueError(f"[rig] {why}")
        r = self.to_settings()
        # the structural mismatches where written; the others keep the robot rig's defaults
        si = self.si(RigSettings)
        kw = {k: si[k] for k in ("valve_delay", "valve_min_on", "compressor_tilt", "sensor_tau") if k in si}
        kw.update(fidelity=r.fidelity, modulus_spread=abs(r.modulus_scale - 1.0), flow_scale=r.flow_scale,
                  V0_scale=r.V0_scale, noise_std=r.noise_std, sample_period=r.sample_period, seed=r.seed)
        try:
            return RobotRigSettings(**kw).validate()
        except ValueError as exc:
            raise ValueError(f"[rig] {exc} (the robot's rig)") from None
