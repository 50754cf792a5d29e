"""The one step API shared by estimators, controllers and the rig daemon that embeds them (SI).

Every role is a small object configured by a settings dataclass, with no global state, and a
``step``:

- estimator: ``step(t, measurement, applied_command) -> Estimate``
- controller: ``step(t, estimate, reference) -> Command``

so a daemon's loop is ``cmd = ctrl.step(t, est.step(t, p_meas, cmd), ref)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["Command", "Estimate", "Reference", "Estimator", "Controller", "SAFE_COMMAND"]


@dataclass(frozen=True)
class Command:
    """Actuator command: compressor speed, inlet and outlet valve duty, each in [0, 1].

    A duty d is the fraction of each PWM period the valve is held open (the relaxed on/off input).
    """

    speed: float = 0.0
    inlet: float = 0.0
    outlet: float = 0.0

    def __post_init__(self) -> None:
        for name in ("speed", "inlet", "outlet"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"command.{name} = {v!r} is out of range [0, 1]")

    def as_array(self) -> np.ndarray:
        return np.array([self.speed, self.inlet, self.outlet])


#: compressor off, inlet closed, outlet open: the membrane deflates to rest
SAFE_COMMAND = Command(0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Estimate:
    """What an estimator knows at time t (SI).

    h1, h2 : cap and cut heights, m; h = h1 - h2 the membrane (platform) height, m
    F : contact force, N; p : chamber gauge pressure, Pa
    mean, cov : the estimator's own state and covariance (layout in ``state_names``)
    std : one-sigma of h1, h2, h, F, p where the estimator provides it
    flags : e.g. {'saturated', 'missing', 'resting'}: what was unusual at this step
    """

    t: float
    h1: float
    h2: float
    h: float
    F: float
    p: float
    mean: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    state_names: tuple = ()
    std: dict = field(default_factory=dict)
    flags: frozenset = frozenset()


@dataclass(frozen=True)
class Reference:
    """Targets for one chamber: membrane height h (m); None = no target (hold)."""

    height: float | None = None


@runtime_checkable
class Estimator(Protocol):
    def step(self, t: float, measurement: float, applied_command: Command) -> Estimate: ...


@runtime_checkable
class Controller(Protocol):
    def step(self, t: float, estimate: Estimate, reference: Reference) -> Command: ...
