"""The law of ``hbma-ctrl fit --contact bonded``: static points of a chamber whose membrane centre is glued
to a rigid disk of radius c, as a lift rig's or the robot's layers are (SI inside).

The exact membrane bonded to the disk (docs/concepts/model.md §9) pushes the disk with F(h, p) at centre
height h and gauge pressure p; :func:`hbma_ctrl.robot.statics.bonded_table` solves it over a grid, once
per geometry (r1, t0), disk radius and material, cached on disk like the exact membrane's other tables.
Materials (:data:`BONDED_MATERIALS`):

- ``nh``: every tension is proportional to the modulus E, so the table at the default modulus E0 serves
  every E: ``F(h, p; E) = s F0(h, p / s)`` with ``s = E / E0``, and the model pressure of a data point
  (h, F) is ``p = s P0(h, F / s)``, P0 the table's inverse at fixed height.
- ``gent`` (a silicone that stiffens towards a locking stretch): at a fixed locking parameter Jm every
  tension is proportional to the shear modulus mu, so one table per Jm serves every mu (``s = mu /
  mu0``). The tables sit on a grid of ``u = 1 / Jm`` (:data:`GENT_U`; ``u = 0`` is nh with E = 3 mu,
  whose table it shares) and a point's pressure at the fitted Jm is a cubic spline in u through its
  pressures at the nodes (:meth:`BondedLaw.pressure`). The other materials change shape with more than
  one parameter (Mooney-Rivlin's C2 / C1, Yeoh's and Ogden's terms): a table family in two or more
  dimensions, not offered.

The grid (:data:`GRID_X`, :data:`GRID_P`) is in the annulus's own scales: heights over its width
``w = r1 - c`` and pressures over ``mu0 t0 / w`` (mu0 the default shear modulus; a narrower annulus
holds a higher pressure), out to past the solver's reach (NaN there: a meridian stretch above 4 or a
slack membrane; below a column's first equilibrium it goes on to higher centres). Pressures are spaced
evenly in their square root: near p = 0 the annulus bulges like
p^(1/3) (small deflection), so F is least smooth there. Interpolation: along each pressure column a cubic
spline of F over the height nodes (continued to h = 0 below the first one), then at each data height a
cubic spline of p over the columns' forces, which grow with p. Against the exact solver itself (at twice
the discretisation) it misses the pressure by about 1e-5 of it, 1e-4 at the edge of the solver's reach.

A row at h = 0 is the disk resting on its stop, the load not lifted: the stop carries what the membrane
does not, so the row is no equilibrium of a lifted disk and says only that its pressure is at most the
lift-off pressure for its force, ``P(0, F)`` (the table continued to h = 0). Given the data's pressures,
its model pressure is ``min(p, P(0, F))``: it counts as a miss only by how far its pressure exceeds
the lift-off pressure.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import Material, make_material
from hbma_ctrl.core.params import Actuator
from hbma_ctrl.models.exact import ExactMembrane

__all__ = ["GRID_X", "GRID_P", "GENT_U", "BONDED_MATERIALS", "JM_MIN", "bonded_grid", "node_material", "BondedLaw"]

#: table heights over the annulus width r1 - c (a meridian stretch of 4 ends the reach below 3.9)
GRID_X = np.concatenate([[0.01, 0.05], np.arange(0.1, 4.001, 0.1)])
#: table pressures over mu0 t0 / (r1 - c), even in their square root: past the force's peak of a Gent
#: membrane (2.8-4.6 for Jm 40-12 in a 70 mm clamp with a 25.4 mm disk); a data pressure p lies in the
#: table of a modulus down to p (r1 - c) / (5 mu0 t0) times the default one
GRID_P = 5.0 * np.linspace(0.0, 1.0, 29) ** 2
#: the Gent tables' locking parameters as u = 1 / Jm: nh (0) to Jm = 10, a membrane that locks at a
#: stretch of about 2.3 in equi-biaxial tension (silicones' fitted Jm lie above); closer where the
#: pressure's dependence on u bends most
GENT_U = np.array([0.0, 0.01, 0.02, 0.03, 0.045, 0.06, 0.08, 0.1])
#: the smallest Jm the bonded fit's tables cover
JM_MIN = float(1.0 / GENT_U[-1])
#: materials the bonded fit takes, each with its parameter names (the first one the modulus)
BONDED_MATERIALS = {"nh": ("E",), "gent": ("mu", "Jm")}


def bonded_grid(r1: float, t0: float, c: float) -> tuple[np.ndarray, np.ndarray]:
    """The table's heights (m) and pressures (Pa, at the default nh modulus) for clamp radius r1, thickness
    t0 and disk radius c (m)."""
    w = r1 - c
    mu0 = ExactMembrane(make_material("nh"), r1, t0, "bonded", c).mu
    return GRID_X * w, GRID_P * mu0 * t0 / w


def node_material(material: str, u: float) -> Material:
    """The material of one table: ``nh`` at its default E; ``gent`` at its default mu with Jm = 1 / u
    (u = 0: nh, the same law with E = 3 mu)."""
    return make_material("nh") if material == "nh" or u == 0 else make_material("gent", Jm=1.0 / u)


class _Inverse:
    """One table's pressure p0(h, f) (Pa, at the default modulus) at the data's distinct heights, for forces
    f (N): at each height a cubic spline of p over the columns' forces, continued one spacing of F either
    side, past that on a straight line (marked beyond)."""

    def __init__(self, hg: np.ndarray, pg: np.ndarray, Ftab: np.ndarray, heights: np.ndarray):
        # F0 of every column at the data heights, continued one node spacing past its last solved height
        # (NaN beyond): a point at the solver's reach between two nodes stays a value, not a penalty
        G = np.full((heights.size, pg.size), np.nan)
        for j in range(pg.size):
            ok = np.isfinite(Ftab[:, j])
            if ok.sum() >= 4:
                hs = hg[ok]
                inside = heights <= hs[-1] + (hs[-1] - hs[-2])
                G[inside, j] = CubicSpline(hs, Ftab[ok, j])(heights[inside])
        # each height's inverse p0(F) over the columns it reaches with F growing, continued one spacing
        # of F either side (below: the pressure a force under the vented membrane's would need); past
        # that, a straight line with the end segments' slopes: a point beyond the reach then pulls the
        # fit no harder than its miss, instead of a penalty the modulus would be moved to escape
        self.inv = []
        for row in G:
            n = 0
            while n < row.size and np.isfinite(row[n]) and (n == 0 or row[n] > row[n - 1]):
                n += 1
            if n >= 4:
                f, q = row[:n], pg[:n]
                lo, hi = 2 * f[0] - f[1], 2 * f[-1] - f[-2]
                cs = CubicSpline(f, q)
                self.inv.append((cs, lo, hi, float(cs(lo)), float(cs(hi)), (q[1] - q[0]) / (f[1] - f[0]),
                                 (q[-1] - q[-2]) / (f[-1] - f[-2])))
            else:
                self.inv.append(None)

    def __call__(self, groups: list, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pressures p0 (Pa; NaN above the height reach) and beyond flags of the points with forces f (N);
        ``groups``: each distinct height's point indices."""
        p, beyond = np.full(f.size, np.nan), np.ones(f.size, dtype=bool)
        for inv, idx in zip(self.inv, groups):
            if inv is None:
                continue
            cs, lo, hi, p_lo, p_hi, k_lo, k_hi = inv
            ff = f[idx]
            inside = (ff >= lo) & (ff <= hi)
            val = np.where(ff > hi, p_hi + k_hi * (ff - hi), p_lo + k_lo * (ff - lo))
            if inside.any():
                val[inside] = cs(ff[inside])
            p[idx], beyond[idx] = val, ~inside
        return p, beyond


class BondedLaw:
    """Model pressures (Pa) of static points (heights h m, forces F N on the disk) of a membrane glued to a
    disk of radius c (m), clamp radius r1, thickness t0 (m), for the parameters of ``material`` (one of
    :data:`BONDED_MATERIALS`: nh [E] or gent [mu, Jm], SI); ``cache``: the tables' directory (None: the
    exact tables' one); ``p``: the data's pressures (Pa), for the rule of rows at h = 0 (none: such a
    row's model pressure is its lift-off pressure)."""

    def __init__(self, r1: float, t0: float, c: float, h: np.ndarray, F: np.ndarray, cache=None,
                 material: str = "nh", p: np.ndarray | None = None):
        from hbma_ctrl.robot.statics import bonded_table

        if material not in BONDED_MATERIALS:
            raise ValueError(f"--material {material}: the bonded fit takes {', '.join(BONDED_MATERIALS)}")
        self.material, self.names = material, BONDED_MATERIALS[material]
        self.mod0 = float(getattr(make_material(material), self.names[0]))
        self.r1, self.c = r1, c
        self.h, self.F = np.asarray(h, dtype=float), np.asarray(F, dtype=float)
        self.p = None if p is None else np.asarray(p, dtype=float)
        self.resting = self.h <= 0
        heights, where = np.unique(self.h, return_inverse=True)
        self._groups = [np.flatnonzero(where == k) for k in range(heights.size)]
        hg, pg = bonded_grid(r1, t0, c)
        self.u = np.array([0.0]) if material == "nh" else GENT_U
        self._nodes, self.paths, self.build_s = [], [], 0.0
        for u in self.u:
            tab = bonded_table(Actuator(r1=r1, t0=t0, material=node_material(material, u)), c, cache, h=hg, p=pg,
                               low_misses=True)
            self.build_s += float(tab["build_s"])
            self.paths.append(tab["path"])
            self._nodes.append(_Inverse(hg, pg, tab["F"], heights))
        self.path = self.paths[0]

    def _lifted(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's pressure (Pa) as a lifted disk's equilibrium (h = 0: the lift-off pressure) and
        whether it lies beyond the tables, for ``values`` (SI, :attr:`names`)."""
        n = self.h.size
        s = float(values[0]) / self.mod0
        nan = np.full(n, np.nan)
        if not s > 0:
            return nan, np.ones(n, dtype=bool)
        f = self.F / s
        if self.material == "nh":
            p0, beyond = self._nodes[0](self._groups, f)
            return s * p0, beyond
        Jm = float(values[1])
        u = 1.0 / Jm if Jm > 0 else np.inf
        if not 0.0 <= u <= self.u[-1]:
            return nan, np.ones(n, dtype=bool)
        P, B = zip(*(node(self._groups, f) for node in self._nodes))
        P, B = np.array(P), np.array(B)
        k = min(int(np.searchsorted(self.u, u, side="right")) - 1, self.u.size - 2)  # bracket [u_k, u_k+1]
        ok = np.isfinite(P)
        beyond = B[k] | B[k + 1] | ~ok[k] | ~ok[k + 1]
        out = nan.copy()
        # through the nodes a point has on either side of u without a gap: a cubic over four or more,
        # a parabola over three, a straight line over two (a point beyond a node's height reach has none)
        lo = np.full(n, k)
        while (lo > 0).any():
            step = (lo > 0) & ok[np.maximum(lo - 1, 0), np.arange(n)]
            if not step.any():
                break
            lo = np.where(step, lo - 1, lo)
        hi = np.full(n, k + 1)
        while (hi < self.u.size - 1).any():
            step = (hi < self.u.size - 1) & ok[np.minimum(hi + 1, self.u.size - 1), np.arange(n)]
            if not step.any():
                break
            hi = np.where(step, hi + 1, hi)
        both = ok[k] & ok[k + 1]
        for a, b in set(zip(lo[both].tolist(), hi[both].tolist())):
            idx = np.flatnonzero(both & (lo == a) & (hi == b))
            out[idx] = CubicSpline(self.u[a:b + 1], P[a:b + 1][:, idx], axis=0)(u)
        return s * out, beyond

    def pressure(self, values: np.ndarray) -> np.ndarray:
        """Model pressures (Pa) at the data points for ``values`` (SI, :attr:`names`); beyond the table's
        forces at a point's height continued on a straight line (:meth:`beyond` names them), NaN above
        every column's reach in height. A row at h = 0 with the data's pressures: ``min(p, P(0, F))``."""
        p, _ = self._lifted(values)
        if self.p is not None:
            rest = self.resting & np.isfinite(p)
            p[rest] = np.minimum(p[rest], self.p[rest])
        return p

    def beyond(self, values: np.ndarray) -> np.ndarray:
        """Whether each point lies beyond the tables at ``values``: its height past every column's reach, or
        its force outside the forces the table holds at that height (one spacing continued); a resting row
        (h = 0) whose pressure is below its continued lift-off pressure is not."""
        p, beyond = self._lifted(values)
        if self.p is not None:
            beyond &= ~(self.resting & np.isfinite(p) & (self.p <= p))
        return beyond

    def beyond_note(self, values: np.ndarray) -> list[str]:
        """A note counting the rows beyond the table at the fitted ``values`` (:meth:`beyond`), naming the
        first; none when every row is inside."""
        bad = np.flatnonzero(self.beyond(values))
        if not bad.size:
            return []
        i = int(bad[0])
        return [f"{bad.size} of {self.h.size} rows lie beyond the exact bonded membrane's reach at the fitted "
                f"parameters (first: row {i + 1}, h {U.to_mm(self.h[i]):g} mm, {self.F[i]:.4g} N): kept with the "
                "pressure continued on a straight line past the table, counted in the NRMSD"]

    def check_reach(self, values: np.ndarray) -> None:
        """ValueError naming the first data row beyond the table at the fitted ``values`` (:meth:`beyond`)."""
        bad = np.flatnonzero(self.beyond(values))
        if bad.size:
            i = int(bad[0])
            at = ", ".join(f"{n} = {float(v):.4g}" + (" Pa" if j == 0 else "")
                           for j, (n, v) in enumerate(zip(self.names, values)))
            raise ValueError(f"data: row {i + 1}: h {U.to_mm(self.h[i]):g} mm with a force of {self.F[i]:.4g} N is beyond "
                             f"the exact bonded membrane's reach at the fitted {at} (a disk of "
                             f"{U.to_mm(self.c):g} mm in a {U.to_mm(self.r1):g} mm clamp: no equilibrium with the "
                             "membrane stretched up to 4, or a pressure past what the annulus around the disk holds); "
                             "check the row's units, or leave it out (--keep-beyond-reach keeps such rows)")
