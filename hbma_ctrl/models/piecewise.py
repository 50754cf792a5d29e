"""Cubic B-spline tables evaluated as their piecewise polynomials, inline in casadi expressions.

A casadi ``bspline`` interpolant is a call node: every evaluation, and every derivative the
estimators' and controllers' algorithmic differentiation takes of it (forward, adjoint, their
products), is another call. The exact membrane's law is evaluated dozens of times per EKF step (the
Newton projections, the integrator's stages, the Jacobians): about 190 such calls in its generated
predict, most of its time. Within one cell of its grid a tensor-product cubic spline is a polynomial of degree 3 in each
coordinate, so :class:`PiecewiseCubic` stores each cell's 4^d coefficients (sampled from the spline
itself, so the two agree to rounding), finds the cell by comparisons (one floor on an evenly spaced
coordinate) and fetches its coefficients
with one linear-interpolant lookup at the cell's integer index (constant on the cell: the seeds
algorithmic differentiation passes into it are zero). The polynomial itself is plain arithmetic in
the caller's expression graph: derivatives of any order are inline.

Outside the grid the value is zero, as the spline's (callers clamp where they need a value there).
"""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np

__all__ = ["PiecewiseCubic"]

#: the local coordinates (0..1 across a cell) where each cell's polynomial is sampled: interior, so
#: every sample lies inside the cell's polynomial piece; the 4 x 4 Vandermonde is well conditioned
_NODES = np.array([0.1, 0.37, 0.63, 0.9])


class PiecewiseCubic:
    """Cubic B-spline interpolants of gridded data, evaluated as per-cell polynomials (SX, MX or DM).

    grid : one increasing array per coordinate (1 or 2 coordinates); values : arrays of the grid's
    shape (row i = the first coordinate's i-th node), one per output. ``self(c)`` returns the outputs
    at c (a column of the coordinates, each within its grid); ``splines`` are the casadi bspline
    interpolants the polynomials reproduce (to about 1e-13 relative, checked at construction).
    """

    def __init__(self, name: str, grid: list, values: list):
        self.grid = [np.asarray(g, dtype=float) for g in grid]
        self.dim = len(self.grid)
        if self.dim not in (1, 2):
            raise ValueError(f"{name}: 1 or 2 coordinates, got {self.dim}")
        shape = tuple(g.size for g in self.grid)
        vals = [np.asarray(v, dtype=float).reshape(shape) for v in values]
        self.splines = [ca.interpolant(f"{name}_{i}", "bspline", self.grid, v.ravel(order="F"))
                        for i, v in enumerate(vals)]
        cells = [g.size - 1 for g in self.grid]
        n_cells = int(np.prod(cells))
        nc = 4 ** self.dim
        # every cell's 4^d sample points at once (cell k = row-major multi-index, as itertools.product)
        lo = np.array(np.meshgrid(*[g[:-1] for g in self.grid], indexing="ij")).reshape(self.dim, -1)
        w = np.array(np.meshgrid(*[np.diff(g) for g in self.grid], indexing="ij")).reshape(self.dim, -1)
        loc = np.array(list(itertools.product(_NODES, repeat=self.dim))).T  # (dim, nc)
        pts = (lo[:, :, None] + w[:, :, None] * loc[:, None, :]).reshape(self.dim, -1)
        vinv = np.linalg.inv(np.vander(_NODES, 4, increasing=True))
        # per cell: its origin and inverse width per coordinate, then each output's coefficients
        rows = np.zeros((n_cells, 2 * self.dim + nc * len(vals)))
        rows[:, 0:2 * self.dim:2], rows[:, 1:2 * self.dim:2] = lo.T, 1.0 / w.T
        for j, sp in enumerate(self.splines):
            f = np.asarray(sp.map(pts.shape[1])(pts)).reshape((n_cells,) + (4,) * self.dim)
            # f[a, b] = sum_ij C[i, j] x_a^i y_b^j  ->  C = V^-1 f V^-T, per cell
            coef = f @ vinv.T if self.dim == 1 else np.einsum("ia,kab,jb->kij", vinv, f, vinv)
            rows[:, 2 * self.dim + j * nc:2 * self.dim + (j + 1) * nc] = coef.reshape(n_cells, nc)
        # cell k of the multi-index (i, j) is i * cells[1] + j: row-major, as itertools.product
        self._strides = [int(np.prod(cells[d + 1:])) for d in range(self.dim)]
        self._n_out = len(vals)
        self._lookup = ca.interpolant(f"{name}_cells", "linear", [np.arange(n_cells, dtype=float)],
                                      rows.T.ravel(order="F"))
        self._check(name)

    def cell(self, c):
        """The flat index of the cell holding c (expression; its derivative is zero): on an evenly
        spaced coordinate by one floor, otherwise by one comparison per interior node."""
        k = 0
        for d in range(self.dim):
            g = self.grid[d]
            step = np.diff(g)
            if np.allclose(step, step[0], rtol=1e-12, atol=0):
                # a node may land in the cell below by rounding: the two polynomials meet there (C2)
                i = ca.fmin(ca.fmax(ca.floor((c[d] - g[0]) / step[0]), 0), g.size - 2)
            else:
                i = 0
                for gi in g[1:-1]:
                    i = i + (c[d] >= gi)
            k = k + self._strides[d] * i
        return k

    def __call__(self, c) -> list:
        """The outputs at coordinates c (column of 1 or 2 entries; zero off the grid)."""
        row = self._lookup(self.cell(c))
        loc = [(c[d] - row[2 * d]) * row[2 * d + 1] for d in range(self.dim)]
        # zero outside the grid, as the bspline it replaces (callers that need a value there clamp)
        inside = 1
        for d in range(self.dim):
            inside = inside * (c[d] >= self.grid[d][0]) * (c[d] <= self.grid[d][-1])
        nc, off = 4 ** self.dim, 2 * self.dim
        out = []
        for j in range(self._n_out):
            C = [row[off + j * nc + i] for i in range(nc)]
            if self.dim == 1:
                v = C[0] + loc[0] * (C[1] + loc[0] * (C[2] + loc[0] * C[3]))
            else:
                a, b = loc
                # Horner in a of polynomials in b (C[4 i + j] multiplies a^i b^j)
                rows_b = [C[4 * i] + b * (C[4 * i + 1] + b * (C[4 * i + 2] + b * C[4 * i + 3])) for i in range(4)]
                v = rows_b[0] + a * (rows_b[1] + a * (rows_b[2] + a * rows_b[3]))
            out.append(ca.if_else(inside, v, 0))
        return out

    def _check(self, name: str) -> None:
        """The polynomials equal the splines at each cell's centre and corners (to 1e-10 relative):
        a wrong cell order or coefficient layout shows here, at construction."""
        mids = [0.5 * (g[:-1] + g[1:]) for g in self.grid]
        pts = np.array(list(itertools.product(*[np.concatenate([m, g]) for m, g in zip(mids, self.grid)]))).T
        n = pts.shape[1]
        c = ca.SX.sym("c", self.dim)
        f = ca.Function("pw", [c], [ca.vertcat(*self(c))]).map(n)
        got = np.asarray(f(pts))
        for j, sp in enumerate(self.splines):
            ref = np.asarray(sp.map(n)(pts)).ravel()
            err = np.max(np.abs(got[j] - ref)) / max(np.max(np.abs(ref)), 1e-300)
            if not err < 1e-10:
                raise RuntimeError(f"{name}: piecewise polynomial differs from its bspline by {err:.2e} (relative)")
