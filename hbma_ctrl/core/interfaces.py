"""The contracts of the roles a loop embeds: what a chamber's estimator and controller and the robot's
controller offer, and the one step API they share (SI).

Every role is a small object configured by a settings dataclass, with no global state, and a
``step``:

- estimator (:class:`Estimator`): ``step(t, measurement, applied_command) -> Estimate`` and its
  diagnostics (output covariance, NIS, innovation, step time: None where it has none);
- controller (:class:`Controller`): ``step(t, estimate, reference[, preview]) -> Command``, its
  settings (``p_max``, ``guard_margin``, ...: :class:`ControllerSettings`), the last step's
  :class:`StepStatus`, its ``plan``, ``applied(command)`` (the command finally sent) and ``stats()``;
- robot controller (:class:`RobotController`): per period the supply and outlet duty of every
  chamber, from the estimate (:class:`RobotEstimateController`) or from the readings
  (:class:`RobotReadingsController`), with its failure flags and plans.

so a daemon's loop is ``cmd = ctrl.step(t, est.step(t, p_meas, cmd), ref)``. The contracts are
runtime-checkable Protocols: :class:`hbma_ctrl.runtime.chamber.ChamberLoop` and
:class:`hbma_ctrl.runtime.robot.RobotLoop` refuse a role that lacks a member (:func:`check_role`), and
then use every member by plain attribute access. The members a role may do without have defaults in
a base class (:class:`EstimatorBase`, :class:`ControllerBase`, :class:`RobotControllerBase`,
:class:`ControllerSettingsDefaults`): a role of one's own subclasses it and writes its ``step``.

Why typed contracts: a loop that probed for a member (``getattr(ctrl, "plan", None)``) silently
skipped a misspelt one; here it is named when the loop is built, as a solver's status codes are part
of its interface (acados) and filters report uniform diagnostics (filterpy).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from numbers import Real
from typing import Any, ClassVar, Literal, Protocol, runtime_checkable

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.settings import setting
from hbma_ctrl.core.validation import finite_or_nan

__all__ = ["Command", "Estimate", "Reference", "SAFE_COMMAND", "check_time",
           "SolveStatus", "StepStatus", "STEP_OK", "ControllerSettings", "ControllerSettingsDefaults",
           "Estimator", "EstimatorBase", "Controller", "ControllerBase",
           "RobotFeedback", "RobotController", "RobotEstimateController", "RobotReadingsController",
           "RobotControllerBase", "protocol_members", "check_role"]

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


# --- a controller step's outcome -------------------------------------------------------------------
class SolveStatus(str, enum.Enum):
    """How a controller step ended: ``OK`` (its command stands), ``FAILED`` (no usable solution: the
    supervisor replays the last plan, then sends the safe command) or ``OVERRUN`` (over its wall-clock
    budget in a real-time loop: the same fallback)."""

    OK = "ok"
    FAILED = "failed"
    OVERRUN = "overrun"


@dataclass(frozen=True)
class StepStatus:
    """A controller step's outcome: its :class:`SolveStatus` and, for a failure, what failed.

    ``str()`` is the text logs and ``last["status"]`` carry: ``'ok'``, ``'failed: <detail>'``,
    ``'overrun'`` or ``'overrun: <detail>'``.
    """

    kind: SolveStatus = SolveStatus.OK
    detail: str = ""

    @property
    def ok(self) -> bool:
        """True when the step's command stands."""
        return self.kind is SolveStatus.OK

    def __str__(self) -> str:
        return f"{self.kind.value}: {self.detail}" if self.detail else self.kind.value


#: the outcome of a step that solved (a class default: it never changes)
STEP_OK = StepStatus()


# --- contracts ---------------------------------------------------------------------------------------
@runtime_checkable
class ControllerSettings(Protocol):
    """What the runtime reads from a chamber controller's settings (SI): the pressure limit and the
    supervisor's guard band, Pa; how many steps a failed step's shifted plan may stand in; the target
    heights a daemon's setpoint is clipped to, m. :class:`ControllerSettingsDefaults` has the last three."""

    p_max: float
    guard_margin: float
    fallback_plan_steps: int
    h_min: float
    h_max: float


def sample_period_setting(default: float = 0.02) -> Any:
    """A chamber controller's period, s, (0, 1]; the scenario's ``sample_ms``."""
    return setting(default, lo=0.0, hi=1.0, lo_open=True, unit="s", user="ms", key="sample_ms",
                   doc="controller period (a multiple of the rig's)")


def p_max_setting(default: float = 35e3) -> Any:
    """A chamber controller's gauge pressure limit, Pa, (0, 1e6]; the scenario's ``p_max_kpa``."""
    return setting(default, lo=0.0, hi=1e6, lo_open=True, unit="Pa", user="kPa", doc="gauge pressure limit")


def guard_margin_setting(default: float) -> Any:
    """How close to p_max the pressure guard cuts the pump, Pa, [0, p_max]; the scenario's ``guard_margin_kpa``."""
    return setting(default, lo=0.0, hi=1e6, unit="Pa", user="kPa",
                   doc="pressure guard margin, at most p_max_kpa; default MPC 0.5, PID, bang-bang and LQI 1")


class ControllerSettingsDefaults:
    """Defaults of the optional :class:`ControllerSettings` members for a settings dataclass that has no
    such field (plain class attributes, so no dataclass field is added): 10 fallback plan steps and
    targets from 0 to 20 mm."""

    fallback_plan_steps: ClassVar[int] = 10
    h_min: ClassVar[float] = 0.0
    h_max: ClassVar[float] = U.mm(20.0)


@runtime_checkable
class Estimator(Protocol):
    """A chamber's estimator: ``step(t, measurement, applied_command) -> Estimate`` (t s, the pressure
    reading Pa, NaN = dropout; the command held over the period the reading ends) and what it reports
    about its last step. Members :class:`EstimatorBase` gives defaults for:

    settings : its settings (a :class:`hbma_ctrl.estimators.common.FilterSettings` for the filters), or None.
    state_names : the layout of ``Estimate.mean`` (empty: no state the runtime can read).
    last_output_cov : covariance (5 x 5) of (h1, h2, h, F, p) at the last step, None = not provided.
    last_nis : the last update's normalised innovation squared, None = no update (or not provided).
    last_innovation : the last update's innovation over its std, None = no update (or not provided).
    last_step_s : the last step's wall time, s, None = not measured.
    attach(rig) : a simulation hands the estimator its rig before the loop starts (a test oracle reads
        the true state from it); the filters ignore it.
    """

    settings: Any
    state_names: tuple[str, ...]
    last_output_cov: np.ndarray | None
    last_nis: float | None
    last_innovation: float | None
    last_step_s: float | None

    def step(self, t: float, measurement: float, applied_command: Command) -> Estimate: ...

    def attach(self, rig: Any) -> None: ...


class EstimatorBase:
    """Defaults of the :class:`Estimator` members an estimator may do without: no settings, no
    readable state, no diagnostics, ``attach`` ignores the rig. Subclass it and write ``step``."""

    settings: Any = None
    state_names: tuple[str, ...] = ()
    last_output_cov: np.ndarray | None = None
    last_nis: float | None = None
    last_innovation: float | None = None
    last_step_s: float | None = None

    def attach(self, rig: Any) -> None:
        """The simulated rig before the loop starts; ignored (a test oracle keeps it to read the truth)."""


@runtime_checkable
class Controller(Protocol):
    """A chamber's controller: ``step(t, estimate, reference, preview=None) -> Command`` (the command to
    hold for the next period; ``preview``: the targets at the next sample periods, m, handed over only
    when ``accepts_preview``) and what the runtime's :class:`~hbma_ctrl.runtime.chamber.ChamberLoop` reads
    around it. Members :class:`ControllerBase` gives defaults for:

    settings : :class:`ControllerSettings` (the supervisor's limits), None = the caller gives the supervisor.
    step_status : the last step's :class:`StepStatus` (a step that failed returns a command anyway; the
        supervisor then falls back).
    plan : the inputs (N, 3) the last step planned over its horizon (an overrun's late solution too),
        replayed by the supervisor after a failure; None = no plan.
    reports_failures : its step_status can say failed or overrun (the runtime then reports the
        fallback's causes and the step's CPU time).
    accepts_preview : ``step`` takes the future targets.
    applied(command) : the command finally sent, after the supervisor (an MPC's rate terms start from it).
    stats() : what it reports itself (variant, horizon, clipped targets, ...), merged into the loop's.
    """

    settings: ControllerSettings | None
    step_status: StepStatus
    plan: np.ndarray | None
    reports_failures: bool
    accepts_preview: bool

    def step(self, t: float, estimate: Estimate, reference: Reference,
             preview: Sequence[float] | None = None) -> Command: ...

    def applied(self, command: Command) -> None: ...

    def stats(self) -> dict: ...


class ControllerBase:
    """Defaults of the :class:`Controller` members a controller may do without: no settings, every
    step ok, no plan, no preview, ``applied`` ignored, no stats. Subclass it and write ``step``."""

    settings: ControllerSettings | None = None
    step_status: StepStatus = STEP_OK
    plan: np.ndarray | None = None
    reports_failures: bool = False
    accepts_preview: bool = False

    def applied(self, command: Command) -> None:
        """The command finally sent; ignored."""

    def stats(self) -> dict:
        """Nothing of its own to report."""
        return {}


@runtime_checkable
class GeneratedEstimator(Protocol):
    """An estimator with a generated form: ``stages(t, p0)`` gives its part of a generated loop
    (:class:`hbma_ctrl.core.loopgen.Part`) over the tick times ``t`` (s), started from the reading ``p0`` (Pa)."""

    def stages(self, t: np.ndarray, p0: float) -> Any: ...


@runtime_checkable
class GeneratedController(Protocol):
    """A controller with a generated form: ``stages(t, every, command)`` gives its part of a generated loop
    (:class:`hbma_ctrl.core.loopgen.Part`) over the tick times ``t`` (s), solving every ``every`` ticks and
    writing the signal ``command``."""

    def stages(self, t: np.ndarray, every: int, command: str = "u") -> Any: ...


#: what a robot controller's ``step`` takes: the bank's estimate or the pressure readings
RobotFeedback = Literal["estimate", "readings"]


@runtime_checkable
class RobotController(Protocol):
    """The robot's controller over its n chambers as :class:`~hbma_ctrl.runtime.robot.RobotLoop` uses it:
    per period the supply and outlet duties ((n,) each, in [0, 1]) from ``step``, whose arguments
    ``feedback`` names (:class:`RobotEstimateController`, :class:`RobotReadingsController`). Members
    :class:`RobotControllerBase` gives defaults for:

    failed : the last step has no usable decision (the supervisor falls back).
    overran : the last step was over its wall-clock budget (also ``failed``).
    plan : the supply and outlet planned over the horizon (N, n, 2) by the last usable step, None = none.
    late_plan : an overrun step's solution (N, n, 2), the supervisor's plan for the next failure.
    status : the last step's status text (a failed step's cause in the supervisor's log).
    inaccurate : steps whose solver did not report 'solved'; overruns : steps over the budget.
    applied(a, o) : the supply and outlet (n,) each finally sent, after the supervisor.
    """

    feedback: RobotFeedback
    failed: bool
    overran: bool
    plan: np.ndarray | None
    late_plan: np.ndarray | None
    status: str
    inaccurate: int
    overruns: int

    def applied(self, a: np.ndarray, o: np.ndarray) -> None: ...


@runtime_checkable
class RobotEstimateController(RobotController, Protocol):
    """A robot controller on the EKF bank's estimate (``feedback = 'estimate'``, the robot NMPC):
    ``step(x0, b, W, h_ref, k, c, a_max) -> (a, o)`` with the gas masses x0, the pump-flow, modulus and
    dead-volume factors b, k, c, the loads W (N), the target heights h_ref (m) and each chamber's supply
    bound a_max ((n,) each); ``prime`` with the same arguments does its start-up work before the first
    period, the controller's state left as it was."""

    def step(self, x0: np.ndarray, b: np.ndarray, W: np.ndarray, h_ref: np.ndarray, k: np.ndarray | None = None,
             c: np.ndarray | None = None, a_max: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]: ...

    def prime(self, x0: np.ndarray, b: np.ndarray, W: np.ndarray, h_ref: np.ndarray, k: np.ndarray | None = None,
              c: np.ndarray | None = None, a_max: np.ndarray | None = None) -> None: ...


@runtime_checkable
class RobotReadingsController(RobotController, Protocol):
    """A robot controller on the pressure readings (``feedback = 'readings'``, the pressure PID):
    ``step(p_meas, W, h_ref) -> (a, o)`` with the readings (Pa; NaN = dropout), the loads (N) and the
    target heights (m), (n,) each."""

    def step(self, p_meas: np.ndarray, W: np.ndarray, h_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class RobotControllerBase:
    """Defaults of the :class:`RobotController` members a robot controller may do without: it never
    fails, has no plan, ignores what was sent and needs no start-up work. Subclass it, set
    ``feedback`` and write ``step``."""

    feedback: ClassVar[RobotFeedback]
    failed: bool = False
    overran: bool = False
    plan: np.ndarray | None = None
    late_plan: np.ndarray | None = None
    status: str = ""
    inaccurate: int = 0
    overruns: int = 0
    #: the last step's report (times in s, counts, ``status``), a new dict every step; None = none kept
    last_parts: dict | None = None

    def applied(self, a: np.ndarray, o: np.ndarray) -> None:
        """The supply and outlet finally sent; ignored."""

    def prime(self, x0: np.ndarray, b: np.ndarray, W: np.ndarray, h_ref: np.ndarray, k: np.ndarray | None = None,
              c: np.ndarray | None = None, a_max: np.ndarray | None = None) -> None:
        """No start-up work."""


#: the base class with a protocol's defaults, named in the error for a role that lacks a member
_BASES: dict = {Estimator: EstimatorBase, Controller: ControllerBase, ControllerSettings: ControllerSettingsDefaults,
                RobotController: RobotControllerBase, RobotEstimateController: RobotControllerBase,
                RobotReadingsController: RobotControllerBase}


def protocol_members(protocol: type) -> tuple[str, ...]:
    """The members (attributes and methods) a Protocol class declares, its protocol bases' included,
    in the order they are declared."""
    names: list[str] = []
    for cls in reversed(protocol.__mro__):
        if not vars(cls).get("_is_protocol") or cls is Protocol:
            continue
        own = list(vars(cls).get("__annotations__", {}))
        own += [n for n, v in vars(cls).items() if callable(v) and not n.startswith("_")]
        names += [n for n in own if n not in names]
    return tuple(names)


def check_role(obj: object, protocol: type, who: str) -> None:
    """TypeError unless ``obj`` satisfies ``protocol`` (one of this module's runtime-checkable
    contracts), naming ``who`` (the caller and the role), the members it lacks and the base class with
    their defaults."""
    if isinstance(obj, protocol):
        return
    missing = [n for n in protocol_members(protocol) if not hasattr(obj, n)]
    base = _BASES.get(protocol)
    hint = f"; subclass {__name__}.{base.__name__} for the defaults" \
        if base is not None and not isinstance(obj, base) else ""
    lacks = f"lacks {', '.join(missing)}" if missing else "does not satisfy"
    raise TypeError(f"{who}: {type(obj).__name__} {lacks} of {__name__}.{protocol.__name__}{hint}")
