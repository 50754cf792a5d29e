"""The simulated rig's plant over one sample period as ONE casadi Function (generates C).

:class:`hbma_ctrl.sim.rig.Rig` advances its :class:`~hbma_ctrl.sim.simulate.Plant` by ``nsub`` fixed
steps per sample period (the fidelity's :meth:`~hbma_ctrl.models.fidelity.Fidelity.step_function`:
euler/rk4 stages, projection, outputs) and handles the hybrid events between the steps in numpy.
For the ``free`` and ``platform`` fidelities every event is a test on the state, so the whole period is
expressible as a casadi Function:

    plant_step(x[nx], mode[1], u[3], theta[ntheta]) -> (x_next[nx], mode_next[1], y[13])

``x`` the fidelity's state (SI), ``mode`` 0 resting / 1 moving, ``u`` = [speed, inlet, outlet] held
over the period (0-1), ``theta`` the parameter vector (:class:`hbma_ctrl.core.physics.ParamSpace`), ``y``
the outputs :data:`hbma_ctrl.models.fidelity.OUTPUTS` at the end of the period. After each internal step:
lift-off (resting and pi r1^2 p > W: start from the flat membrane, project in contact), touch-down
(platform: moving with z <= 0 and v <= 0: z = v = 0, resting), as ``_events_and_modes`` does.

The rig's membrane law (the cap or the exact membrane's tables, piecewise cubics in casadi) and its
pump map (tilted or not: another CSV) are inside the fidelity, so they generate as they are. The rig's
structure around the plant is two more Functions, so that a loop without Python has it too:

    valve_line(u[3], hist[3 keep]) -> (u_sub[3 x nsub], hist_next[3 keep])
    sensor_lag(p_sensed[1], p_prev[1], y[13]) -> (p_sensed_next[1], p_prev_next[1])

``valve_line`` is :class:`hbma_ctrl.sim.rig.ValveLine`: the command shaped for the valves' minimum
on-time and kept with the last ones sent, and the inputs acting over each internal step (the valves as
sent ``valve_delay`` before it, the speed as sent last); ``plant_step_function(..., per_substep=True)``
takes those inputs, one column per internal step. ``sensor_lag`` is
:meth:`~hbma_ctrl.sim.rig.RigSettings.sense` once per period. Refused (:func:`plant_step_support`
says which key): the quasi-static snap-through (a search for the far branch).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hbma_ctrl.models.fidelity import MODE_MOVING, MODE_REST, OUTPUTS, Fidelity

__all__ = ["plant_step_function", "plant_step_support", "initial_plant_state", "PLANT_FIDELITIES",
           "valve_line_function", "valve_history_size", "sensor_lag_function"]

#: fidelities whose period step is one casadi Function
PLANT_FIDELITIES = ("free", "platform")


def plant_step_support(fidelity: str, settings) -> str | None:
    """Why a rig (its fidelity name and :class:`~hbma_ctrl.sim.rig.RigSettings`) has no plant_step
    Function, naming the scenario key; None when it has one. Every membrane law, pump map, valve timing
    and sensor lag generates (the module docstring); only the quasi-static snap-through does not."""
    if fidelity not in PLANT_FIDELITIES:
        return (f"[rig] fidelity = '{fidelity}': its snap-through jump is a search, not a casadi expression "
                f"(codegen supports {', '.join(PLANT_FIDELITIES)})")
    return None


def _events(fid: Fidelity, x, u, theta, mode):
    """Lift-off and touch-down after one internal step: (x, mode) as ``_events_and_modes`` leaves them."""
    if fid.name == "free":
        return x, mode
    names = fid.space.names
    r1, W = theta[names.index("r1")], theta[names.index("W")]
    p = fid.out(x, u, theta, mode)[OUTPUTS.index("p")]
    # same operation order as the numpy path: (pi * r1**2) * p > W
    lift = ca.logic_and(mode == MODE_REST, (math.pi * (r1 * r1)) * p > W)
    if fid.name == "platform":
        down = ca.logic_and(ca.logic_and(mode == MODE_MOVING, x[2] <= 0), x[3] <= 0)
    else:  # pragma: no cover - quasi_static is refused by plant_step_support
        down = ca.logic_and(mode == MODE_MOVING, x[1] - x[2] <= 0)
    new_mode = ca.if_else(lift, MODE_MOVING, ca.if_else(down, MODE_REST, mode))
    x_down = ca.vertcat(x[0], x[1], 0, 0) if fid.name == "platform" else x
    # leaving rest: start from the flat membrane that carries the current pressure, then project in contact
    x_lift = fid.project(fid.project(x, theta, MODE_REST), theta, new_mode)
    x_touch = fid.project(x_down, theta, new_mode)
    return ca.if_else(lift, x_lift, ca.if_else(down, x_touch, x)), new_mode


def plant_step_function(fid: Fidelity, integrator: str, dt: float, nsub: int,
                        name: str = "plant_step", per_substep: bool = False) -> ca.Function:
    """``nsub`` internal steps of ``dt`` s (``integrator`` 'rk4' or 'euler') of the fidelity, with its
    events, as one Function (see the module docstring for the signature). ``per_substep``: its input
    ``u`` is 3 x nsub, the inputs acting over each internal step (the valves' delay, ``valve_line``);
    else one command held over the period."""
    if fid.name not in PLANT_FIDELITIES:
        raise ValueError(f"plant_step: fidelity '{fid.name}' is not supported; allowed: {', '.join(PLANT_FIDELITIES)}")
    if not (isinstance(nsub, int) and nsub >= 1):
        raise ValueError(f"plant_step: nsub = {nsub!r} must be an integer >= 1")
    step = fid.step_function(integrator, dt)
    xs, us, ths, ms = (ca.SX.sym("x", fid.nx), ca.SX.sym("u", 3), ca.SX.sym("theta", fid.space.size),
                       ca.SX.sym("mode"))
    xn = step(xs, us, ths, ms)[0]
    xe, me = _events(fid, xn, us, ths, ms)
    sub = ca.Function(f"{name}_sub", [xs, us, ths, ms], [xe, me], ["x", "u", "theta", "mode"], ["x_next", "mode_next"])
    # MX around the substep: the generated C calls it nsub times instead of inlining nsub copies
    x, mode, theta = ca.MX.sym("x", fid.nx), ca.MX.sym("mode"), ca.MX.sym("theta", fid.space.size)
    u = ca.MX.sym("u", 3, nsub) if per_substep else ca.MX.sym("u", 3)
    xk, mk = x, mode
    for j in range(nsub):
        xk, mk = sub(xk, u[:, j] if per_substep else u, theta, mk)
    # the outputs with the inputs of the last internal step, as the rig's plant computes them
    y = fid.out(xk, u[:, nsub - 1] if per_substep else u, theta, mk)
    return ca.Function(name, [x, mode, u, theta], [xk, mk, y], ["x", "mode", "u", "theta"],
                       ["x_next", "mode_next", "y"])


def valve_history_size(settings) -> int:
    """Commands :func:`valve_line_function` keeps (the ones sent within ``valve_delay`` of now, and the
    one acting before them)."""
    return int(math.ceil(settings.valve_delay / settings.sample_period)) + 1


def valve_line_function(settings, nsub: int, name: str = "valve_line") -> ca.Function:
    """:class:`hbma_ctrl.sim.rig.ValveLine` of rig settings ``settings`` over one period of ``nsub``
    internal steps, as a Function (module docstring): the command sent now is shaped
    (:meth:`~hbma_ctrl.sim.rig.RigSettings.valve_duty`) and appended to ``hist`` (oldest first;
    zeros before any command: shut valves); internal step j's valves are the newest command sent at least
    ``valve_delay`` before it, its speed the one sent now."""
    T, delay = float(settings.sample_period), float(settings.valve_delay)
    dt = T / nsub
    n = valve_history_size(settings)
    u, hist = ca.SX.sym("u", 3), ca.SX.sym("hist", 3, n)
    shaped = [u[0], settings.valve_duty(u[1]), settings.valve_duty(u[2])]
    sent = ca.horzcat(hist[:, 1:], ca.vertcat(*shaped))  # column n - 1 is now, n - 1 - i was sent i periods ago
    cols = []
    for j in range(nsub):
        # ValveLine.at(t + j dt): the last command with t - i T <= t + j dt - delay (+1e-12), i.e. the
        # smallest such i (at most n - 1: the history reaches back past the delay); the rig's clock adds
        # the same 1e-12 slack
        i = next(i for i in range(n) if -i * T <= j * dt - delay + 1e-12)
        cols.append(ca.vertcat(shaped[0], sent[1:, n - 1 - i]))
    return ca.Function(name, [u, hist], [ca.horzcat(*cols), sent], ["u", "hist"], ["u_sub", "hist_next"])


def sensor_lag_function(settings, name: str = "sensor_lag") -> ca.Function:
    """:meth:`hbma_ctrl.sim.rig.RigSettings.sense` over one period as a Function: the lagged reading
    ``p_sensed`` and the last true pressure ``p_prev`` (Pa) after a period that ends at the outputs
    ``y`` (:data:`hbma_ctrl.models.fidelity.OUTPUTS`): ``sense`` itself on casadi symbols, so it rounds
    as the rig does."""
    ys, prev, sensed = ca.SX.sym("y", len(OUTPUTS)), ca.SX.sym("p_prev"), ca.SX.sym("p_sensed")
    p_now = ys[OUTPUTS.index("p")]
    nxt = settings.sense(sensed, prev, p_now)
    return ca.Function(name, [sensed, prev, ys], [nxt, p_now], ["p_sensed", "p_prev", "y"],
                       ["p_sensed_next", "p_prev_next"])


def initial_plant_state(fid: Fidelity, theta: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The rig's state at t = 0 (unpressurised, at rest), its mode and outputs with the inputs off."""
    x0, m0 = fid.initial_state(theta)
    y0 = np.asarray(fid.out(x0, np.zeros(3), theta, m0)).ravel()
    return np.asarray(x0, dtype=float), float(m0), y0
