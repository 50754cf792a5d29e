"""The throttled valve inputs in numpy: the oracle :func:`hbma_ctrl.models.bank.throttled_inputs_function`
(which :meth:`hbma_ctrl.models.bank.ChamberBank.valve_inputs` runs) is compared with. The compressor map
read bilinearly on its grid, as the Function reads it; the throttling as the module docstring of
:mod:`hbma_ctrl.models.bank` states it."""

from __future__ import annotations

import numpy as np

from hbma_ctrl.models.bank import STALL_MARGIN, PumpMap, commands_from_inputs


class NumpyPump(PumpMap):
    """The compressor map q(speed, p) (kg/s, before flow_scale) as numpy, bilinear on the table's grid
    like the model's casadi interpolant; pressures are clipped to the grid (Pa gauge)."""

    def at_pressures(self, p: np.ndarray) -> np.ndarray:
        """(n, n_speeds): the flow at every grid speed at each pressure p (n,)."""
        pg = self.pressures
        # np.minimum/np.maximum: np.clip's wrapper costs more than the interpolation here
        pc = np.minimum(np.maximum(np.asarray(p, dtype=float), pg[0]), pg[-1])
        j = np.minimum(np.maximum(np.searchsorted(pg, pc, side="right") - 1, 0), pg.size - 2)
        f = (pc - pg[j]) / (pg[j + 1] - pg[j])
        return np.maximum(self.q[:, j].T * (1 - f)[:, None] + self.q[:, j + 1].T * f[:, None], 0.0)

    def flow(self, speed, p) -> np.ndarray:
        """Pump flow (kg/s, before flow_scale) at speeds (n,) 0-1 and gauge pressures p (n,) Pa."""
        return self.flow_on(self.at_pressures(np.atleast_1d(p)), speed)

    def flow_on(self, Q: np.ndarray, speed) -> np.ndarray:
        """Flow at speeds (n,) on rows Q (n, n_speeds) of the map already taken at the pressures."""
        sg = self.speeds
        sp = np.broadcast_to(np.minimum(np.maximum(np.asarray(speed, dtype=float), sg[0]), sg[-1]), (Q.shape[0],))
        k = np.minimum(np.maximum(np.searchsorted(sg, sp, side="right") - 1, 0), sg.size - 2)
        f = (sp - sg[k]) / (sg[k + 1] - sg[k])
        r = np.arange(Q.shape[0])
        return Q[r, k] * (1 - f) + Q[r, k + 1] * f

    def speed_for(self, q_target, p) -> np.ndarray:
        """The lowest speed (n,) 0-1 whose flow at p (n,) Pa reaches q_target (n,) kg/s (1 where even
        full speed does not; 0 for no flow)."""
        return self.speed_on(self.at_pressures(np.atleast_1d(p)), q_target)

    def speed_on(self, Q: np.ndarray, q_target) -> np.ndarray:
        """:meth:`speed_for` on rows Q (n, n_speeds) of the map already taken at the pressures."""
        Q = np.maximum.accumulate(Q, axis=1)  # non-decreasing in speed
        n, sg = Q.shape[0], self.speeds
        qt = np.broadcast_to(np.asarray(q_target, dtype=float), (n,))
        # every row at once (the daemon throttles every chamber each period): the first grid speed whose
        # flow reaches the target (a row's searchsorted, left), a NaN target past the grid as there
        k = np.where(np.isnan(qt), sg.size, (Q < qt[:, None]).sum(axis=1))
        kk = np.minimum(np.maximum(k, 1), sg.size - 1)
        r = np.arange(n)
        q0, q1 = Q[r, kk - 1], Q[r, kk]
        out = sg[kk - 1] + (sg[kk] - sg[kk - 1]) * (qt - q0) / np.maximum(q1 - q0, 1e-300)
        out = np.where(k >= sg.size, 1.0, np.where(k == 0, sg[0], out))
        return np.minimum(np.maximum(np.where(qt <= 0.0, 0.0, out), 0.0), 1.0)



def throttled_inputs(a: np.ndarray, o: np.ndarray, p: np.ndarray, topology: str, pump: NumpyPump,
                     stall_margin: float = STALL_MARGIN) -> np.ndarray:
    """Per-chamber decisions (supply a as a full-speed inlet duty, outlet o; (n,) each, 0-1) at gauge
    pressures p (n,) Pa -> plant inputs U (3 x n) with the compressor throttled so that each inflow
    is ``a q(1, p)`` (see the module doc), the speed never below the one whose stall pressure is
    ``stall_margin`` Pa above p. Chambers the full-speed pump cannot feed at their pressure keep
    ``[1, a]`` (no flow either way)."""
    U = commands_from_inputs(a, o, topology)
    a = U[1]
    if topology == "shared" and a.sum() > 1.0:
        a = U[1] = a / a.sum()  # the manifold's budget (as the rig applies it)
    p = np.asarray(p, dtype=float).reshape(a.shape)
    p = np.where(np.isfinite(p), p, 0.0)
    draw = a > 0
    if not draw.any():
        return U
    Qp = pump.at_pressures(p)  # the map at the chambers' pressures, once
    q1 = pump.flow_on(Qp, np.ones(a.size))
    feedable = draw & (q1 > 0)
    # the lowest speed that still delivers at p + margin (1 where none does: full speed)
    s_min = pump.speed_for(np.full(a.size, 1e-12), p + stall_margin) if stall_margin > 0 else np.zeros(a.size)
    if topology == "per_chamber":
        sp = np.maximum(pump.speed_on(Qp, a * q1), s_min)
        q_s = pump.flow_on(Qp, sp)
        U[0] = np.where(feedable, sp, U[0])
        U[1] = np.where(feedable, np.minimum(a * q1 / np.maximum(q_s, 1e-300), 1.0), a)
        return U
    # shared: one speed; the lowest at which every duty a q1 / q(s) is <= 1 and they sum to <= 1
    if not feedable.any():
        return U
    idx = np.nonzero(feedable)[0]
    target = a[idx] * q1[idx]

    Q = Qp[idx]

    def duties(s: float) -> np.ndarray:
        q = pump.flow_on(Q, np.full(idx.size, s))
        return np.where(q > 0, target / np.maximum(q, 1e-300), np.inf)

    lo = float(max(pump.speed_on(Q, target).max(), s_min[idx].max()))  # each inlet at most fully open
    if not np.isfinite(duties(lo)).all() or duties(lo).sum() > 1.0:
        hi = 1.0
        for _ in range(16):  # the duties' sum falls with the speed: bisection on [lo, 1]
            mid = 0.5 * (lo + hi)
            d = duties(mid)
            lo, hi = (lo, mid) if np.isfinite(d).all() and d.sum() <= 1.0 else (mid, hi)
        lo = hi
    d = duties(lo)
    U[0] = np.full(a.shape, lo)
    U[1][idx] = np.minimum(d, 1.0)
    return U
