"""The [rig] table: the simulated rig's mismatch and sensor, in the user's units (kPa, ms).

Bounds are those of ``RigSettings.validate``. The same table also sets up the robot's rig
(:meth:`RigTable.to_robot_rig`).
"""

from __future__ import annotations

from typing import Literal

from pydantic import model_validator

from hbma_ctrl.app.schema.fields import RuleError, Table, as_is, choice, integer, num
from hbma_ctrl.core import units as U
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["RigTable"]


class RigTable(Table):
    """[rig] in the user's units; :meth:`to_settings` gives the SI RigSettings."""

    fidelity: Literal["platform", "quasi_static"] = choice("platform", "plant model while a load is on")
    membrane: Literal["exact", "cap"] = choice(RigSettings.membrane, "membrane law, free and on the plate: "
                                                "exact (exact membrane tables) or cap (spherical cap)")
    modulus_scale: float = num(1.15, 0.2, 5.0, "-", "every modulus of the material times this")
    flow_scale: float = num(0.9, 0.0, 5.0, "-", "compressor map times this")
    V0_scale: float = num(1.2, 0.2, 5.0, "-", "dead volume times this")
    noise_std_kpa: float = num(0.2, 0.0, 10.0, "kPa", "sensor noise, one sigma")
    sensor_range_kpa: float = num(35.0, 1.0, 1000.0, "kPa", "sensor saturation pressure")
    sample_period_ms: float = num(10.0, 0.0, 1000.0, "ms", "sensor and command period", lo_open=True)
    dropout_prob: float = num(0.0, 0.0, 1.0, "-", "probability that a sample is missing")
    seed: int = integer(0, 0, None, "seed of the noise and dropout stream")
    integrator: Literal["rk4", "euler"] = choice("rk4", "fixed-step scheme")
    dt_ms: float | None = num(None, 1e-4, 1000.0, "ms", "internal step, at most sample_period_ms; "
                              "default per fidelity", lo_open=True)

    valve_delay_ms: float = num(U.to_ms(RigSettings.valve_delay), 0.0, 100.0, "ms",
                                "the valves act this long after their command (a small solenoid)")
    valve_min_on_ms: float = num(U.to_ms(RigSettings.valve_min_on), 0.0, 100.0, "ms",
                                 "shortest valve opening per PWM (sample) period (a small solenoid)")
    compressor_tilt: float = num(RigSettings.compressor_tilt, -1.0, 1.0, "-", "pump flow times "
                                 "1 - k (p / p_top - 1/2): another shape (0 = the map's own)")
    sensor_tau_ms: float = num(U.to_ms(RigSettings.sensor_tau), 0.0, 1000.0, "ms",
                               "first-order lag of the pressure sensor (0 = none)")

    @model_validator(mode="after")
    def _dt(self) -> RigTable:
        if self.dt_ms is not None and self.dt_ms > self.sample_period_ms:
            raise RuleError(f"dt_ms = {self.dt_ms!r} is out of range (0.0001, {self.sample_period_ms:g}] ms "
                            "(at most sample_period_ms)")
        return self

    def _si(self) -> dict:
        return {name: conv(getattr(self, key)) for key, (name, conv) in _SI.items()
                if key in self.model_fields_set and getattr(self, key) is not None}

    def to_settings(self) -> RigSettings:
        """SI rig settings (Pa, s); keys not written keep RigSettings' defaults."""
        try:
            return RigSettings(**self._si()).validate()
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
        si = self._si()
        kw = {k: si[k] for k in ("valve_delay", "valve_min_on", "compressor_tilt", "sensor_tau") if k in si}
        kw.update(fidelity=r.fidelity, modulus_spread=abs(r.modulus_scale - 1.0), flow_scale=r.flow_scale,
                  V0_scale=r.V0_scale, noise_std=r.noise_std, sample_period=r.sample_period, seed=r.seed)
        try:
            return RobotRigSettings(**kw).validate()
        except ValueError as exc:
            raise ValueError(f"[rig] {exc} (the robot's rig)") from None


#: the [rig] keys a robot's rig takes (:meth:`RigTable.to_robot_rig`)
ROBOT_RIG_KEYS = ("fidelity", "modulus_scale", "flow_scale", "V0_scale", "noise_std_kpa", "sample_period_ms", "seed",
                  "valve_delay_ms", "valve_min_on_ms", "compressor_tilt", "sensor_tau_ms")

#: table key -> (RigSettings field, conversion from the user's unit)
_SI = {
    "fidelity": ("fidelity", as_is),
    "membrane": ("membrane", as_is),
    "modulus_scale": ("modulus_scale", float),
    "flow_scale": ("flow_scale", float),
    "V0_scale": ("V0_scale", float),
    "noise_std_kpa": ("noise_std", U.kpa),
    "sensor_range_kpa": ("sensor_range", U.kpa),
    "sample_period_ms": ("sample_period", U.ms),
    "dropout_prob": ("dropout_prob", float),
    "seed": ("seed", as_is),
    "integrator": ("integrator", as_is),
    "dt_ms": ("dt", U.ms),
    "valve_delay_ms": ("valve_delay", U.ms),
    "valve_min_on_ms": ("valve_min_on", U.ms),
    "compressor_tilt": ("compressor_tilt", float),
    "sensor_tau_ms": ("sensor_tau", U.ms),
}
