"""The chamber RTI's QP in numpy: the oracle :func:`hbma_ctrl.controllers.rti_c.qp_data_function` (what
both RTI + OSQP variants hand OSQP) is compared with. The QP as the module docstring of
:mod:`hbma_ctrl.controllers.mpc` states it, in the variable layout of
:class:`hbma_ctrl.controllers.rti_c._RtiOsqp` (x_0..x_N, u_0..u_{N-1}, the slacks of stages 1..N) and its
row order (x_0, dynamics, input box, rates, inlet - speed, soft limits per stage, slacks)."""

from __future__ import annotations

import numpy as np

from hbma_ctrl.controllers.mpc_solvers import _Problem


def qp_matrices(rti, pr: _Problem, Xb: np.ndarray, Ub: np.ndarray) -> dict:
    """``rti``'s QP linearised along the states ``Xb`` (N+1,) and inputs ``Ub`` (N, 3), unshifted: dense
    P (its upper triangle), A, and q, l, u (QP units: mm, kPa, 1/100; infinite bounds as inf)."""
    N, s, nz = rti.N, rti.s, rti.nz
    ix, iu, isl = rti.ix, rti.iu, rti.isl
    Uext = np.vstack([Ub, Ub[-1:]])
    Ulin = Uext.copy()
    Ulin[:, :2] = np.maximum(Ulin[:, :2], s.rti_lin_floor)
    res = rti.stage.lin.map(N + 1)(Xb[None, :], Uext.T, Ulin.T, pr.W, pr.dp)
    f, a, b, h, ch, p, cp, lam, cl = (np.asarray(v) for v in res)
    f, a, h, ch, p, cp, lam, cl = (v.ravel() for v in (f, a, h, ch, p, cp, lam, cl))
    b = b.reshape(N + 1, 3).T  # a row of three per node -> 3 x (N+1)
    wr, wu, cu = (np.array(v, float) for v in (s.w_rate, s.w_input, s.c_input))
    du = np.array(s.du_max, float) * s.sample_period
    # cost: Gauss-Newton height terms h_k(x) + dh - r = ch x + e, input rates, inputs, slacks
    wk = np.full(N + 1, s.w_height)
    wk[0] = 0.0
    wk[N] += s.w_terminal
    r_mm, dh_mm = np.r_[pr.r[0], pr.r] * 1e3, pr.dh * 1e3
    e = h - ch * Xb + dh_mm - r_mm
    P = np.zeros((nz, nz))
    q = np.zeros(nz)
    P[ix, ix] = 2 * wk * ch ** 2 + 1e-8
    q[ix] = 2 * wk * ch * e
    for k in range(N):
        nd = 2 if k < N - 1 else 1
        P[iu[k], iu[k]] = 2 * wr * nd + 2 * wu + 1e-8
        if k > 0:
            P[iu[k - 1], iu[k]] = -2 * wr
        q[iu[k]] = cu - (2 * wr * pr.u_prev if k == 0 else 0.0)
    P[isl, isl] = 2 * s.w_slack
    q[isl] = s.c_slack
    rows = []

    def row(entries, lo, up):
        v = np.zeros(nz)
        for col, val in entries:
            v[col] = val
        rows.append((v, lo, up))

    row([(ix[0], 1.0)], pr.x0, pr.x0)
    for k in range(N):  # x_{k+1} - a x_k - b u_k = f - a xb - b ub
        c = f[k] - a[k] * Xb[k] - b[:, k] @ Ub[k]
        row([(ix[k + 1], 1.0), (ix[k], -a[k])] + [(iu[k, i], -b[i, k]) for i in range(3)], c, c)
    for k in range(N):
        for i in range(3):
            lo, up = (max(0.0, pr.u_prev[i] - du[i]), min(s.u_max[i], pr.u_prev[i] + du[i])) if k == 0 else \
                (0.0, s.u_max[i])
            row([(iu[k, i], 1.0)], lo, up)
    for k in range(1, N):
        for i in range(3):
            row([(iu[k, i], 1.0), (iu[k - 1, i], -1.0)], -du[i], du[i])
    for k in range(N):
        row([(iu[k, 1], 1.0), (iu[k, 0], -1.0)], 0.0, np.inf)
    for k in range(N):
        j = k + 1  # y(x_j) ~ y_j + cy_j (x_j - xb_j) <= limit + slack
        limits = [(cp[j], pr.p_lim * 1e-3 - pr.dp * 1e-3 - (p[j] - cp[j] * Xb[j])),
                  (cl[j], s.lam_max * 1e2 - (lam[j] - cl[j] * Xb[j])),
                  (ch[j], s.h_max * 1e3 - dh_mm - (h[j] - ch[j] * Xb[j]))]
        if s.h_min > 0:
            limits.append((-ch[j], -(s.h_min * 1e3 - dh_mm - (h[j] - ch[j] * Xb[j]))))
        for slope, bound in limits:
            row([(ix[j], slope), (isl[k], -1.0)], -np.inf, bound)
    for k in range(N):
        row([(isl[k], 1.0)], 0.0, np.inf)
    A = np.array([v for v, _, _ in rows])
    return {"P": P, "A": A, "q": q, "l": np.array([lo for _, lo, _ in rows]), "u": np.array([up for _, _, up in rows])}
