"""The chamber RTI's QP values in numpy: the oracle :func:`hbma_ctrl.controllers.rti_c.qp_data_function`
(what both RTI + OSQP variants hand OSQP) is compared with. The QP as the module docstring of
:mod:`hbma_ctrl.controllers.mpc` states it, on the pattern of :class:`hbma_ctrl.controllers.rti_c._RtiOsqp`."""

from __future__ import annotations

import numpy as np

from hbma_ctrl.controllers.mpc_solvers import _Problem


def qp_values(rti, pr: _Problem, Xb: np.ndarray, Ub: np.ndarray) -> dict:
    """OSQP's data (P_x, A_x in CSC data order, q, l, u; QP units, infinite bounds as inf) of ``rti``'s
    QP linearised along the states ``Xb`` (N+1,) and inputs ``Ub`` (N, 3), unshifted."""
    N, s = rti.N, rti.s
    Uext = np.vstack([Ub, Ub[-1:]])
    Ulin = Uext.copy()
    Ulin[:, :2] = np.maximum(Ulin[:, :2], s.rti_lin_floor)
    res = rti.stage.lin.map(N + 1)(Xb[None, :], Uext.T, Ulin.T, pr.W, pr.dp)
    f, a, b, h, ch, p, cp, lam, cl = (np.asarray(v) for v in res)
    f, a, h, ch, p, cp, lam, cl = (v.ravel() for v in (f, a, h, ch, p, cp, lam, cl))
    b = b.reshape(3, N + 1, order="F")
    # P: x diagonal from the Gauss-Newton height cost
    wk = np.full(N + 1, s.w_height)
    wk[0] = 0.0
    wk[N] += s.w_terminal
    r_mm, dh_mm = np.r_[pr.r[0], pr.r] * 1e3, pr.dh * 1e3
    e = h - ch * Xb + dh_mm - r_mm  # h_k(x) + dh - r = ch x + e
    Pv = np.array(rti.p_values(np.array(s.w_rate, float), np.array(s.w_input, float), s.w_slack))
    Pv[rti.P_x] = 2 * wk * ch ** 2 + 1e-8
    q = np.zeros(rti.nz)
    q[rti.ix] = 2 * wk * ch * e
    q[rti.iu[0]] += -2 * np.array(s.w_rate, float) * pr.u_prev
    q[rti.iu] += np.array(s.c_input, float)[None, :]
    q[rti.isl] = s.c_slack
    Av = rti.A_vals.copy()
    Av[rti.A_dyn_a] = -a[:N]
    Av[rti.A_dyn_b] = -b[:, :N].T
    k1 = np.arange(1, N + 1)
    Av[rti.A_soft[:, 0]] = cp[k1]
    Av[rti.A_soft[:, 1]] = cl[k1]
    Av[rti.A_soft[:, 2]] = ch[k1]
    if s.h_min > 0:
        Av[rti.A_soft[:, 3]] = -ch[k1]
    lo, up = rti.l0.copy(), rti.u0.copy()
    lo[rti.r_init] = up[rti.r_init] = pr.x0
    # x_{k+1} - a x_k - b u_k = f - a xb - b ub
    c = f[:N] - a[:N] * Xb[:N] - np.einsum("ik,ki->k", b[:, :N], Ub)
    lo[rti.r_dyn:rti.r_dyn + N] = up[rti.r_dyn:rti.r_dyn + N] = c
    # first input: box intersected with the rate limit from the applied command
    lo[rti.r_box:rti.r_box + 3] = np.maximum(0.0, pr.u_prev - rti.du)
    up[rti.r_box:rti.r_box + 3] = np.minimum(np.array(s.u_max, float), pr.u_prev + rti.du)
    rs = rti.r_soft + rti.n_soft * np.arange(N)
    up[rs] = pr.p_lim * 1e-3 - pr.dp * 1e-3 - (p[k1] - cp[k1] * Xb[k1])
    up[rs + 1] = s.lam_max * 1e2 - (lam[k1] - cl[k1] * Xb[k1])
    up[rs + 2] = s.h_max * 1e3 - dh_mm - (h[k1] - ch[k1] * Xb[k1])
    if s.h_min > 0:
        up[rs + 3] = -(s.h_min * 1e3 - dh_mm - (h[k1] - ch[k1] * Xb[k1]))
    return {"Px": Pv[rti.P.perm], "Ax": Av[rti.A.perm], "q": q, "l": lo, "u": up}
