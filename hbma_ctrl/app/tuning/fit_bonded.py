"""The law of ``hbma-ctrl fit --contact bonded``: static points of a chamber whose membrane centre is glued
to a rigid disk of radius c, as a lift rig's or the robot's layers are (SI inside).

The exact membrane bonded to the disk (docs/concepts/model.md §9) pushes the disk with F(h, p) at centre
height h and gauge pressure p; :func:`hbma_ctrl.robot.statics.bonded_table` solves it over a grid, once
per geometry (r1, t0), disk radius and material, cached on disk like the exact membrane's other tables.
For ``nh`` every tension is proportional to the modulus E, so the table at the default modulus E0
serves every E: ``F(h, p; E) = s F0(h, p / s)`` with ``s = E / E0``, and the model pressure of a data
point (h, F) is ``p = s P0(h, F / s)``, P0 the table's inverse at fixed height.

The grid (:data:`GRID_X`, :data:`GRID_P`) is in the annulus's own scales: heights over its width
``w = r1 - c`` and pressures over ``mu0 t0 / w`` (mu0 the default shear modulus; a narrower annulus
holds a higher pressure), out to past the solver's reach (NaN there: a meridian stretch above 4 or a
slack membrane). Pressures are spaced evenly in their square root: near p = 0 the annulus bulges like
p^(1/3) (small deflection), so F is least smooth there. Interpolation: along each pressure column a cubic
spline of F over the height nodes (continued to h = 0 below the first one), then at each data height a
cubic spline of p over the columns' forces, which grow with p. Against the exact solver itself (at twice
the discretisation) it misses the pressure by about 1e-5 of it, 1e-4 at the edge of the solver's reach.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import make_material
from hbma_ctrl.core.params import Actuator
from hbma_ctrl.models.exact import ExactMembrane

__all__ = ["GRID_X", "GRID_P", "bonded_grid", "BondedLaw"]

#: table heights over the annulus width r1 - c (a meridian stretch of 4 ends the reach below 3.9)
GRID_X = np.concatenate([[0.01, 0.05], np.arange(0.1, 4.001, 0.1)])
#: table pressures over mu0 t0 / (r1 - c), even in their square root
GRID_P = 4.0 * np.linspace(0.0, 1.0, 26) ** 2


def bonded_grid(r1: float, t0: float, c: float) -> tuple[np.ndarray, np.ndarray]:
    """The table's heights (m) and pressures (Pa, at the default nh modulus) for clamp radius r1, thickness
    t0 and disk radius c (m)."""
    w = r1 - c
    mu0 = ExactMembrane(make_material("nh"), r1, t0, "bonded", c).mu
    return GRID_X * w, GRID_P * mu0 * t0 / w


class BondedLaw:
    """Model pressures (Pa) of static points (heights h m, forces F N on the disk) of an nh membrane glued
    to a disk of radius c (m), clamp radius r1, thickness t0 (m), for any modulus E (Pa); ``cache``: the
    tables' directory (None: the exact tables' one)."""

    def __init__(self, r1: float, t0: float, c: float, h: np.ndarray, F: np.ndarray, cache=None):
        from hbma_ctrl.robot.statics import bonded_table

        mat0 = make_material("nh")
        self.E0, self.r1, self.c = float(mat0.E), r1, c
        self.h, self.F = np.asarray(h, dtype=float), np.asarray(F, dtype=float)
        hg, pg = bonded_grid(r1, t0, c)
        tab = bonded_table(Actuator(r1=r1, t0=t0, material=mat0), c, cache, h=hg, p=pg)
        self.build_s, self.path = float(tab["build_s"]), tab["path"]
        # F0 of every column at the data heights, continued one node spacing past its last solved height
        # (NaN beyond): a point at the solver's reach between two nodes stays a value, not a penalty
        G = np.full((self.h.size, pg.size), np.nan)
        for j in range(pg.size):
            ok = np.isfinite(tab["F"][:, j])
            if ok.sum() >= 4:
                hs = hg[ok]
                inside = self.h <= hs[-1] + (hs[-1] - hs[-2])
                G[inside, j] = CubicSpline(hs, tab["F"][ok, j])(self.h[inside])
        # each point's inverse p0(F) over the columns it reaches with F growing, continued one spacing
        # of F either side (below: the pressure a force under the vented membrane's would need); past
        # that, a straight line with the end segments' slopes: a point beyond the reach then pulls the
        # fit no harder than its miss, instead of a penalty the modulus would be moved to escape
        self._inv = []
        for row in G:
            n = 0
            while n < row.size and np.isfinite(row[n]) and (n == 0 or row[n] > row[n - 1]):
                n += 1
            if n >= 4:
                f, q = row[:n], pg[:n]
                lo, hi = 2 * f[0] - f[1], 2 * f[-1] - f[-2]
                cs = CubicSpline(f, q)
                self._inv.append((cs, lo, hi, float(cs(lo)), float(cs(hi)), (q[1] - q[0]) / (f[1] - f[0]),
                                  (q[-1] - q[-2]) / (f[-1] - f[-2])))
            else:
                self._inv.append(None)

    def pressure(self, values: np.ndarray) -> np.ndarray:
        """Model pressures (Pa) at the data points for ``values`` = [E] (Pa); beyond the table's forces at
        a point's height continued on a straight line (:meth:`beyond` names them), NaN above every column's
        reach in height."""
        s = float(values[0]) / self.E0
        out = np.full(self.h.size, np.nan)
        if not s > 0:
            return out
        for i, inv in enumerate(self._inv):
            if inv is None:
                continue
            cs, lo, hi, p_lo, p_hi, k_lo, k_hi = inv
            f = self.F[i] / s
            out[i] = s * (float(cs(f)) if lo <= f <= hi else p_hi + k_hi * (f - hi) if f > hi else p_lo + k_lo * (f - lo))
        return out

    def beyond(self, values: np.ndarray) -> np.ndarray:
        """Whether each point lies beyond the table at ``values`` = [E] (Pa): its height past every column's
        reach, or its force outside the forces the table holds at that height (one spacing continued)."""
        s = float(values[0]) / self.E0
        return np.array([inv is None or not s > 0 or not inv[1] <= f / s <= inv[2] for inv, f in zip(self._inv, self.F)])

    def check_reach(self, values: np.ndarray) -> None:
        """ValueError naming the first data row beyond the table at the fitted ``values`` (:meth:`beyond`)."""
        bad = np.flatnonzero(self.beyond(values))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"data: row {i + 1}: h {U.to_mm(self.h[i]):g} mm with a force of {self.F[i]:.4g} N is beyond "
                             f"the exact bonded membrane's reach at the fitted E = {float(values[0]):.4g} Pa (a disk of "
                             f"{U.to_mm(self.c):g} mm in a {U.to_mm(self.r1):g} mm clamp: no equilibrium with the "
                             "membrane stretched up to 4, or a pressure past what the annulus around the disk holds); "
                             "check the row's units, or leave it out")
