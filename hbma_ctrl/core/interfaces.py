"""The one step API shared by estimators, controllers and the rig daemon that embeds them (SI).

Every role is a small object configured by a settings dataclass, with no global state, and a
``step``:

- estimator: ``step(t, measurement, applied_command) -> Estimate``
- controller: ``step(t, estimate, reference) -> Command``

so a daemon's loop is ``cmd = ctrl.step(t, est.step(t, p_meas, cmd), ref)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from numbers import Real
from typing import Protocol, runtime_checkable

import numpy as np

from hbma_ctrl.core.validation import finite_or_nan

__all__ = ["Command", "Estimate", "Reference", "Estimator", "Controller", "SAFE_COMMAND", "check_time"]

_UNITS = {"t": "s", "h1": "m", "h2": "m", "h": "m", "F": "N", "p": "Pa"}


def _is_number(v) -> bool:
    # bool is an int to Python, and a str would only fail later inside numpy with no name attached
    return isinstance(v, (Real, np.floating, np.integer)) and not isinstance(v, (bool, np.bool_))


def check_time(t, who: str) -> float:
    """``t`` as a float; ValueError naming ``t`` (and ``who``: the caller) unless a finite number of s."""
    if math.isnan(finite_or_nan(t)):
        raise ValueError(f"{who}: t = {t!r} must be a finite time (s)")
    return float(t)


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

    def __post_init__(self) -> None:
        # NaN is allowed (no estimate yet, a dropout); a string or None is refused here, by name
        for name, unit in _UNITS.items():
            v = getattr(self, name)
            if not _is_number(v):
                raise TypeError(f"estimate.{name} = {v!r} must be a number ({unit})")


@dataclass(frozen=True)
class Reference:
    """Targets for one chamber: membrane height h (m); None = no target (hold)."""

    height: float | None = None

    def __post_init__(self) -> None:
        h = self.height
        if h is not None and math.isnan(finite_or_nan(h)):
            raise ValueError(f"reference.height = {h!r} must be a finite height (m) or None (hold)")


@runtime_checkable
class Estimator(Protocol):
    def step(self, t: float, measurement: float, applied_command: Command) -> Estimate: ...


@runtime_checkable
class Controller(Protocol):
    def step(self, t: float, estimate: Estimate, reference: Reference) -> Command: ...
