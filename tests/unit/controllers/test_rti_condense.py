"""The RTI step's QP condensed onto its inputs and slacks (hbma_ctrl.controllers.rti_condense) against the
sparse QP, on the QPs of a cold start and of a shifted step with active input and rate limits: the condensed
QP solved by DAQP (casadi's plugin, an active-set solver) and mapped back (z = T y + t) meets every bound and
row of the sparse QP (1e-9) at a cost no higher than the sparse QP's optimum by OSQP at 1e-10 (the oracle),
so it is that QP's optimum (its cost is strictly convex on the feasible set), and it is OSQP's solution to
OSQP's accuracy."""

from __future__ import annotations

import casadi as ca
import numpy as np
import osqp
import pytest
import scipy.sparse as sp

from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.controllers.rti_condense import INF, condensing
from hbma_ctrl.controllers.rti_step import rti_step_function

W400 = 0.4 * 9.80665
N = 6
TOL = 1e-10


@pytest.fixture(scope="module")
def parts(cap_prediction_model):
    s = MPCSettings(horizon=N, codegen=False).validate()
    rti = rti_step_function(cap_prediction_model, s, "osqp")
    data = rti.find_function("rti_qp_data")
    return cap_prediction_model, s, data, condensing(data)


def _sparse_osqp(P, q, A, lo, hi):
    m = osqp.OSQP()
    m.setup(sp.triu(sp.csc_matrix(P)).tocsc(), q, sp.csc_matrix(A), lo, hi, verbose=False, polishing=False,
            eps_abs=TOL, eps_rel=TOL, max_iter=400000)
    r = m.solve()
    assert r.info.status == "solved"
    return r.x


def _dense_daqp(H, g, A, lo, hi):
    ny, mc = H.shape[0], A.shape[0]
    qp = ca.conic("c", "daqp", {"h": ca.Sparsity.dense(ny, ny), "a": ca.Sparsity.dense(mc, ny)})
    r = qp(h=H, g=g, a=A, lbx=lo[:ny], ubx=hi[:ny], lba=lo[ny:], uba=hi[ny:])
    return np.asarray(r["x"]).ravel()


def _inputs(model, s, h, r, u_prev, X=None, U=None, shift=0.0):
    x0 = float(model.x_at_height(h, W400))
    X = np.full(N + 1, x0) if X is None else X
    U = np.tile(np.asarray(u_prev, float)[:, None], (1, N)) if U is None else U
    return [x0, W400, 1e-4, 300.0, np.asarray(u_prev, float), s.p_max - s.p_margin, np.full(N, r), X, U,
            np.zeros(8 * N + 4), np.zeros(11 * N), shift]


def _compare(data, cond, ins) -> None:
    H, g, A, lba, uba, lbx, ubx = (np.asarray(ca.DM(v)) for v in data(*ins)[:7])
    nz, g = H.shape[0], g.ravel()
    clip = lambda v: np.clip(v.ravel(), -INF, INF)  # noqa: E731
    Af, lo_f, hi_f = np.vstack([np.eye(nz), A]), clip(np.vstack([lbx, lba])), clip(np.vstack([ubx, uba]))
    z = _sparse_osqp(H, g, Af, lo_f, hi_f)
    out = cond.function(ca.DM(data(*ins)[0]).nz[:], g, ca.DM(data(*ins)[2]).nz[:], lba, uba, lbx, ubx)
    Hc, gc, Ac, lo, hi, Tnz, t = (np.asarray(v).ravel() for v in out)
    ny, mc = cond.ny, cond.mc
    y = _dense_daqp(Hc.reshape(ny, ny), gc, Ac.reshape(mc, ny), lo, hi)
    zc = np.asarray(ca.DM(cond.T, Tnz)) @ y + t
    Az = Af @ zc
    tol = 1e-9 * (1.0 + np.abs(Az))
    assert np.all(Az >= lo_f - tol) and np.all(Az <= hi_f + tol)
    cost = lambda v: 0.5 * v @ H @ v + g @ v  # noqa: E731
    assert cost(zc) <= cost(z) + 1e-9 * (1.0 + abs(cost(z)))
    assert np.max(np.abs(zc - z)) <= 1e-5 * max(1.0, np.max(np.abs(z)))


def test_condensed_qp_keeps_inputs_and_slacks_and_drops_equalities(parts):
    """The condensed QP's variables are the inputs and slacks (4 a stage), its rows the sparse QP's
    inequalities with a finite bound (the first stage's rate rows, bounded by u_0's box, leave)."""
    _, _, data, cond = parts
    assert cond.ny == 4 * N
    assert cond.mc == 7 * N - 3
    Hc = np.asarray(cond.function.sparsity_out(0).shape)
    assert tuple(Hc) == (cond.ny, cond.ny)


@pytest.mark.parametrize("h, r, u_prev", [(5.0e-3, 5.3e-3, (0.3, 0.5, 0.1)), (5.0e-3, 5.05e-3, (0.0, 0.0, 0.0)),
                                          (6.0e-3, 5.6e-3, (1.0, 1.0, 0.0))])
def test_condensed_solution_is_the_sparse_one_at_a_cold_start(parts, h, r, u_prev):
    """Cold start (the guess is the estimate and the last input): z = T y + t of the condensed QP's solution
    is the sparse QP's optimum (feasible, no costlier than OSQP's, OSQP's to its accuracy)."""
    model, s, data, cond = parts
    _compare(data, cond, _inputs(model, s, h, r, u_prev))


def test_condensed_solution_is_the_sparse_one_on_a_shifted_step(parts):
    """A shifted RTI step from a plan that pumps hard (inputs at their box and rate limits): the same."""
    model, s, data, cond = parts
    x0 = float(model.x_at_height(5.0e-3, W400))
    X = np.linspace(x0, 1.05 * x0, N + 1)
    U = np.tile(np.array([[1.0], [1.0], [0.0]]), (1, N))
    _compare(data, cond, _inputs(model, s, 5.0e-3, 5.4e-3, (1.0, 1.0, 0.0), X, U, 1.0))
