"""The robot rig: the mismatched, higher-fidelity truth every robot estimator and controller is judged against (SI).

the "truth": every chamber of the robot is the ``platform`` fidelity
  (the chamber's share of the layers as a moving mass with damping; ``quasi_static``, a dead load,
  as a setting) (gas mass, resting / lift-off / far branch handled by
  :class:`hbma_ctrl.sim.simulate.Plant`), all chambers in ONE batch, with mismatched parameters
  (:func:`hbma_ctrl.sim.rig.mismatched`: pump flow x0.9, dead volume x1.2; the modulus is +15 % and -15 %
  on alternate chambers, so both signs of the error are present). Every sample (10 ms) each
  chamber's load W is its share of the weight and of the tip load from
  :func:`hbma_ctrl.robot.statics.load_sharing` of the TRUE heights. The sensors: 0.2 kPa noise, saturation
  at the robot's sensor range (50 kPa). Shared compressor: the pump's flow is split among the open
  inlets by their duties; if the duties sum to more than 1 each chamber gets its duty / sum (the
  manifold model the NMPC's coupling row respects).

The single chamber's structural mismatches (:class:`hbma_ctrl.sim.rig.RigSettings`), on by default
with its values (``hbma_ctrl.sim.rig.STRUCTURED_RIG``: 5 ms, 2 ms, 0.2, 3 ms): ``valve_delay`` and
``valve_min_on`` (every chamber's valves, :class:`hbma_ctrl.sim.rig.ValveLine`: the plant then advances
in its internal steps with the valves as they act at each), ``compressor_tilt`` (every chamber's pump
map, or the shared one's, tilted with back pressure) and ``sensor_tau`` (each sensor's first-order
lag). ``RobotRigSettings(**IDEAL_STRUCTURE)`` is the rig without them, for the loop with instant
valves and sensor (``hbma_ctrl.models.defaults.ROBOT_INSTANT``). The membrane stays the cap: the
robot's chambers run to about 4 r1 on their far branch, past the exact tables' reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.params import Platform, Pneumatics
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.models.fidelity import make_fidelity
from hbma_ctrl.robot.design import RobotDesign, shared_supply
from hbma_ctrl.robot.plant import W_FLOOR
from hbma_ctrl.robot.statics import load_sharing
from hbma_ctrl.sim.rig import CAP_RIG, STRUCTURED_RIG, RigSettings, ValveLine, mismatched
from hbma_ctrl.sim.simulate import Plant

H_TARGET_MAX = 13e-3  # m: the per-chamber tables reach 14 mm
M_MIN = 5e-3  # kg: smallest moving mass a platform-fidelity rig chamber carries


@dataclass(frozen=True)
class RobotRigSettings(Settings):
    """Mismatch, dynamics and sensors of the robot rig (SI; each field's unit, range and one-line doc
    are in its declaration). fidelity 'platform' is the higher-fidelity truth, 'quasi_static' what the
    controller assumes. valve_delay, valve_min_on, compressor_tilt, sensor_tau: the structural
    mismatches of :class:`hbma_ctrl.sim.rig.RigSettings`, with its bounds and defaults (module docstring)."""

    WHERE = "robot rig"

    fidelity: str = setting("platform", choices=("platform", "quasi_static"),
                            doc="each chamber carries its share of the layers as a moving mass, or a dead load")
    damping: float = setting(0.5, lo=0.0, hi=1e3, unit="N s/m", doc="the moving masses' damping")
    modulus_spread: float = setting(0.15, lo=0.0, hi=0.8, doc="chambers alternate modulus x(1 + spread), x(1 - spread)")
    flow_scale: float = setting(0.9, lo=0.1, hi=5.0, doc="compressor map times this")
    V0_scale: float = setting(1.2, lo=0.2, hi=5.0, doc="dead volume times this")
    noise_std: float = setting(200.0, lo=0.0, hi=1e4, unit="Pa", doc="sensor noise, one sigma")
    sample_period: float = setting(0.01, lo=1e-3, hi=1.0, unit="s", doc="sensor and command period")
    seed: int = setting(0, integer=True, lo=0, doc="seed of the noise stream")
    dt: float | None = setting(None, lo=1e-5, hi=1.0, unit="s", doc="internal rk4 step (at most sample_period)")
    valve_delay: float = STRUCTURED_RIG["valve_delay"]
    valve_min_on: float = STRUCTURED_RIG["valve_min_on"]
    compressor_tilt: float = STRUCTURED_RIG["compressor_tilt"]
    sensor_tau: float = STRUCTURED_RIG["sensor_tau"]

    def check_rules(self) -> None:
        if self.dt is not None:
            self.within("dt", hi=self.sample_period)
        try:
            # the structural mismatches are the chamber rig's: its ranges are the ones that apply (one
            # place to change them), reported under this section's name
            self.chamber_rig()
        except ValueError as e:
            raise ValueError(f"robot {e}") from None

    def chamber_rig(self, modulus_scale: float = 1.0) -> RigSettings:
        """One chamber's :class:`RigSettings` (the cap, these mismatches and structure)."""
        return RigSettings(fidelity=self.fidelity, modulus_scale=modulus_scale, flow_scale=self.flow_scale,
                           V0_scale=self.V0_scale, noise_std=self.noise_std, sample_period=self.sample_period,
                           **{**CAP_RIG, "valve_delay": self.valve_delay, "valve_min_on": self.valve_min_on,
                              "compressor_tilt": self.compressor_tilt, "sensor_tau": self.sensor_tau}).validate()


class RobotRig:
    """All chambers of the robot as one mismatched batch plant with pressure sensors (module doc)."""

    def __init__(self, design: RobotDesign, pneumatics: Pneumatics, sensor_range: float, topology: str,
                 settings: RobotRigSettings | None = None, tip_load=()):
        self.s = (settings or RobotRigSettings()).validate()
        self.design = design
        self.n = 3 * design.n_layers
        self.topology = topology
        self.sensor_range = sensor_range
        self.tip_load = tuple(tip_load)
        thetas = []
        fid = None
        self.modulus_scales = 1.0 + self.s.modulus_spread * np.where(np.arange(self.n) % 2 == 0, 1.0, -1.0)
        for scale in self.modulus_scales:
            # the robot's chambers are the cap (module docstring), whatever the single-chamber rig's defaults
            act, pn = mismatched(design.chamber, pneumatics, self.s.chamber_rig(scale))
            if fid is None:
                fid = make_fidelity(self.s.fidelity, act.material, str(pn.csv_path))
            thetas.append(fid.space.values(act, pn, Platform(load=1e-3, damping=self.s.damping)))
        dt = self.s.dt if self.s.dt is not None else (1e-3 if self.s.fidelity == "platform" else 5e-3)
        self.plant = Plant(fid, np.column_stack(thetas), "rk4", dt)
        self._rng = np.random.default_rng(self.s.seed)
        self.design_g = 9.80665
        self._timing = self.s.chamber_rig()  # the valve line and sensor lag (the same for every chamber)
        self._valves = ValveLine(self._timing, self.n)
        self._p_sensed = self._p_prev = self.plant.output("p").copy()  # lagged sensor state, true p, Pa
        self._update_loads()

    @property
    def t(self) -> float:
        return self.plant.t

    def tip_force(self, t: float) -> np.ndarray:
        """Tip force (N, world) at time t from the (t, fx, fy, fz) rows (held from each row's time)."""
        f = np.zeros(3)
        for row in self.tip_load:
            if t + 1e-9 >= row[0]:
                f = np.asarray(row[1:4], dtype=float)
        return f

    def _update_loads(self) -> None:
        h = np.maximum(self.plant.output("h"), 0.0)
        F = load_sharing(self.design, h.reshape(-1, 3), self.tip_force(self.plant.t)).forces.ravel()
        W = np.maximum(F, W_FLOOR)
        self.plant.set_param("W", W)
        if self.plant.fid.name == "platform":
            # the moving mass each chamber carries: its share of the layers' weight (and tip load),
            # at least M_MIN so a nearly unloaded chamber stays a slow enough oscillator for RK4
            self.plant.set_param("M", np.maximum(W / self.design_g, M_MIN))
        self.loads = F

    def apply(self, Ucmd: np.ndarray) -> None:
        """Hold the inputs (3 x n) for one sample period, then update the loads from the true heights."""
        self._valves.send(self.plant.t, Ucmd)
        self._valves.drive(self.plant, self.plant.t, self._manifold)
        p_now = self.plant.output("p").copy()
        self._p_sensed = self._timing.sense(self._p_sensed, self._p_prev, p_now)
        self._p_prev = p_now
        self._update_loads()

    def _manifold(self, U: np.ndarray) -> np.ndarray:
        """The inlets' duties as the shared pump's flow splits among them (duty / sum when above 1)."""
        if self.topology == "shared":
            U = np.vstack([U[0], shared_supply(U[1]), U[2]])
        return U

    def measure(self) -> np.ndarray:
        """Pressure readings (n,), Pa: truth (through the sensor's lag) + noise, saturated at the sensor range."""
        # without a lag the plant's pressure now (a state set between periods reads at once)
        p_true = self._p_sensed if self.s.sensor_tau > 0 else self.plant.output("p")
        p = p_true + self.s.noise_std * self._rng.standard_normal(self.n)
        return np.minimum(p, self.sensor_range)

    def truth(self) -> dict:
        return {k: self.plant.output(k).copy() for k in ("h", "p", "lam", "m")}
