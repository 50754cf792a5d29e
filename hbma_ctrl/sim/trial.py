"""Trials, their input schedules, simulator settings and the simulated log (SI).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hbma_ctrl.core.params import Actuator, Platform, Pneumatics, check_range
from hbma_ctrl.core.settings import Settings, setting

INTEGRATORS = ("euler", "rk4", "radau")
#: default step per integrator and fidelity, s (chosen by ``hbma-ctrl bench sim``)
#: the most fixed steps one run may take (about ten minutes on one core): a step small enough to need
#: more is a typo, not a finer answer (rk4 at the default steps is already converged)
MAX_STEPS = 10_000_000

DEFAULT_DT = {
    ("euler", "free"): 1e-3, ("rk4", "free"): 5e-3, ("radau", "free"): 5e-3,
    ("euler", "quasi_static"): 1e-3, ("rk4", "quasi_static"): 5e-3, ("radau", "quasi_static"): 5e-3,
    ("euler", "platform"): 1e-4, ("rk4", "platform"): 1e-3, ("radau", "platform"): 5e-3,
    # the exact rung of a loaded trial is the platform model (a free one steps at the free default)
    ("euler", "exact"): 1e-4, ("rk4", "exact"): 1e-3, ("radau", "exact"): 5e-3,
}


@dataclass(frozen=True)
class InputSchedule:
    """Piecewise-constant inputs: rows of (t_start s, speed 0-1, inlet duty 0-1, outlet duty 0-1).

    The first row must start at t = 0; rows are sorted by time.
    """

    rows: tuple = ((0.0, 0.0, 0.0, 0.0),)

    def validate(self, where: str = "schedule") -> "InputSchedule":
        if not self.rows or self.rows[0][0] != 0.0:
            raise ValueError(f"{where}: the first row must start at t = 0 s")
        last = -1.0
        for i, r in enumerate(self.rows):
            if len(r) != 4:
                raise ValueError(f"{where}[{i}]: need (t, speed, inlet, outlet), got {r}")
            check_range(f"{where}[{i}]", "t", r[0], 0.0, 1e6, "s")
            if r[0] <= last:
                raise ValueError(f"{where}[{i}].t = {r[0]} must be after the previous row's {last}")
            last = r[0]
            for name, v in zip(("speed", "inlet", "outlet"), r[1:]):
                check_range(f"{where}[{i}]", name, v, 0.0, 1.0)
        return self

    @property
    def times(self) -> np.ndarray:
        return np.array([r[0] for r in self.rows])

    def at(self, t: float) -> np.ndarray:
        """u(t) = [speed, inlet, outlet]."""
        i = int(np.searchsorted(self.times, t, side="right") - 1)
        return np.array(self.rows[max(i, 0)][1:], dtype=float)

    @staticmethod
    def inflate_deflate(speed: float, t_inflate: float) -> "InputSchedule":
        """The protocol's trial: pump at ``speed`` with the inlet open, then open the outlet."""
        return InputSchedule(((0.0, speed, 1.0, 0.0), (t_inflate, 0.0, 0.0, 1.0)))


@dataclass(frozen=True)
class Trial(Settings):
    """One open-loop scene: an actuator, its pneumatics and load, inputs and duration (SI)."""

    WHERE = "trial"

    actuator: Actuator = field(default_factory=Actuator)
    pneumatics: Pneumatics = field(default_factory=Pneumatics)
    platform: Platform = field(default_factory=Platform)
    schedule: InputSchedule = field(default_factory=lambda: InputSchedule.inflate_deflate(1.0, 3.0))
    duration: float = setting(6.0, lo=1e-3, hi=1e5, lo_open=True, unit="s", doc="scene length")
    name: str = setting("trial", text=True, doc="the trial's name in outputs")

    def check_rules(self) -> None:
        self.actuator.validate()
        self.pneumatics.validate()
        self.platform.validate()
        self.schedule.validate()
        late = [t for t in self.schedule.times if t >= self.duration]
        if late:
            raise ValueError(f"trial.schedule: switch time {late[0]} s is not before trial.duration = {self.duration} s")

    def default_fidelity(self) -> str:
        """Fewest states the scene needs: free inflation without a load, else the paper's model."""
        return "free" if self.platform.mass <= 0 else "quasi_static"


@dataclass
class SimSettings(Settings):
    """How to integrate (SI; each field's unit, range and one-line doc are in its declaration). The
    reference also reports at the log's times; atol is a fraction of each state's typical magnitude
    (gas mass 1e-5 kg, lengths 1e-2 m, velocity 1e-2 m/s)."""

    WHERE = "sim"

    integrator: str = setting("rk4", choices=INTEGRATORS, doc="integration scheme")
    dt: float | None = setting(None, lo=1e-7, hi=0.1, unit="s", user="ms",
                               doc="fixed step; default per integrator and fidelity")
    log_dt: float = setting(0.01, lo=1e-5, hi=10.0, unit="s", user="ms", doc="log sampling period")
    rtol: float = setting(1e-8, lo=1e-14, hi=1e-1, lo_open=True, doc="relative tolerance of the adaptive integrator")
    atol: float = setting(1e-8, lo=1e-16, hi=1.0, lo_open=True, doc="absolute tolerance of the adaptive integrator")
    sensor_range: float = setting(35e3, lo=1e3, hi=1e6, unit="Pa", user="kPa", doc="sensor saturation pressure")

    def step_for(self, fidelity: str) -> float:
        return self.dt if self.dt is not None else DEFAULT_DT[(self.integrator, fidelity)]


@dataclass
class Log:
    """Time series of one trial (SI): columns t, inputs, outputs
    (:data:`hbma_ctrl.models.fidelity.OUTPUTS`), mode, mass_in.

    ``mass_in`` is the integrated net mass flow since t = 0 (kg), integrated by the same scheme
    as the state, so ``m - m0 - mass_in`` measures mass conservation. ``events`` holds
    (t, name) pairs; ``status`` is 'ok', 'resting' (a load that never lifted), 'diverged' or
    'incomplete' (the adaptive reference stopped at its segment cap). ``peaks`` holds the largest
    h, p and F (m, Pa, N) over every integration step, not only the logged rows: a coarse log
    interval must not hide a peak between two rows.
    """

    name: str
    fidelity: str
    data: dict
    events: list = field(default_factory=list)
    status: str = "ok"
    wall_s: float = 0.0
    peaks: dict = field(default_factory=dict)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.data[key]
