"""The robot's loop a rig daemon embeds: 3N readings -> EKF bank -> loads -> controller -> supervisor (SI).

Per ``RobotLoop.tick(t, readings_pa)`` (no I/O):

- the EKF bank steps on the readings with the previous period's decisions (the supply as the
  full-speed inlet duty its flow equals, the outlet) and loads (one mapped call);
- the loads are recomputed from the estimated heights by the robot's load sharing (used by this
  period's controller and the next predict: a one-period lag);
- the layer targets give every chamber's target height (:func:`hbma_ctrl.robot.targets.chamber_targets`);
  with ``target_rate`` each chamber's target moves towards it at most that fast (from the estimated
  height at the first tick; a zero target, the vent rule, applies at once): a new pose then moves
  the layers as fast as the rate, not as fast as the pumps and vents can, and a chamber's pressure
  follows its equilibrium curve instead of overshooting it (the layers' mass on the membranes);
- the robot NMPC (or the pressure PID, which works on the readings) picks every chamber's supply and
  outlet; for the NMPC a chamber whose target is zero gets no supply budget (a shared pump's duty
  would otherwise be shared with it), and the cautious cap limits the supply of a chamber near its
  limit point while its modulus factor is uncertain;
- the :class:`Supervisor` applies the fallback on a failed solve or an NMPC overrun (its step
  exceeded ``budget`` x period: replay the plan, then the safe command; an overrun's late plan is
  kept for the next failure), the vent rule (zero target), the pressure interlock (supply cut
  while a reading is within the margin of the limit), the stretch interlock (supply cut while a
  chamber's estimated stretch is at the design's ``max_stretch``) and the lost-estimate vent: a
  chamber whose filter is lost (its gas mass at the top of the model's tables, or a factor at the
  edge of its range: the estimate no longer says how far the membrane has grown, and a far-branch
  membrane pumped on grows without bound at a falling pressure, which the pressure interlock never
  sees) is vented until its reading is down, then its filter restarts from that reading; and the
  burst rule: a chamber whose readings fall far below its filter's prediction, period after period,
  or whose estimate is lost again and again (:class:`hbma_ctrl.runtime.burst.BurstTest` on the bank's
  signed innovations and lost estimates: a burst membrane or an outlet stuck open), gets the safe
  command until the supervisor is reset; the NMPC gets no
  supply budget for a chamber held by any of these; the command sent is handed back to the controller
  (``applied``: the NMPC's input-rate terms start from it);
- with ``valve_min_on`` the inlet and outlet duties sent are each 0 or at least the valves' minimum
  opening, a smaller one realised on average over the periods (:class:`hbma_ctrl.runtime.pwm.MinOnTime`,
  as the single chamber's loop does), and the bank predicts with the duties sent. A vent shorter than
  the minimum opening is first netted into the same chamber's supply, and one left over is sent
  only when the chamber's estimate is more than :data:`VENT_DEADBAND` and half the height one
  minimum opening takes off above its target (:meth:`RobotLoop.net_vents`).

The slew, the supply caps and the short vents are evaluated by the casadi Functions of
:mod:`hbma_ctrl.runtime.robot_step`, the supervisor, the burst test and the minimum on-time by their
own: those a generated robot loop runs.

The controller does not know the tip load (a disturbance). Step, EKF and controller times go into
bounded :class:`StepStats` (s); ``last_timing`` has this tick's.

Live-stream inputs: ``t`` must be a finite time not before the last tick's (ValueError naming
``t``); a tick k periods after the last one predicts the bank k periods (bounded by its
``max_gap``); targets (:meth:`RobotLoop.set_targets`) must be finite numbers, refused with a
ValueError naming the layer, row and key. Readings that cannot be physical are the bank's outliers.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import replace

import numpy as np

from hbma_ctrl.core.interfaces import (
    RobotController,
    RobotEstimateController,
    RobotReadingsController,
    check_role,
)
from hbma_ctrl.core.validation import finite_or_nan, floats_or_nan
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank
from hbma_ctrl.models.bank import ChamberBank, commands_from_inputs
from hbma_ctrl.models.defaults import DEFAULT_VALVE_MIN_ON
from hbma_ctrl.robot.design import RobotDesign, shared_supply
from hbma_ctrl.robot.plant import W_FLOOR
from hbma_ctrl.robot.statics import load_sharing
from hbma_ctrl.robot.targets import chamber_targets
from hbma_ctrl.runtime.burst import BurstTest, BurstTestSettings
from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction
from hbma_ctrl.runtime.pwm import MinOnTime
from hbma_ctrl.runtime.robot_step import VENT_DEADBAND, caps_function, net_vents_function, slew_function
from hbma_ctrl.runtime.safety import ZERO_TARGET, Supervisor, SupervisorSettings
from hbma_ctrl.runtime.stats import StepStats

__all__ = ["RobotLoop", "robot_supervisor", "check_targets"]

#: the controller contract for each ``feedback``: what its step takes
_FEEDBACK = {"estimate": RobotEstimateController, "readings": RobotReadingsController}

#: the keys of a layer target row, in order (units: s, m, rad, rad)
TARGET_KEYS = ("t", "centre", "bend", "direction")


def check_targets(targets: dict, n_layers: int) -> dict:
    """Layer targets {layer: ((t s, centre m, bend rad, direction rad), ...)} checked: every layer
    0..n_layers-1 present, rows of four finite numbers, times ascending. Returns them as float tuples;
    raises ValueError naming the layer, row and key."""
    if not isinstance(targets, dict):
        raise ValueError(f"targets must be a dict {{layer: rows}}, got {type(targets).__name__}")
    out = {}
    for k in range(n_layers):
        if k not in targets:
            raise ValueError(f"targets: layer {k} is missing (the robot has layers 0..{n_layers - 1})")
        rows = targets[k]
        if isinstance(rows, (str, bytes)) or not hasattr(rows, "__len__") or len(rows) == 0:
            raise ValueError(f"targets[{k}] must be a non-empty sequence of (t, centre, bend, direction) rows")
        clean = []
        for j, row in enumerate(rows):
            if isinstance(row, (str, bytes)) or not hasattr(row, "__len__") or len(row) != 4:
                raise ValueError(f"targets[{k}][{j}] = {row!r} must be (t s, centre m, bend rad, direction rad)")
            vals = []
            for key, v in zip(TARGET_KEYS, row):
                f = finite_or_nan(v)
                if math.isnan(f):
                    raise ValueError(f"targets[{k}][{j}].{key} = {v!r} must be a finite number")
                vals.append(f)
            if clean and vals[0] < clean[-1][0]:
                raise ValueError(f"targets[{k}][{j}].t = {vals[0]} s is before the previous row's {clean[-1][0]} s")
            clean.append(tuple(vals))
        out[k] = tuple(clean)
    extra = set(targets) - set(range(n_layers))
    if extra:
        raise ValueError(f"targets: layer {sorted(extra, key=str)[0]!r} does not exist (layers 0..{n_layers - 1})")
    return out


def robot_supervisor(pressure_limit: float, n: int, interlock_margin: float = 1e3, plan_period: float | None = None,
                     **overrides) -> Supervisor:
    """The robot's supervisor: interlock on the readings (supply cut within ``interlock_margin`` Pa of
    ``pressure_limit`` Pa; no forced vent; a dropout does not trigger it), vent on a zero target, the
    NMPC plan replayed at ``plan_period`` s per row. ``overrides`` set other :class:`SupervisorSettings`
    fields; its ``stretch_max`` left None, :class:`RobotLoop` guards the design's ``max_stretch``."""
    kw = dict(p_max=float(pressure_limit), guard_margin=float(interlock_margin), vent_margin=None,
              missing_is_limit=False, vent_height=ZERO_TARGET, plan_period=plan_period)
    kw.update(overrides)
    return Supervisor(SupervisorSettings(**kw), n=n)


#: commands remembered for matching a rig's report of the one it held, and the match's tolerance
#: (a per-mille link rounds to 0.0005)
HELD_HISTORY = 16
HELD_ATOL = 6e-4


def _flow_duty(a: np.ndarray, topology: str) -> np.ndarray:
    """The supply as the full-speed inlet duty the plant's flow equals (what the bank predicts with):
    tiny duties zeroed, a shared pump's budget applied."""
    d = commands_from_inputs(a, np.zeros_like(a), topology)[1]
    return shared_supply(d) if topology == "shared" else d


class RobotLoop:
    """EKF bank, load sharing, targets, controller and supervisor of a robot (see module doc).

    Parameters
    ----------
    design : the robot.
    model : the nominal per-chamber model (the controller's and the bank's).
    bank : the chambers' EKF bank (:class:`ChamberEKFBank`).
    controller : a :class:`~hbma_ctrl.core.interfaces.RobotController` over all chambers: on the bank's
        estimate (``feedback = 'estimate'``: :class:`hbma_ctrl.controllers.robot_mpc.RobotNMPC`) or on
        the readings (``'readings'``: :class:`hbma_ctrl.controllers.robot_pid.RobotPressurePID`). A
        controller that lacks a member is a TypeError naming it, an unknown ``feedback`` a ValueError.
    supervisor : an n-chamber :class:`Supervisor` (:func:`robot_supervisor`).
    targets : layer targets {layer index: ((t s, centre height m, bend rad, direction rad), ...)}.
    cautious : (pressure fraction, k std, duty): while a chamber's estimated pressure is above the
        fraction of its estimated peak pressure and its modulus factor's std is above the threshold,
        its supply duty is capped (the NMPC's input bound; pass the peak slowly so that its filter
        can tell the far branch from the near one); None = off. Estimate feedback only.
    stats_capacity : samples kept for the median and p99 of the step times.
    throttle : the compressor speed is a decision: throttled to the planned flow at each chamber's
        estimated pressure (:meth:`ChamberBank.valve_inputs`); False = full speed while an inlet is
        open (the inlet valve meters the flow).
    target_rate : the fastest a chamber's target height moves, m/s (None or 0: targets step).
    valve_min_on : the valves' shortest opening, s, [0, sample period] (0: duties sent as decided;
        default the models' 2 ms, :mod:`hbma_ctrl.models.defaults`).
    burst : the burst test on the bank's innovations (:class:`BurstTestSettings`; None = off): a chamber
        it flags gets the safe command until the supervisor is reset (its rule 7); ``bursts`` lists them.
    """

    def __init__(self, design: RobotDesign, model: ChamberBank, bank: ChamberEKFBank, controller: RobotController,
                 supervisor: Supervisor, targets: dict, cautious: tuple | None = (0.75, 0.03, 0.3),
                 stats_capacity: int = 4096, throttle: bool = True, target_rate: float | None = None,
                 valve_min_on: float = DEFAULT_VALVE_MIN_ON, burst: BurstTestSettings | None = BurstTestSettings()):
        self.design = design
        self.model = model
        self.bank = bank
        self.controller = controller
        self.supervisor = supervisor
        self.targets = check_targets(targets, design.n_layers)
        self.cautious = cautious
        self.throttle = bool(throttle)
        rate = 0.0 if target_rate is None else finite_or_nan(target_rate)
        if not rate >= 0.0:
            raise ValueError(f"RobotLoop: target_rate = {target_rate!r} must be a finite rate >= 0 m/s (0 = steps)")
        self.target_rate = rate
        #: the chamber targets the controller worked to at the last tick, m (the slewed ones)
        self.href: np.ndarray | None = None
        self.n = 3 * design.n_layers
        if supervisor.n != self.n:
            raise ValueError(f"RobotLoop: the supervisor is for {supervisor.n} chambers, the robot has {self.n}")
        check_role(controller, RobotController, "RobotLoop: controller")
        if controller.feedback not in _FEEDBACK:
            raise ValueError(f"RobotLoop: controller.feedback = {controller.feedback!r}: allowed "
                             f"{', '.join(map(repr, _FEEDBACK))}")
        check_role(controller, _FEEDBACK[controller.feedback], "RobotLoop: controller")
        #: the controller steps on the bank's estimate (the NMPC's arguments, the cautious cap, prime)
        self.is_mpc = controller.feedback == "estimate"
        if supervisor.settings.stretch_max is None:
            # a robot's loop always guards the membranes' stretch: the design's limit, unless the
            # supervisor was given its own
            supervisor.settings = replace(supervisor.settings, stretch_max=design.max_stretch).validate()
        self.step_s, self.ekf_s, self.ctrl_s = (StepStats(stats_capacity) for _ in range(3))
        self.last_timing = (float("nan"),) * 3
        #: the last tick's controller part split up, s: loads and targets, the controller's step, the
        #: supervisor, the valve inputs (a slow tick's report says where its time went)
        self.last_parts: dict = {}
        self.cautious_steps = 0
        self.estimate: dict | None = None
        self.valve_commands = np.zeros((3, self.n))
        #: the last tick's (supply, outlet) duties, each (n,): the decision the valve commands carry out
        self.decision = (np.zeros(self.n), np.zeros(self.n))
        self._w_prev = np.zeros((2, self.n))
        # the valve commands sent lately with what the bank predicts with for each (newest last): a rig
        # that reports the command it held (tick's ``held``) names one of them
        self._sent: deque = deque(maxlen=HELD_HISTORY)
        self.held_unmatched = 0
        self.loads = np.maximum(load_sharing(design, np.zeros((design.n_layers, 3))).forces.ravel(), W_FLOOR)
        self._tcache: dict = {}
        self._k = 0
        self._t: float | None = None
        self._period = float(bank.settings.sample_period)
        self.pwm = MinOnTime(self._period, valve_min_on)
        self.pwm.carry = np.zeros((2, self.n))
        #: the tick's blocks' Functions on buffers, by what they are built from (:meth:`_block`)
        self._blocks: dict = {}
        #: the limit-point pressures of the cautious cap at the loads (refreshed every tenth tick), Pa
        self._peak_p = np.zeros(self.n)
        self._peak_p = self._caps(self.loads, np.ones(self.n), np.zeros(self.n), np.zeros(self.n),
                                  np.full(self.n, np.nan), np.full(self.n, np.nan), np.zeros(self.n), True)[2]
        self.burst = None if burst is None else BurstTest(self.n, burst)

    def set_targets(self, targets: dict) -> None:
        """Replace the layer targets ({layer: ((t s, centre m, bend rad, direction rad), ...)}) from the next
        tick on (the cache of chamber targets is dropped with them). ValueError (naming the layer, row
        and key) on a non-finite or non-numeric value; the old targets then stay."""
        self.targets = check_targets(targets, self.design.n_layers)
        self._tcache.clear()

    def chamber_targets(self, t: float) -> np.ndarray:
        """Every chamber's target height at time t, m (n,)."""
        return chamber_targets(self.design, self.targets, t, self._tcache)

    def tick(self, t: float, readings_pa: np.ndarray, held: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One period at time t (s) with the 3N pressure readings (Pa, NaN = dropout) -> (supply, outlet),
        each (n,) in [0, 1]; the plant's valve inputs (3 x n) are in ``valve_commands``. ``held``: the
        valve inputs (3 x n) the rig reports it held over the period these readings end (None = the
        last ones returned, as in a lockstep simulation); the bank predicts with them."""
        tf = finite_or_nan(t)
        if math.isnan(tf):
            raise ValueError(f"RobotLoop.tick: t = {t!r} must be a finite time in s")
        if self._t is not None and tf < self._t - 1e-9:
            raise ValueError(f"RobotLoop.tick: t = {tf} s is before the last tick's {self._t} s "
                             "(time must not go backwards)")
        # periods since the last tick (a late tick predicts them all; the bank bounds a long gap)
        steps = 1 if self._t is None else max(1, int(round((tf - self._t) / self._period)))
        self._t = t = tf
        ctrl, sup, model = self.controller, self.supervisor, self.model
        t0 = time.perf_counter()
        est = self.bank.step(readings_pa, self._held_input(held), self.loads, steps=steps)
        # the supervisor's interlock sees the readings the bank trusted (an outlier is no pressure)
        z = np.where(est["outlier"], np.nan, floats_or_nan(readings_pa, self.n))
        t1 = time.perf_counter()
        self.estimate = est
        burst = None
        if self.burst is not None:
            # a chamber lost again and again: the supervisor's rule 6 below starts an episode here
            self.burst.step(t, est["r"], est["lost"] & ~self.supervisor.lost)
            burst = self.burst.flagged
        W = np.maximum(load_sharing(self.design, est["h"].reshape(-1, 3)).forces.ravel(), W_FLOOR)
        self.loads = W
        href = self._slew(self.chamber_targets(t), est["h"], steps * self._period)
        self.href = href
        stretch, lost = est["lam"], est["lost"]
        t_ctrl = time.perf_counter()
        plan, ok, cause = None, True, "ok"
        try:
            if self.is_mpc:
                a_max, near, self._peak_p = self._caps(W, est["k"], est["p"], est["k_std"], href, stretch, lost,
                                                       self._k % 10 == 0)
                self.cautious_steps += int(near.sum())
                # no preview: the NMPC sees the current target only (as the PID does); a preview would
                # start each move up to one horizon early
                a, o = ctrl.step(est["x"], est["b"], W, href, est["k"], est["c"], a_max)
            else:
                a, o = ctrl.step(z, W, href)
            ok = not ctrl.failed
            if ok:
                cause, plan = "ok", self._plan(ctrl.plan)
            elif ctrl.overran:
                # late: the supervisor replays the last plan now and keeps this one for the next failure
                cause, plan = "overrun", self._plan(ctrl.late_plan)
            else:
                cause = f"qp: {ctrl.status}"
        except Exception as exc:  # noqa: BLE001 - a daemon must keep commanding whatever a controller raises
            a, o, ok, cause = np.zeros(self.n), np.zeros(self.n), False, f"exception: {type(exc).__name__}"
        t_sup = time.perf_counter()
        cmd = sup.apply(t, np.column_stack([a, o]), z, ok=ok, plan=plan, target=href, cause=cause,
                        stretch=stretch, lost=lost, burst=burst)
        if sup.released.any():
            # vented down: the chamber is flat again, its filter restarts from the reading (the factors
            # that took it off its model are not kept), and so does its burst test's sum
            self.bank.reset(z, sup.released)
            if self.burst is not None:
                self.burst.restart(sup.released)
        a, o = cmd[:, 0].copy(), cmd[:, 1].copy()
        ctrl.applied(a, o)
        # the compressor throttled to the planned flows at the estimated pressures (the bank and the
        # NMPC keep working in a: a full-speed inlet duty)
        t_valves = time.perf_counter()
        if self.pwm.active:
            a, o = self.net_vents(a, o, est, W, est["h"] - href)
        Uc = model.valve_inputs(a, o, est["p"], throttle=self.throttle)
        supply = _flow_duty(a, model.topology)
        if self.pwm.active:
            Us = self.pwm.shape_inputs(Uc)
            # the flow at the same speed scales with the inlet's duty: the bank predicts with what is sent
            inlet = Uc[1]
            supply = supply * np.where(inlet > 0.0, Us[1] / np.where(inlet > 0.0, inlet, 1.0), 0.0)
            Uc = Us
        t2 = time.perf_counter()
        self.last_timing = (t2 - t0, t1 - t0, t2 - t1)
        self.last_parts = {"targets": t_ctrl - t1, "controller": t_sup - t_ctrl, "supervisor": t_valves - t_sup,
                           "valves": t2 - t_valves}
        for st, v in zip((self.step_s, self.ekf_s, self.ctrl_s), self.last_timing):
            st.add(v)
        # the bank predicts with the full-speed duty a, not with the throttled speed and inlet sent:
        # they deliver a q(1, p) at the estimated pressure, and in closed loop at the true one within
        # 0.5 %; predicting with the sent inputs (exact, ChamberEKFBank takes them) delayed the
        # release of the cautious cap (the modulus factor's std) on the shared pump (models.bank)
        self._w_prev = np.vstack([supply, Uc[2]])
        self.valve_commands = Uc
        self.decision = (a, o)
        self._sent.append((Uc.copy(), self._w_prev))
        self._k += 1
        return a, o

    def _block(self, key: tuple, build, compile: bool = False) -> FastFunction:
        """The Function ``build()`` on buffers, made once per ``key`` (what it is built from: a setting
        changed after the start builds it again); with ``compile`` as C at the per-step flags."""
        if key not in self._blocks:
            self._blocks[key] = FastFunction(build(), compile, HOT_OPT, HOT_FLAGS)
        return self._blocks[key]

    def _caps(self, W, k, p, k_std, href, lam, lost, refresh: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The NMPC's supply bounds this tick (:func:`~hbma_ctrl.runtime.robot_step.caps_function`, the
        supervisor's vent rule and interlocks by its settings and latches): (a_max, near the limit
        point under the cautious cap, the limit-point pressures kept, Pa), each (n,)."""
        s = self.supervisor.settings
        cautious = None if self.cautious is None else tuple(self.cautious)
        f = self._block(("caps", cautious, s.vent_height, s.stretch_max),
                        lambda: caps_function(self.model, self.n, cautious, s.vent_height, s.stretch_max))
        out = f(W, k, p, k_std, href, lam, lost, self.supervisor.lost, self.supervisor.burst, self._peak_p,
                float(refresh and self.cautious is not None))
        return out[0].copy(), out[1] > 0.5, out[2].copy()

    def net_vents(self, a: np.ndarray, o: np.ndarray, est: dict, W: np.ndarray,
                  excess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a, o) as sent with a minimum valve opening (:func:`~hbma_ctrl.runtime.robot_step.net_vents_function`:
        a short vent netted into the supply, or dropped near the target) at the bank's estimate ``est``,
        loads W (N), heights above the targets ``excess`` (m); the minimum on-time forgets the carried
        duty of a dropped vent."""
        # compiled: its chambers' table look-ups take 90 us a tick for 9 chambers on casadi's virtual
        # machine, 30 us as C
        f = self._block(("net_vents",), lambda: net_vents_function(self.model, self.n, self.pwm.min_duty, self._period),
                        compile=True)
        a, o, carry = f(a, o, est["p"], est["b"], excess, est["x"], W, est["k"], est["c"], self.pwm.carry)
        self.pwm.carry = carry.reshape(2, self.n, order="F").copy()
        return a.copy(), o.copy()

    def prime(self, readings_pa: np.ndarray | None = None) -> None:
        """Start-up work before the first deadline, the loop's state left as it was: the NMPC's solver
        set up and solved once at rest (the bank's starting estimate from ``readings_pa``, Pa, default
        0; the targets of t = 0 moved as the first tick would move them), the valve inputs' Function
        built, the supervisor's Function built for the NMPC's plans and, with a minimum opening, the
        short vents' Function compiled. The first tick then fits its period (without it: 9-12 ms of a
        10 ms period here)."""
        p = np.zeros(self.n) if readings_pa is None else np.nan_to_num(floats_or_nan(readings_pa, self.n))
        a = np.zeros(self.n)
        if self.is_mpc:
            X0 = self.bank.rest_state(p)
            x0, (b, k, c) = self.bank.gas_mass(X0), X0[1:]
            href = self._slew(self.chamber_targets(0.0), np.zeros(self.n), self._period)
            # the vent rule's bounds alone: no interlock holds a chamber at rest
            a_max = self._caps(self.loads, np.ones(self.n), np.zeros(self.n), np.zeros(self.n), href,
                               np.full(self.n, np.nan), np.zeros(self.n), False)[0]
            self.controller.prime(x0, b, self.loads, href, k, c, a_max)
            self.supervisor.prepare(2, self.controller.s.horizon)
            a = np.full(self.n, 0.5 / self.n)  # a supply on every chamber: the throttle's whole path
        self.model.valve_inputs(a, np.zeros(self.n), p, throttle=self.throttle)
        if self.pwm.active:
            # the short vents' Function built (the minimum on-time's carry left as it was)
            carry = self.pwm.carry
            rest = {"p": p, "b": np.ones(self.n), "x": np.zeros(self.n), "k": np.ones(self.n), "c": np.ones(self.n)}
            self.net_vents(np.zeros(self.n), np.zeros(self.n), rest, np.full(self.n, W_FLOOR), np.zeros(self.n))
            self.pwm.carry = carry

    def _slew(self, goal: np.ndarray, h_est: np.ndarray, dt: float) -> np.ndarray:
        """The targets this tick (m, :func:`~hbma_ctrl.runtime.robot_step.slew_function`): ``goal`` when
        there is no rate; otherwise the last ones (the estimated heights at the first tick) moved
        towards it by at most target_rate x dt, a zero target at once."""
        f = self._block(("slew", self.target_rate), lambda: slew_function(self.n, self.target_rate))
        first = self.href is None
        return f(goal, np.zeros(self.n) if first else self.href, h_est, float(first), float(dt))[0].copy()

    def _held_input(self, held: np.ndarray | None) -> np.ndarray:
        """What the bank predicts with for the valve inputs the rig held: those of the newest command
        sent that matches them (to the link's per-mille resolution); the safe command's (no supply,
        the rig's outlets); otherwise the last one, counted in ``held_unmatched``."""
        if held is None:
            return self._w_prev
        h = np.asarray(held, dtype=float)
        for Uc, w in reversed(self._sent):
            if Uc.shape == h.shape and np.allclose(Uc, h, rtol=0.0, atol=HELD_ATOL):
                return w
        if h.shape == (3, self.n) and not np.any(h[0] * h[1] > 0.0):
            return np.vstack([np.zeros(self.n), h[2]])
        self.held_unmatched += 1
        return self._w_prev

    def _plan(self, plan: np.ndarray | None) -> np.ndarray | None:
        """The NMPC's plan (H, n, 2) with a shared pump's budget applied to every row (as to row 0)."""
        if plan is None:
            return None
        p = np.array(plan, dtype=float)
        if self.model.topology == "shared":
            p[:, :, 0] = shared_supply(p[:, :, 0])
        return p

    def stats(self) -> dict:
        """Step, EKF and controller times (ms: median, p99, max, n), fallbacks (failed controller
        steps), interlocks (pressure interlock's supply cuts, per chamber and step), stretch_interlocks
        (the stretch interlock's), lost_estimate_steps (chamber steps vented for a lost estimate),
        cautious steps, QPs not solved, held_unmatched (reports of a held command matching none
        sent lately), bursts (chambers the burst test flagged, indices) and burst_peak_sigma (the
        test's largest sum over the chambers, sigma: its margin to the threshold)."""
        sup = self.supervisor
        ms = lambda st: {k: (v * 1e3 if k != "n" else v) for k, v in st.summary().items()}  # noqa: E731
        return {"step_ms": ms(self.step_s), "ekf_ms": ms(self.ekf_s), "controller_ms": ms(self.ctrl_s),
                "fallbacks": int(sup.failed_steps), "interlocks": int(sup.counts["guard"]),
                "stretch_interlocks": int(sup.counts["stretch_guard"]),
                "lost_estimate_steps": int(sup.counts["lost_estimate"]),
                "vents": int(sup.counts["vent"]), "cautious_steps": int(self.cautious_steps),
                "qp_not_solved": int(self.controller.inaccurate),
                "overruns": int(self.controller.overruns),
                "held_unmatched": int(self.held_unmatched),
                "bursts": [int(i) for i in np.nonzero(sup.burst)[0]],
                "burst_peak_sigma": float(self.burst.peak.max()) if self.burst is not None else 0.0,
                "estimator": self.bank.stats()}
