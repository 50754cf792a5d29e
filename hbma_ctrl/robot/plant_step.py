"""The robot rig over one sample period as ONE casadi Function (SI), a building block of a generated robot loop.

:class:`hbma_ctrl.robot.rig.RobotRig` advances every chamber's plant as one batch, with the valves'
delay and minimum opening (:class:`hbma_ctrl.sim.rig.ValveLine`), a shared pump's manifold, each
sensor's lag, and at the end of the period every chamber's load from the robot's load sharing of the
true heights. Each part is a casadi expression here, so the whole period is one Function:

    robot_rig_step(X[nx x n], mode[1 x n], U[3 x n], hist[3 keep x n], theta[ntheta x n],
                   p_sensed[1 x n], p_prev[1 x n], f_tip[3])
        -> (X_next, mode_next, y[13 x n], hist_next, theta_next, p_sensed_next, p_prev_next, F[1 x n])

``U`` is the command sent for the period (speed, inlet, outlet per chamber, 0-1), ``hist`` each
chamber's valve history (:func:`hbma_ctrl.sim.plant_step.valve_line_function`; one command when the
rig has no valve delay), ``y`` the outputs :data:`hbma_ctrl.models.fidelity.OUTPUTS` at the end of
the period (before the loads change), ``theta_next`` the parameters with each chamber's load ``W``
(and, for the ``platform`` fidelity, its moving mass ``M``) from the load sharing, ``F`` the shared
normal forces themselves (N; negative = tension, floored at :data:`hbma_ctrl.robot.plant.W_FLOOR` in W).

:func:`load_sharing_function` is :func:`hbma_ctrl.robot.statics.load_sharing` (with the forward
kinematics it needs) as a Function of the chamber heights and the tip load. Its rotation is the same
twist-free one written without the bend angle's trig (smooth through a level layer), so it agrees with
the numpy path to rounding, not bit for bit.

Not here: the sensors' noise and saturation (drawn outside, as the chamber loop's ``sensor`` stage
does) and the tip load's schedule (an input).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.models.fidelity import OUTPUTS
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.plant import W_FLOOR
from hbma_ctrl.robot.rig import M_MIN
from hbma_ctrl.sim.plant_step import (
    plant_step_function,
    plant_step_support,
    sensor_lag_function,
    valve_history_size,
    valve_line_function,
)

__all__ = ["load_sharing_function", "robot_rig_step_function"]


def _rotation(a, b):
    """Twist-free rotation (3 x 3 SX) mapping z onto the normal of the plane h = c + a x + b y: the
    rotation of :func:`hbma_ctrl.robot.kinematics._rots` about (-sin psi, cos psi, 0) by the bend
    theta = atan(hypot(a, b)), psi = atan2(-b, -a), with sin and cos of theta and psi taken from a, b."""
    t2 = a * a + b * b
    r = ca.sqrt(1 + t2)
    s1 = 1 / r  # sin(theta) / t with t = tan(theta): K's entries times sin(theta) are -a / r, -b / r
    g = 1 / (r * (r + 1))  # (1 - cos(theta)) / t^2: K^2's entries times (1 - cos(theta))
    # K = [[0, 0, cp], [0, 0, sp], [-cp, -sp, 0]], cp = -a / t, sp = -b / t
    K1 = ca.vertcat(ca.horzcat(0, 0, -a * s1), ca.horzcat(0, 0, -b * s1), ca.horzcat(a * s1, b * s1, 0))
    K2 = ca.vertcat(ca.horzcat(-a * a * g, -a * b * g, 0), ca.horzcat(-a * b * g, -b * b * g, 0),
                    ca.horzcat(0, 0, -t2 * g))
    return ca.SX.eye(3) + K1 + K2


def load_sharing_function(design: RobotDesign, name: str = "load_sharing") -> ca.Function:
    """``(h[3N], f_tip[3], m_tip[3]) -> (F[3N], tip[3])``: every chamber's normal force (N, negative =
    tension) from the weights of the bodies above and the tip load (force N, moment N m, world frame)
    for chamber heights h (m, layer by layer, >= 0), and the tip position (m); the equations of
    :func:`hbma_ctrl.robot.statics.load_sharing`."""
    design.validate()
    N, L = design.n_layers, design.layer_thickness
    xy = design.chamber_xy()
    Minv = np.linalg.inv(np.column_stack([np.ones(3), xy]))  # h_i = c + a x_i + b y_i
    h, f_tip, m_tip = ca.SX.sym("h", 3 * N), ca.SX.sym("f_tip", 3), ca.SX.sym("m_tip", 3)
    Rw, Ow = ca.SX.eye(3), ca.SX.zeros(3, 1)  # frame k in the world
    frames, contacts = [], []
    for k in range(N):
        hk = h[3 * k:3 * k + 3]
        c, a, b = (ca.mtimes(ca.DM(Minv[i:i + 1, :]), hk) for i in range(3))
        local = [ca.vertcat(float(xy[i, 0]), float(xy[i, 1]), L + hk[i]) for i in range(3)]
        contacts.append([ca.mtimes(Rw, p) + Ow for p in local])
        Rk, Ok = _rotation(a, b), ca.vertcat(0, 0, L + c)
        Ow = ca.mtimes(Rw, Ok) + Ow
        Rw = ca.mtimes(Rw, Rk)
        frames.append((Rw, Ow))  # frame k + 1
    R_top, O_top = frames[-1]
    tip = R_top[:, 2] * L + O_top
    grav = ca.DM([0.0, 0.0, -design.g])
    masses = design.body_masses
    w = [float(masses[k]) * grav for k in range(N)]
    com = [frames[k][0][:, 2] * (L / 2) + frames[k][1] for k in range(N)]
    forces = []
    for k in range(N):  # chamber layer k carries bodies k + 1..N (frames k..N-1 here)
        R, O = frames[k]
        f = f_tip + sum(w[k:], ca.DM.zeros(3, 1))
        M = m_tip + ca.cross(tip - O, f_tip)
        for j in range(k, N):
            M = M + ca.cross(com[j] - O, w[j])
        fl, Ml = ca.mtimes(R.T, f), ca.mtimes(R.T, M)
        pts = [ca.mtimes(R.T, p - O) for p in contacts[k]]  # contacts in frame k + 1 (z ~ 0)
        A = ca.vertcat(ca.horzcat(1, 1, 1), ca.horzcat(*[p[1] for p in pts]), ca.horzcat(*[p[0] for p in pts]))
        forces.append(ca.solve(A, ca.vertcat(-fl[2], -Ml[0], Ml[1])))
    return ca.Function(name, [h, f_tip, m_tip], [ca.vertcat(*forces), tip], ["h", "f_tip", "m_tip"], ["F", "tip"])


def robot_rig_step_function(rig, name: str = "robot_rig_step") -> ca.Function:
    """One sample period of a :class:`hbma_ctrl.robot.rig.RobotRig` as a Function (module docstring):
    its fidelity, internal step, valve timing, sensor lag, topology and design. ValueError naming the
    key when its plant's period is not one casadi Function."""
    fid = rig.plant.fid
    timing = rig._timing
    why = plant_step_support(fid.name, timing)
    if why:
        raise ValueError(f"robot codegen: {why}")
    n, T, dt = rig.n, timing.sample_period, rig.plant.dt
    nsub = max(1, int(round(T / dt)))
    names = fid.space.names
    iW, iM = names.index("W"), (names.index("M") if fid.name == "platform" else None)
    iH = OUTPUTS.index("h")
    sub = plant_step_function(fid, "rk4", dt, 1, name=f"{name}_sub").map(n)
    sense = sensor_lag_function(timing, name=f"{name}_sense").map(n)
    keep = valve_history_size(timing)
    X, mode = ca.MX.sym("X", fid.nx, n), ca.MX.sym("mode", 1, n)
    U, hist = ca.MX.sym("U", 3, n), ca.MX.sym("hist", 3 * keep, n)
    theta, p_sensed, p_prev = ca.MX.sym("theta", fid.space.size, n), ca.MX.sym("p_sensed", 1, n), ca.MX.sym("p_prev", 1, n)
    f_tip = ca.MX.sym("f_tip", 3)
    line = valve_line_function(timing, nsub, name=f"{name}_valves").map(n)
    u_sub, hist_next = line(U, ca.reshape(hist, 3, keep * n))
    hist_next = ca.reshape(hist_next, 3 * keep, n)
    cols = [u_sub[:, j::nsub] for j in range(nsub)]  # internal step j's inputs, 3 x n
    Xk, mk = X, mode
    for j in range(nsub):
        Uj = cols[j]
        if rig.topology == "shared":
            tot = ca.sum2(Uj[1, :])
            Uj = ca.vertcat(Uj[0, :], ca.if_else(tot > 1.0, Uj[1, :] / tot, Uj[1, :]), Uj[2, :])
        Xk, mk, y = sub(Xk, mk, Uj, theta)
    ps_next, pp_next = sense(p_sensed, p_prev, y)
    share = load_sharing_function(rig.design, name=f"{name}_loads")
    h = ca.fmax(y[iH, :], 0.0)
    F = share(h.T, f_tip, ca.DM.zeros(3))[0].T
    W = ca.fmax(F, W_FLOOR)
    rows = [theta[i, :] for i in range(fid.space.size)]
    rows[iW] = W
    if iM is not None:
        # the moving mass each chamber carries, as RobotRig._update_loads sets it
        rows[iM] = ca.fmax(W / rig.design_g, M_MIN)
    theta_next = ca.vertcat(*rows)
    return ca.Function(name, [X, mode, U, hist, theta, p_sensed, p_prev, f_tip],
                       [Xk, mk, y, hist_next, theta_next, ps_next, pp_next, F],
                       ["X", "mode", "U", "hist", "theta", "p_sensed", "p_prev", "f_tip"],
                       ["X_next", "mode_next", "y", "hist_next", "theta_next", "p_sensed_next", "p_prev_next", "F"])
