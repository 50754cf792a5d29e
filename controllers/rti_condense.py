"""The RTI step's sparse QP condensed onto its inputs and slacks, for a dense QP solver.

The sparse QP of :func:`hbma_ctrl.controllers.rti_step.rti_step_function` (its ``rti_qp_data`` part:
min 1/2 z'Hz + g'z, lbx <= z <= ubx, lba <= Az <= uba) fixes the first state and the previous input by
their bounds (lbx = ubx) and ties every other state and previous-input copy to the inputs by equality
rows (the dynamics, v_{k+1} = u_k), leaving those variables unbounded. :func:`condensing` finds this
structure in the data Function's expressions (a bound or a row whose two sides are the same expression
is an equality; a variable with no finite bound is free), writes every fixed or free variable as an
affine function of the others (the inputs and slacks: y), z = T y + t, by substituting the equality
rows one after another, and returns the casadi Function of the condensed QP

    min 1/2 y'Hc y + gc'y,   lby <= y <= uby,   lbc <= Ac y <= ubc

whose solution y gives the sparse QP's solution z = T y + t (the same problem once the equalities are
substituted; its cost differs by a constant). Rows that are equalities, or have no finite bound, leave
the condensed QP.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

__all__ = ["Condensing", "condensing"]

#: a bound at or beyond this is no bound (OSQP's and DAQP's infinity)
INF = 1e30


@dataclass
class Condensing:
    """The condensed QP's Function and its sizes.

    ``function``: (H nonzeros, g, A nonzeros, lba, uba, lbx, ubx) of the sparse QP (its data Function's
    first seven outputs; H and A in their patterns) -> (Hc dense ny x ny, gc, Ac dense mc x ny row by
    row, the bounds [lby; lbc] and [uby; ubc] clipped to +-:data:`INF`, T's nonzeros, t); ``T`` the
    sparsity of T (nz x ny); ``free``: the sparse variables y holds, in order; ``rows``: the sparse
    rows the condensed QP keeps, in order."""

    function: ca.Function
    T: ca.Sparsity
    free: np.ndarray
    rows: np.ndarray

    @property
    def ny(self) -> int:
        """Variables of the condensed QP."""
        return int(self.free.size)

    @property
    def mc(self) -> int:
        """General constraint rows of the condensed QP."""
        return int(self.rows.size)


def _same(a: ca.SX, b: ca.SX) -> bool:
    return bool(ca.is_equal(a, b, 2))


def _is_inf(v: ca.SX, sign: float) -> bool:
    return bool(v.is_constant()) and float(v) * sign >= INF


def condensing(data: ca.Function, name: str = "hbma_qp_condense") -> Condensing:
    """The condensing of the sparse QP built by ``data`` (``rti_qp_data``: outputs H, g, A, lba, uba,
    lbx, ubx first). ValueError when the fixed and free variables are not determined by the equality
    rows one at a time (each row, in some order, adds exactly one of them)."""
    sx = [ca.SX.sym(data.name_in(i), data.sparsity_in(i)) for i in range(data.n_in())]
    H, g, A, lba, uba, lbx, ubx = data(*sx)[:7]
    nz, nc = A.size2(), A.size1()
    fixed = [i for i in range(nz) if _same(lbx[i], ubx[i])]
    free_var = [i for i in range(nz) if _is_inf(lbx[i], -1) and _is_inf(ubx[i], 1)]
    dep = sorted(fixed + free_var)
    keep = np.array([i for i in range(nz) if i not in set(dep)])
    eq = [r for r in range(nc) if _same(lba[r], uba[r])]
    rows = np.array([r for r in range(nc) if r not in set(eq) and not (_is_inf(lba[r], -1) and _is_inf(uba[r], 1))])
    # the function's symbolic inputs: the sparse QP's numbers
    Hv, Av = ca.SX.sym("H", H.nnz()), ca.SX.sym("A", A.nnz())
    Hs, As = ca.SX(H.sparsity(), Hv), ca.SX(A.sparsity(), Av)
    gs, la, ua, lx, ux = (ca.SX.sym(n, nz if n in ("g", "lbx", "ubx") else nc) for n in ("g", "lba", "uba", "lbx", "ubx"))
    ny = keep.size
    # z_i = expr_i[:ny] . y + expr_i[ny]: a sparse column each
    expr: dict[int, ca.SX] = {}
    for j, i in enumerate(keep):
        e = ca.SX(ny + 1, 1)
        e[j] = 1.0
        expr[int(i)] = e
    for i in fixed:
        e = ca.SX(ny + 1, 1)
        e[ny] = lx[i]
        expr[i] = e
    Acol, Arow = np.array(A.sparsity().colind()), np.array(A.sparsity().row())
    row_entries: dict[int, list] = {r: [] for r in eq}
    for j in range(nz):
        for k in range(Acol[j], Acol[j + 1]):
            if int(Arow[k]) in row_entries:
                row_entries[int(Arow[k])].append((j, k))
    pending = list(eq)
    while pending:
        progress = []
        for r in pending:
            unknown = [(j, k) for j, k in row_entries[r] if j not in expr]
            if len(unknown) > 1:
                continue
            if not unknown:
                raise ValueError(f"{data.name()}: equality row {r} holds no fixed or free variable to solve for")
            (jn, kn), = unknown
            acc = ca.SX(ny + 1, 1)
            acc[ny] = la[r]
            for j, k in row_entries[r]:
                if j != jn:
                    acc = acc - Av[k] * expr[j]
            expr[jn] = acc / Av[kn]
            progress.append(r)
        if not progress:
            raise ValueError(f"{data.name()}: the equality rows do not determine the fixed and free variables")
        pending = [r for r in pending if r not in progress]
    if len(expr) != nz:
        raise ValueError(f"{data.name()}: {nz - len(expr)} free variables are in no equality row")
    Z = ca.horzcat(*[expr[i] for i in range(nz)]).T  # nz x (ny + 1)
    T, t = Z[:, :ny], Z[:, ny]
    # the data's H is the full symmetric matrix
    Hc = ca.mtimes(T.T, ca.mtimes(Hs, T))
    gc = ca.mtimes(T.T, ca.mtimes(Hs, t) + gs)
    Ain = As[[int(r) for r in rows], :]
    Ac = ca.mtimes(Ain, T)
    shift = ca.mtimes(Ain, t)
    clip = lambda v: ca.fmin(ca.fmax(v, -INF), INF)  # noqa: E731
    lo = ca.vertcat(lx[keep.tolist()], la[rows.tolist()] - shift)
    hi = ca.vertcat(ux[keep.tolist()], ua[rows.tolist()] - shift)
    # DAQP reads A row by row (row-major), casadi stores column by column: the transpose's columns
    outs = [ca.densify(Hc), ca.densify(gc), ca.vec(ca.densify(Ac).T), clip(lo), clip(hi), T.nz[:], ca.densify(t)]
    fun = ca.Function(name, [Hv, gs, Av, la, ua, lx, ux], outs, ["H", "g", "A", "lba", "uba", "lbx", "ubx"],
                      ["Hc", "gc", "Ac", "lo", "hi", "T", "t"], {"cse": True})
    return Condensing(fun, T.sparsity(), keep, rows)
