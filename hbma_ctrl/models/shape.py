"""The one numeric membrane-shape solver of a chamber (SI), used by the simulator, the rig, the
robot statics and the equilibrium tables.

A chamber's shape is the pair (h1, h2): virtual cap height and cut height, m (h = h1 - h2 the
membrane height). Under a dead load W (N) the contact condition ``F(h1, h2) = pi a^2 p = W`` fixes
the shape at every height h; along this constant-load path the gas law ``G(h1, h2) = (p + p_env) V
= m R T`` then picks the height for a gas mass m (the paper's quasi-static model of a ballooning
membrane under a dead load). :meth:`ShapeSolver.contact` is the bisection of the contact condition
at given heights, the one solve every numeric user shares; :meth:`ShapeSolver.free_h1` is the unloaded
case (``h2 = 0``), a scalar Newton on the gas law. The casadi (symbolic) Newton the estimators
differentiate through is :func:`hbma_ctrl.models.reduced.shape_newton`.
"""

from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np

from hbma_ctrl.core import physics as ph

__all__ = ["ShapeSolver", "shape_function", "SHAPE_OUTPUTS"]

#: outputs of :func:`shape_function`, in order
SHAPE_OUTPUTS = ("p", "F", "lam", "V", "G")


@lru_cache(maxsize=8)
def shape_function(space: ph.ParamSpace) -> ca.Function:
    """(h1, h2, theta) -> (p Pa, F N, lam -, V m^3, G J) of the membrane physics, one material family."""
    h1, h2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    theta, P = space.symbols()
    g = ph.geometry(h1, h2, P)
    p = ph.pressure(h1, h2, P)
    return ca.Function("chamber", [h1, h2, theta], [p, ca.pi * g["a2"] * p, g["lam"], g["V"], ph.gas_pv(h1, h2, P)],
                       ["h1", "h2", "theta"], list(SHAPE_OUTPUTS))


@lru_cache(maxsize=64)
def _mapped(fun: ca.Function, n: int) -> ca.Function:
    """fun mapped over n columns (cached: building a map costs more than a small solve)."""
    return fun.map(n)


class ShapeSolver:
    """Vectorised shape solves of one chamber with its parameters bound.

    space : the parameter layout (:class:`hbma_ctrl.core.physics.ParamSpace`); theta : the
    parameter vector, SI (the load entry W is not used: loads are arguments); fun : the membrane law as
    (h1, h2, theta) -> :data:`SHAPE_OUTPUTS` (default the cap's, :func:`shape_function`; the exact
    membrane's is :func:`hbma_ctrl.models.tables.exact_shape_function`, in the same chart).
    """

    def __init__(self, space: ph.ParamSpace, theta: np.ndarray, fun: ca.Function | None = None):
        self.space = space
        self.fun = shape_function(space) if fun is None else fun
        self.theta = np.asarray(theta, dtype=float)
        self._ix = {n: i for i, n in enumerate(space.names)}
        self.r1 = float(self.theta[self._ix["r1"]])

    def eval(self, h1, h2) -> dict:
        """p (Pa), F (N), lam (-), V (m^3), G (J) at shapes (h1, h2) (m), elementwise."""
        h1 = np.atleast_1d(np.asarray(h1, dtype=float))
        h2 = np.broadcast_to(np.asarray(h2, dtype=float), h1.shape)
        n = h1.size
        th = np.repeat(self.theta[:, None], n, 1)
        out = _mapped(self.fun, n)(h1.ravel()[None, :], h2.ravel()[None, :], th)
        return {k: np.asarray(v).reshape(h1.shape) for k, v in zip(SHAPE_OUTPUTS, out)}

    def contact(self, h, W, span: float, grow: int = 0, iters: int = 60, unknown: str = "h2"
                ) -> tuple[np.ndarray, np.ndarray]:
        """Shapes (h1, h2) at membrane heights h (m) with contact force ``F(h1, h2) = W`` (N).

        Bisection (F grows with h2 at fixed h) on the bracket ``h2 in [0, span]`` (m), doubled up
        to ``grow`` times while F at its top is still below W. ``unknown`` names the bisected
        variable: 'h2' (h1 = h + h2) or 'h1' (bracket h1 in [h, h + span], h2 = h1 - h). Both solve
        the same problem; they differ in the last bits of the result (the equilibrium tables bisect h1,
        :mod:`hbma_ctrl.models.tables`).
        """
        h = np.atleast_1d(np.asarray(h, dtype=float))
        W = np.broadcast_to(np.asarray(W, dtype=float), h.shape)
        if unknown == "h2":
            lo, hi = np.zeros(h.shape), np.full(h.shape, span)

            def shape(v):
                return h + v, v
        elif unknown == "h1":
            if grow:
                raise ValueError("ShapeSolver.contact: grow needs unknown='h2'")
            lo, hi = h.copy(), h + span

            def shape(v):
                return v, v - h
        else:
            raise ValueError(f"ShapeSolver.contact: unknown = '{unknown}': allowed h2, h1")
        for _ in range(grow):
            small = self.eval(*shape(hi))["F"] < W
            if not small.any():
                break
            hi = np.where(small, 2 * hi, hi)
        for _ in range(iters):
            mid = 0.5 * (lo + hi)
            big = self.eval(*shape(mid))["F"] > W
            hi, lo = np.where(big, mid, hi), np.where(big, lo, mid)
        return shape(0.5 * (lo + hi))

    def h2_for_force(self, h, F) -> np.ndarray:
        """Cut height h2 (m) with contact force F (N, > 0) at membrane height h (m > 0)."""
        return self.contact(h, F, self.r1, grow=40)[1]

    def free_h1(self, G: float, h0: float, iters: int = 60) -> float:
        """Free-inflation cap height h1 (m, h2 = 0) holding ``G = m R T`` (J), Newton from h0 (m)."""
        p_env = float(self.theta[self._ix["p_env"]])
        h = max(h0, 1e-4)
        pi_r1 = np.pi * self.r1 ** 2
        for _ in range(iters):
            y = self.eval(h, 0.0)
            g = (float(y["p"][0]) + p_env) * float(y["V"][0])
            # dG/dh1 >= p_env dV/dh1 = p_env pi (r1^2 + h^2) / 2: a slope that never overshoots
            dG = p_env * 0.5 * (pi_r1 + np.pi * h * h) + 1e-12
            hn = max(h - (g - G) / dG, 0.0)
            if abs(hn - h) < 1e-12:
                break
            h = hn
        return h

    def h_for_stretch(self, lam: float, F) -> np.ndarray:
        """Membrane height (m) at stretch lam (-) under contact force F (N; fixed point on h2)."""
        F = np.atleast_1d(np.asarray(F, dtype=float))
        r1 = self.r1
        h2 = np.zeros(F.shape)
        for _ in range(30):
            # lam^2 r1^2 = h1^2 + r1^2 - h2^2 with h1 = h + h2
            h = -h2 + np.sqrt(h2**2 + r1**2 * (lam**2 - 1))
            new = np.where(F > 0, self.h2_for_force(h, np.maximum(F, 1e-12)), 0.0)
            if np.max(np.abs(new - h2)) < 1e-12:
                h2 = new
                break
            h2 = new
        return -h2 + np.sqrt(h2**2 + r1**2 * (lam**2 - 1))

    def load_path(self, F: float, h_hi: float, n: int = 600) -> dict:
        """Shape and state (:data:`SHAPE_OUTPUTS`, h, h1, h2) along the constant-load path h in
        (0, h_hi] (m) at contact force F >= 0 (N)."""
        h = np.linspace(h_hi / n, h_hi, n)
        h2 = self.h2_for_force(h, F) if F > 0 else np.zeros(n)
        out = self.eval(h + h2, h2)
        out.update(h=h, h1=h + h2, h2=h2)
        return out
