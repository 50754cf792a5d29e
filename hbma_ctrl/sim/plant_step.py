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

Refused (:func:`plant_step_support` says which key): the quasi-static snap-through (a search for the
far branch), the exact membrane (its law is a table the rig builds at run time), valve delay and minimum
on-time (a command history), the sensor lag and the tilted pump map.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hbma_ctrl.models.fidelity import MODE_MOVING, MODE_REST, OUTPUTS, Fidelity

__all__ = ["plant_step_function", "plant_step_support", "initial_plant_state", "PLANT_FIDELITIES"]

#: fidelities whose period step is one casadi Function
PLANT_FIDELITIES = ("free", "platform")


def plant_step_support(fidelity: str, settings) -> str | None:
    """Why a rig (its fidelity name and :class:`~hbma_ctrl.sim.rig.RigSettings`) has no plant_step
    Function: every reason, each naming the scenario key (its value as the user writes it, since the
    rig's defaults set several of them), joined by '; '; None when it has one."""
    why = []
    if fidelity not in PLANT_FIDELITIES:
        why.append(f"[rig] fidelity = '{fidelity}': its snap-through jump is a search, not a casadi expression "
                   f"(codegen supports {', '.join(PLANT_FIDELITIES)})")
    if getattr(settings, "membrane", "cap") != "cap":
        why.append(f"[rig] membrane = '{settings.membrane}': codegen supports 'cap'")
    for key, unit in (("valve_delay", "ms"), ("valve_min_on", "ms"), ("sensor_tau", "ms")):
        if getattr(settings, key, 0.0) != 0.0:
            why.append(f"[rig] {key}_{unit} = {getattr(settings, key) * 1e3:g} {unit}: codegen supports 0 {unit} only")
    if getattr(settings, "compressor_tilt", 0.0) != 0.0:
        why.append(f"[rig] compressor_tilt = {settings.compressor_tilt:g}: codegen supports 0 only")
    return "; ".join(why) or None


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
                        name: str = "plant_step") -> ca.Function:
    """``nsub`` internal steps of ``dt`` s (``integrator`` 'rk4' or 'euler') of the fidelity, with its
    events, as one Function (see the module docstring for the signature)."""
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
    x, mode, u, theta = (ca.MX.sym("x", fid.nx), ca.MX.sym("mode"), ca.MX.sym("u", 3),
                         ca.MX.sym("theta", fid.space.size))
    xk, mk = x, mode
    for _ in range(nsub):
        xk, mk = sub(xk, u, theta, mk)
    y = fid.out(xk, u, theta, mk)
    return ca.Function(name, [x, mode, u, theta], [xk, mk, y], ["x", "mode", "u", "theta"],
                       ["x_next", "mode_next", "y"])


def initial_plant_state(fid: Fidelity, theta: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The rig's state at t = 0 (unpressurised, at rest), its mode and outputs with the inputs off."""
    x0, m0 = fid.initial_state(theta)
    y0 = np.asarray(fid.out(x0, np.zeros(3), theta, m0)).ravel()
    return np.asarray(x0, dtype=float), float(m0), y0
