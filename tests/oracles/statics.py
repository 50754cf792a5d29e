"""The robot's statics for given gas masses and the glued chambers' pressures for a pose, in numpy:
oracles that invert the product's statics (:func:`hbma_ctrl.robot.statics.chamber_states`,
:func:`hbma_ctrl.robot.statics.load_sharing`, :class:`hbma_ctrl.robot.statics.BondedChamber`)."""

from __future__ import annotations

import math
from functools import lru_cache

import casadi as ca
import numpy as np

from hbma_ctrl.core import physics as ph
from hbma_ctrl.models.fidelity import shape_jacobian
from hbma_ctrl.models.shape import ShapeSolver
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.kinematics import _heights_array
from hbma_ctrl.robot.statics import BOND_RADIUS, bonded_chamber, chamber_solver, chamber_states, load_sharing


@lru_cache(maxsize=8)
def _gf_function(space: ph.ParamSpace) -> ca.Function:
    """(h1, h2, theta) -> (G, F, d(G, F)/d(h1, h2))."""
    h1, h2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    theta, P = space.symbols()
    G, F, J = shape_jacobian(h1, h2, P)
    return ca.Function("gf", [h1, h2, theta], [G, F, J], ["h1", "h2", "theta"], ["G", "F", "J"])


def newton(ch: ShapeSolver, h1, h2, G, F, iters: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Newton on (h1, h2) (m) of ``ch`` for ``G(h1, h2) = G`` (J) and ``F(h1, h2) = F`` (N) from a nearby guess.

    Keeps 0 <= h2 <= h1 and halves a step that would leave the chart; the guess picks the branch.
    """
    h1, h2 = np.array(h1, dtype=float), np.array(h2, dtype=float)
    n = h1.size
    fun = _gf_function(ch.space).map(n)
    th = np.repeat(ch.theta[:, None], n, 1)
    for _ in range(iters):
        Gv, Fv, J = (np.asarray(x) for x in fun(h1[None, :], h2[None, :], th))
        J = J.reshape(2, n, 2).transpose(0, 2, 1)  # mapped 2x2 blocks side by side -> [row, col, chamber]
        r0, r1 = Gv.ravel() - G, Fv.ravel() - F
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        d1 = (J[1, 1] * r0 - J[0, 1] * r1) / det
        d2 = (-J[1, 0] * r0 + J[0, 0] * r1) / det
        step = np.ones(n)
        for _k in range(30):  # stay in the chart
            n1, n2 = h1 - step * d1, h2 - step * d2
            bad = (n2 < 0) | (n1 - n2 < 0)
            if not bad.any():
                break
            step = np.where(bad, step / 2, step)
        h1, h2 = h1 - step * d1, np.maximum(h2 - step * d2, 0.0)
        if np.all(np.abs(d1) < 1e-13) and np.all(np.abs(d2) < 1e-13):
            break
    return h1, h2


def chamber_states_from_masses(design: RobotDesign, masses, tip_force=(0.0, 0.0, 0.0),
                               tip_moment=(0.0, 0.0, 0.0), iters: int = 40, tol: float = 1e-9) -> dict:
    """Static equilibrium of the robot for given gas masses (N x 3 or 3N, kg).

    For every chamber the constant-load path h -> (h1, h2) with F(h1, h2) = its load share is
    searched for G(h1, h2) = m R T (G = (p + p_env) V, the gas law, README Model §4); the loads follow from the heights
    by :func:`load_sharing`, iterated to a fixed point. A chamber whose gas cannot lift its share
    rests (h = 0). Along the load path G grows with h for the robot's chambers (no fold: the gas
    is compressible, which is why the far branch is stable at fixed mass), so the height is unique;
    where G is not monotone the lowest crossing is taken and ``ambiguous`` is flagged. Returns
    :func:`chamber_states` of the heights plus ``heights`` and ``ambiguous`` (N, 3).
    """
    N = design.n_layers
    m = np.asarray(masses, dtype=float)
    if m.size != 3 * N or not np.all(np.isfinite(m)) or m.min() <= 0:
        raise ValueError(f"masses: need {3 * N} finite gas masses > 0 kg")
    m = m.ravel()
    act = design.chamber
    ch = chamber_solver(act)
    rt = act.R * act.T
    lam_hi = min(1.5 * design.max_stretch, act.material.lam_max() * 0.999)
    h_hi = float(ch.h_for_stretch(lam_hi, 0.0)[0])
    n = 3 * N
    h1, h2 = np.zeros(n), np.zeros(n)
    active = np.zeros(n, dtype=bool)
    amb = np.zeros(n, dtype=bool)
    h = np.zeros(n)
    for _ in range(iters):
        F = np.maximum(load_sharing(design, h.reshape(N, 3), tip_force, tip_moment).forces.ravel(), 0.0)
        G_rest = (F / (math.pi * act.r1**2) + act.p_env) * act.V0
        act_now = m * rt > G_rest
        for i in np.nonzero(act_now & ~active)[0]:  # a coarse walk along the load path: the initial guess
            path = ch.load_path(F[i], h_hi, 120)
            G = path["G"] - m[i] * rt
            cross = np.nonzero((G[:-1] < 0) & (G[1:] >= 0))[0]
            if G[0] >= 0:
                cross = np.append([0], cross)
            if cross.size == 0:
                raise ValueError(f"masses: chamber {design.names[i]} holds more gas than the stretch "
                                 f"{lam_hi:g} allows")
            amb[i] = cross.size > 1 or bool(np.any(np.diff(path["G"]) <= 0))
            j = int(cross[0])
            h1[i], h2[i] = path["h1"][j + 1], path["h2"][j + 1]
        active = act_now
        if active.any():
            h1[active], h2[active] = newton(ch, h1[active], h2[active], m[active] * rt, F[active])
        h1[~active], h2[~active] = 0.0, 0.0
        new = h1 - h2
        done = np.max(np.abs(new - h)) < tol
        h = new
        if done:
            break
    h = h.reshape(N, 3)
    amb = amb.reshape(N, 3)
    out = chamber_states(design, h, tip_force, tip_moment)
    out["heights"] = h
    out["ambiguous"] = amb
    return out


def bonded_chamber_states(design: RobotDesign, heights, c: float = BOND_RADIUS, tip_force=(0.0, 0.0, 0.0),
                          tip_moment=(0.0, 0.0, 0.0)) -> dict:
    """Each glued chamber's pressure for chamber heights (N x 3, m), tension allowed.

    The load sharing (:func:`load_sharing`) gives each chamber's force F (N, negative = the glue pulls
    the layer down); the bonded table gives the pressure p (Pa) at which the glued membrane at its
    height pushes (or pulls) with exactly F. Returns (N, 3) arrays F, p (NaN where the table has no
    such state: ``beyond``) and ``tension`` (F < 0), ``beyond`` (bool).
    """
    h = _heights_array(design, heights)
    F = load_sharing(design, h, tip_force, tip_moment).forces
    ch = bonded_chamber(design.chamber, c)
    p = np.array([[ch.pressure(h[k, i], F[k, i]) for i in range(3)] for k in range(h.shape[0])])
    return {"F": F, "p": p, "tension": F < 0, "beyond": ~np.isfinite(p)}
