"""One chamber as a system: ``tick(t, p[1], held[3, 1]) -> u[3, 1]``, the start-up calibration, setpoints
and the status a daemon shows (SI).

:class:`ChamberSystem` wraps :class:`hbma_ctrl.runtime.chamber.ChamberLoop` (estimator, controller,
supervisor) and the :class:`hbma_ctrl.runtime.calibrate.StartupCalibration` that runs before it for the
rig's view: the readings of every chamber (Pa, (n,)) in, the plant input ``u`` (3, n) out. Setpoints are
checked on the caller's thread (:meth:`ChamberSystem.check_setpoint`: clipped to what is reachable,
saying what was clipped) and applied between periods (:meth:`ChamberSystem.apply_setpoint`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Command, Controller, GeneratedController, GeneratedEstimator, check_role
from hbma_ctrl.core.loopgen import LogColumn, LoopSpec, Part, Stage
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.runtime.calibrate import StartupCalibration
from hbma_ctrl.runtime.chamber import ChamberLoop, chamber_supervisor, whole_multiple
from hbma_ctrl.sim.rig import RigSettings
from hbma_ctrl.system.base import SystemBase
from hbma_ctrl.system.roles import (
    calibration_summary,
    controller_settings_of,
    default_estimator,
    make_calibration,
    make_controller,
    make_pwm,
)
from hbma_ctrl.system.sections import ControllerSection

__all__ = ["ChamberSystem", "chamber_system", "chamber_setpoint"]


class _RigClock:
    """The loop's estimator, stepped at the rig's own time stamp of the reading (s), not the loop's
    schedule time: its prediction spans the true time between readings. ``inner`` is the wrapped
    estimator; every other attribute is the estimator's own."""

    def __init__(self, estimator, system: "ChamberSystem"):
        self.inner, self._system = estimator, system

    def step(self, t: float, measurement, applied):
        """The wrapped estimator's step at the rig time of this reading (``t``, the loop's time, unused)."""
        return self.inner.step(self._system.t_rig, measurement, applied)

    def __getattr__(self, name):
        return getattr(self.inner, name)


class ChamberSystem(SystemBase):
    """One chamber under :class:`ChamberLoop` (see module doc). ``h_range``: reachable targets (lo, hi), m.

    ``calibration``: a :class:`StartupCalibration` run first (``[controller] calibrate``): its excitation
    drives the chamber, its estimator is the loop's. While it runs, ``warming`` is True: its fit (about
    a second in the tick that ends it, while the chamber vents) does not feed the loop watchdog.
    ``take_events()`` hands the caller what to log.

    Clocks: the loop closes at its first tick after the calibration (at once without one). From then on
    the controller, the target schedule and the load schedule of a scene run on the loop's time, whole
    sample periods (``sample_period`` s) since it closed: a lockstep rig's k-th reading is at exactly k
    periods, so a schedule's step lands on the same sample wherever the loop starts, and a real rig's
    jitter does not move a target change by a fraction of a period. The estimator runs on the rig's own
    time stamps (its prediction spans the true time between readings).
    """

    kind = "chamber"

    def __init__(self, loop: ChamberLoop, p_limit: float, h_range: tuple[float, float], sample_period: float,
                 names=("C1",), calibration: StartupCalibration | None = None):
        super().__init__(loop, names, p_limit)
        self.h_range = (float(h_range[0]), float(h_range[1]))
        self.sample_period = float(sample_period)
        self.calibration = calibration
        self.calibration_summary: dict | None = None
        self.t_rig = math.nan  # the rig time of the newest reading, s
        self.t_closed: float | None = None  # the rig time the loop closed at, s
        self._t0: float | None = None
        loop.estimator = _RigClock(loop.estimator, self)

    @classmethod
    def of(cls, estimator, controller: Controller, sample_period: float, reference=None,
           **loop_options) -> "ChamberSystem":
        """A chamber system from role objects, without a scenario: ``estimator`` and ``controller`` in
        a :class:`ChamberLoop` on a rig sampled every ``sample_period`` s, following ``reference``
        (m at time t s, a constant height m, or None = hold). The controller runs every
        ``settings.sample_period / sample_period`` ticks (ValueError naming both when that is no whole
        number); ``loop_options`` go to :class:`ChamberLoop` (supervisor, preview_steps, pwm, ...)."""
        check_role(controller, Controller, "ChamberSystem.of: controller")
        settings = controller.settings
        every = whole_multiple(float(getattr(settings, "sample_period", sample_period)), float(sample_period),
                               f"{type(controller).__name__} sample_period", "the rig's sample_period")
        loop = ChamberLoop(estimator, controller, reference=reference, every=every, **loop_options)
        return cls(loop, settings.p_max, (settings.h_min, settings.h_max), sample_period)

    @property
    def warming(self) -> bool:
        """True while the start-up calibration runs (its ticks do not feed the loop watchdog)."""
        return self.calibration is not None and not self.calibration.done

    def loop_time(self, t: float) -> float:
        """The loop's time (s) at rig time ``t``: whole sample periods since it closed (see the class doc)."""
        if self.t_closed is None:
            raise ValueError("ChamberSystem.loop_time: the loop has not closed yet")
        return round((float(t) - self.t_closed) / self.sample_period) * self.sample_period

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s) with the reading p (Pa, (1,)) -> U (3, 1); ``held`` (3, 1): the
        command the rig reports it held over the period p ends (None: the last one returned)."""
        self.t_rig = float(t)
        if self._t0 is None:
            self._t0 = float(t)
            if self.calibration is not None:
                self._events.append(("calibration", "start-up calibration: vent, pump pulse, hold, vent"))
        h = None if held is None else Command(*(float(x) for x in np.asarray(held, dtype=float).reshape(3)))
        if self.warming:
            cmd, done = self.calibration.tick(t, float(p[0]), h)
            if done:
                self.loop.command = cmd  # the loop takes over from the calibration's vent command
            return cmd.as_array().reshape(3, 1)
        if self.t_closed is None:
            self._close(float(t))
        return self.loop.tick(self.loop_time(t), float(p[0]), h).as_array().reshape(3, 1)

    def _close(self, t: float) -> None:
        """The loop closes at rig time t (s): after the calibration, its outcome is reported with the
        time it took until now."""
        self.t_closed = t
        cal = self.calibration
        if cal is None:
            return
        self.calibration_summary = calibration_summary(cal, t - self._t0)
        s = self.calibration_summary
        facts = (f": flow x{s['flow_factor']:.3f}, modulus x{s['modulus_factor']:.3f}, dead volume "
                 f"x{s['dead_volume_factor']:.3f}" if cal.result is not None else "")
        self._events.append(("calibration", f"{cal.status} after {t - self._t0:.2f} s{facts}"))

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m (NaN = none)."""
        tg = self.loop.target
        return np.array([np.nan if tg is None else tg])

    def _reach(self) -> float:
        """The highest height the controller's last step could reach under the load it estimated, within
        its pressure and stretch limits, m (inf when it reports none: before its first step, or a
        controller that computes no reach)."""
        r = (getattr(self.loop.controller, "last", None) or {}).get("reachable_height")
        return float(r) if r is not None and math.isfinite(r) else math.inf

    def effective_targets(self) -> np.ndarray:
        """The target the controller works to, m: this period's, limited to the reach of its last step."""
        tg = self.targets()
        return np.minimum(tg, max(self._reach(), self.h_range[0]))

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber from the estimator, NaN before the first tick."""
        e = self.loop.estimate
        if e is None:
            return (np.full(1, np.nan),) * 3
        return np.array([e.h]), np.array([float(e.std.get("h", np.nan))]), np.array([e.p])

    def layers(self) -> list:
        """No layers: a single chamber."""
        return []

    def check_setpoint(self, request: dict) -> dict:
        """Heights {0: h m} -> {"applied", "clipped"} (clipped to ``h_range`` and to the reach of the
        controller's last step: what the chamber reaches under its present load within its pressure and
        stretch limits, the height it settles at); ValueError for layers or
        another chamber. The request is a validated :class:`~hbma_ctrl.app.schema.api.SetpointRequest`'s
        (finite heights)."""
        return chamber_setpoint(request, self.h_range, max(self._reach(), self.h_range[0]))

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold the applied height from now on (the file's target schedule ends)."""
        h = applied.get("heights", {}).get(0)
        if h is not None:
            self.loop.set_reference(lambda _t, h=float(h): h)

    def to_function(self, t: np.ndarray, p0: float, estimate: bool = True) -> LoopSpec:
        """This system's control side as a generated loop (:class:`~hbma_ctrl.core.loopgen.LoopSpec`) over
        the tick times ``t`` (s, whole sample periods from the loop's closing), the roles' own stages
        (:meth:`hbma_ctrl.estimators.ekf.EKF.stages`, :meth:`hbma_ctrl.controllers.mpc.NMPC.stages`,
        :meth:`hbma_ctrl.runtime.safety.Supervisor.stages`, the valves' minimum on-time shaping) in the
        tick's order. Reads ``t`` and the reading ``p`` (Pa; the estimator starts from the first, p0,
        and is stepped by it here); writes ``u``, the command sent, which a lockstep loop holds over the
        next period (the ``held`` of :meth:`tick`). The target, estimate, command and solver status are
        its log columns. ``estimate`` False leaves the estimator out: the caller's stages write
        ``est_h``, ``est_p``, ``est_F`` and ``resting`` first. ValueError naming the setting that cannot
        be generated."""
        loop = self.loop
        if self.calibration is not None:
            raise ValueError("[controller] calibrate = true: the start-up calibration does not generate; build "
                             "the system without it")
        if loop.reference is None:
            raise ValueError("the loop has no reference: a generated loop follows a target schedule")
        t = np.asarray(t, dtype=float)
        ctrl = loop.controller
        est = loop.estimator.inner  # the loop's estimator is always wrapped (ChamberSystem.__init__)
        if not isinstance(ctrl, GeneratedController):
            raise ValueError(f"[controller] kind: {type(ctrl).__name__} has no generated form (only 'mpc' does)")
        if estimate and not isinstance(est, GeneratedEstimator):
            raise ValueError(f"[estimator] filter = '{type(est).__name__.lower()}': only the EKF generates C")
        N, pwm = ctrl.settings.horizon, loop.pwm
        cmd = "u" if pwm is None else "wanted"  # the command the controller and its supervisor hold
        target = np.array([loop.reference(tk) for tk in t])
        P, dp = loop.preview_steps, loop.preview_period
        ref = (np.array([[loop.reference(tk + dp * (min(j, P - 1) + 1)) for j in range(N)] for tk in t]) if P
               else np.repeat(target[:, None], N, axis=1))
        part = Part([], {"t": [0.0], "p": [p0], "u": np.zeros(3), "target": [0.0], "ref": np.zeros(N)},
                    {"t": t[:, None], "target": target, "ref": ref},
                    [LogColumn("target_mm", "target", 0, 1e3)] + [LogColumn(k, "u", i) for i, k in enumerate(
                        ("speed", "inlet", "outlet"))])
        if estimate:
            part = part.add(est.stages(t, p0))
        else:
            part = part.add(Part([], {"est_h": [0.0], "est_p": [0.0], "est_F": [0.0], "resting": [1.0]}, log=[
                LogColumn("h_est_mm", "est_h", 0, 1e3), LogColumn("p_est_kpa", "est_p", 0, 1e-3),
                LogColumn("F_est_n", "est_F", 0, 1.0)]))
        part = part.add(ctrl.stages(t, loop.every, cmd))
        part = part.add(loop.supervisor.stages(3, N, {"t": "t", "command": "u0", "pressure": "est_p", "ok": "ok",
                                                      "plan": "U_guess", "plan_given": "ok", "target": "target",
                                                      "command_out": cmd}, loop.every))
        if pwm is not None:
            # every tick, the held command shaped for the valves' minimum opening (its carry per valve)
            part = part.add(Part([Stage(pwm.function(), ["wanted", "pwm_carry"], ["u", "pwm_carry"])],
                                 {"wanted": np.zeros(3), "pwm_carry": np.zeros(2)}))
            part.meta["controller"] += f", duties shaped for a {pwm.min_duty:g} minimum duty"
        return LoopSpec("chamber", self.sample_period, t.size, part.signals, part.streams, part.stages, part.log,
                        part.meta).validate()

    def stats(self) -> dict:
        """The controller's and the runtime's statistics (ms, counts), and ``calibration`` (the
        start-up calibration's outcome, edge units, as the controller scene reports it) when it ran."""
        out = super().stats()
        if self.calibration is not None:
            out["calibration"] = self.calibration_summary or {"status": self.calibration.status}
        return out


def chamber_system(actuator: Actuator, pneumatics: Pneumatics, platform: Platform, section: ControllerSection,
                   rig_settings: RigSettings, *, estimator=None, controller=None, model: PredictionModel | None = None,
                   calibrate: bool | None = None, realtime: bool = False, stats_capacity: int = 4096,
                   period_key: str = "[rig] sample_period_ms") -> ChamberSystem:
    """The chamber system a ``[controller]`` section asks for on a rig of ``rig_settings`` (SI).

    ``estimator`` defaults to the EKF on the nominal model (:func:`~hbma_ctrl.system.roles.default_estimator`),
    ``controller`` to the one the section names; an NMPC with a horizon gets the future targets for ramps and
    sines (or as ``[controller] preview`` says). ``calibrate`` (None = the section's ``calibrate``) puts the
    start-up calibration first. ``realtime``: the loop runs against a wall clock (the rig daemon), so the
    NMPC's solve-time budget is enforced whatever the section says. ``period_key`` names the rig's period as
    the user sets it, for the error when the controller's period is no whole multiple of it.
    """
    rs = rig_settings
    est = estimator or default_estimator(actuator, pneumatics, rs)
    if controller is None and realtime and section.kind == "mpc":
        # a real-time loop always bounds the solver: an overrun is a failed step (the supervisor replays
        # the last plan, then the safe command), never a late command
        section = replace(section, mpc=replace(section.mpc, enforce_budget=True))
    ctrl = controller or make_controller(section, actuator, pneumatics, model)
    check_role(ctrl, Controller, "chamber_system: controller")
    every = whole_multiple(section.sample_period, rs.sample_period, "[controller] sample_ms", period_key)
    # controllers with a horizon get the future targets (a rig daemon knows its trajectory too)
    use_preview = section.preview if section.preview is not None else (
        section.reference.interpolation == "linear" or section.reference.sine_amplitude > 0)
    preview_n = section.mpc.horizon if ctrl.accepts_preview and use_preview else 0
    settings = ctrl.settings or controller_settings_of(section)
    loop = ChamberLoop(est, ctrl, chamber_supervisor(settings), reference=section.reference, every=every,
                       preview_steps=preview_n, preview_period=section.sample_period, stats_capacity=stats_capacity,
                       pwm=make_pwm(section, rs.sample_period))
    h_min, h_max = float(settings.h_min), float(settings.h_max)
    cal = None
    if section.calibrate if calibrate is None else calibrate:
        cal = make_calibration(actuator, pneumatics, platform, section, rs, est)
    return ChamberSystem(loop, section.p_max, (h_min, h_max), rs.sample_period, calibration=cal)


def chamber_setpoint(request: dict, h_range: tuple[float, float], reach: float = math.inf) -> dict:
    """One chamber's setpoint request (heights {0: h m}) -> {"applied", "clipped"}: each height clipped
    to ``h_range`` (m) and to ``reach`` (m, the highest the chamber reaches now), each clip said in a
    line; ValueError for layers or another chamber."""
    if request.get("layers"):
        raise ValueError("layers: this daemon runs one chamber; send heights_mm instead")
    heights = request.get("heights") or {}
    if not heights:
        raise ValueError("no setpoint given: send heights_mm for chamber 0")
    clipped, applied = [], {}
    lo, hi = h_range
    for i, h in heights.items():
        if int(i) != 0:
            raise ValueError(f"heights_mm.{i}: chamber index out of range [0, 0] (one chamber)")
        h = float(h)
        hc = min(max(h, lo), hi, reach)
        if hc != h:
            why = (f"the controller's range [{U.to_mm(lo):g}, {U.to_mm(hi):g}] mm" if h < lo or reach >= hi
                   else "the highest the chamber reaches under its present load within its pressure and "
                        "stretch limits")
            clipped.append(f"heights_mm.{i} = {U.to_mm(h):g} clipped to {U.to_mm(hc):.2f} mm ({why})")
        applied[0] = hc
    return {"applied": {"heights": applied}, "clipped": clipped}
