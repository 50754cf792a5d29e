"""A bank of per-chamber EKFs for the robot, stepped as one mapped casadi call (SI).

One filter per chamber, each from its own pressure sensor. State ``[y, b, k, c]``: ``y = (x + 1) / c``
with ``x`` the gas mass (scaled by the NOMINAL ``p_env V0 / RT``, minus 1) of
:class:`hbma_ctrl.models.bank.ChamberBank`, and three slow random walks: the pump-flow factor ``b``, the
membrane-modulus factor ``k`` and the dead-volume factor ``c`` (see :meth:`ChamberBank.outputs_expr`);
``step`` reports ``x``.
Why y and not x: a resting chamber's pressure is ``p_env ((x + 1) / c - 1)``, so in (x, c) the first
reading pins only their ratio and the filter starts with x and c correlated 0.9999; each update then
moves both along that ridge by up to 0.1 (the onset of a structured rig's first pumping throws the
filters' dead-volume and flow factors to their bounds). In y the reading pins y alone. The load ``W`` of
each chamber is not a state: the robot's statics give it (:func:`hbma_ctrl.robot.statics.load_sharing`
of the estimated heights), one control period late.

Why separate filters rather than one joint filter: given the loads, the chambers' gas masses are
dynamically independent (each has its own valves and sensor; with the shared pump the manifold
model keeps each chamber's inflow its own duty times the pump flow), so a joint filter's
covariance would be block diagonal up to the load coupling, which enters through W and is small
against the parameter mismatch. Nine 4-state filters (one mapped call) cost a fraction of one
36-state filter's dense algebra.

Why k and c. Without k a softer rig membrane, whose pressure peaks lower, drags the filter back
onto the near branch as soon as the pressure falls past the (earlier, lower) true limit point:
the falling pressure is explained by less gas instead of by a far-branch membrane (first runs: a
-15 % modulus chamber estimated at 2.5 mm while it stood at 15 mm). Without c the larger dead volume
biases the height by the cap volume's share (-0.2 to -0.7 mm near 6 mm in the first 3-layer run).
What is observable when: at rest only ``(x + 1) / c`` (the pressure) and ``b / c`` (its rise per
command) are; k is not (a flat membrane's pressure does not depend on it). After lift-off the shape
of p(gas mass) and the peak value separate k and c. Near the limit point the pressure hardly
depends on the gas mass (dp/dx -> 0): there the filter leans on the flow model (the gas mass
integrates the commanded flow with the learnt b), which is what keeps the far branch observable at
all. Targets held on the near branch, below the peak, leave k and c partly unlearnt (a residual
height error of a few tenths of a mm is then possible).

All chambers are stepped by ONE call of the casadi ``map`` of the single-chamber step (predict with
rk4 + Jacobians, covariance predict, scalar Joseph update), so 9 filters cost about one call.
A missing (NaN) or saturated (>= sensor range) reading skips that chamber's update.

Live-stream guards (as in :class:`hbma_ctrl.estimators.ekf.EKF`): a reading that cannot be physical (+-inf,
not a number, below vacuum or ``reading_min``, above ``reading_max_rel`` times the sensor range) and
one whose NIS exceeds ``gate_nis`` are outliers: that chamber predicts only, counted in
:meth:`ChamberEKFBank.stats`. ``gate_reopen`` gated readings in a row of one chamber re-open its
gate: its prior covariance is inflated (inside the mapped step) until the reading's NIS equals
``gate_nis`` (by at most ``INFLATION_MAX``), and the reading is used; it stays open until a
reading passes it unaided. ``step(..., steps=k)`` predicts k periods (a late tick);
more than ``max_gap`` of them are cut to ``max_gap`` and the covariance is widened by the initial
spread (counted as ``time_jumps``).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.estimators.common import INFLATION_MAX, VACUUM_GAUGE, classify_expr, physical_reading_bounds
from hbma_ctrl.core.codegen import FastFunction, is_finite
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.models.actuation import CommandTiming, sensor_delay_setting, valve_delay_setting
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.models.defaults import DEFAULT_VALVE_DELAY, ROBOT_SENSOR_DELAY

__all__ = ["ChamberEKFSettings", "ChamberEKFBank", "bank_step_function"]


@dataclass(frozen=True)
class ChamberEKFSettings(Settings):
    """Per-chamber EKF tuning (SI; each field's unit, range and one-line doc are in its declaration).

    max_gap : see the module doc. valve_delay, sensor_delay : the commands are taken as acting that
    late (:class:`hbma_ctrl.models.actuation.CommandTiming`, as by the single chamber's EKF; 0 = at
    once; defaults :mod:`hbma_ctrl.models.defaults`).
    """

    WHERE = "robot_ekf"

    sample_period: float = setting(0.01, lo=1e-4, hi=1.0, unit="s", doc="time between steps")
    noise_std: float = setting(200.0, lo=1.0, hi=1e4, unit="Pa", doc="sensor noise one sigma")
    model_rel_std: float = setting(0.01, lo=0.0, hi=1.0, doc="relative pressure model error (modulus mismatch)")
    x_abs_std: float = setting(2e-4, lo=0.0, hi=1.0, doc="process noise of the scaled gas mass per step")
    x_rel_std: float = setting(0.1, lo=0.0, hi=10.0,
                               doc="process noise of the scaled gas mass relative to its predicted change")
    b_rate_std: float = setting(0.05, lo=0.0, hi=10.0, unit="1/sqrt(s)", doc="random walk of the flow factor")
    b0: float = setting(1.0, lo=0.5, hi=2.0, doc="initial flow factor")
    b0_std: float = setting(0.25, lo=0.0, hi=2.0, doc="its one sigma")
    k0_std: float = setting(0.15, lo=0.0, hi=1.0, doc="initial one sigma of the modulus factor (prior 1)")
    k_rate_std: float = setting(0.002, lo=0.0, hi=10.0, unit="1/sqrt(s)", doc="random walk of the modulus factor")
    c0_std: float = setting(0.25, lo=0.0, hi=1.0, doc="initial one sigma of the dead-volume factor (prior 1)")
    c_rate_std: float = setting(0.002, lo=0.0, hi=10.0, unit="1/sqrt(s)",
                                doc="random walk of the dead-volume factor")
    sensor_range: float = setting(50e3, lo=1e3, hi=1e6, unit="Pa", doc="readings at or above this are not used")
    reading_min: float = setting(VACUUM_GAUGE, lo=VACUUM_GAUGE, hi=0.0, unit="Pa",
                                 doc="lowest physical reading, gauge (below: an outlier)")
    reading_max_rel: float = setting(1.5, lo=1.0, hi=1000.0,
                                     doc="a reading above this times sensor_range is an outlier")
    gate_nis: float = setting(400.0, lo=1.0, hi=1e6, lo_open=True,
                              doc="NIS gate (chi-square, one degree of freedom)")
    gate_reopen: int = setting(5, integer=True, lo=1, hi=1000,
                               doc="gated readings in a row that re-open a chamber's gate")
    max_gap: float = setting(1.0, lo=0.0, hi=3600.0, unit="s",
                             doc="longest time one step predicts over (at least sample_period)")
    valve_delay: float = valve_delay_setting(DEFAULT_VALVE_DELAY)
    sensor_delay: float = sensor_delay_setting(ROBOT_SENSOR_DELAY)

    def check_rules(self) -> None:
        self.within("max_gap", lo=self.sample_period)


B_RANGE = (0.5, 2.0)
K_RANGE = (0.6, 1.6)
C_RANGE = (0.6, 1.8)
#: the factors' rows in the state and their ranges (the clip and the lost-estimate test both use them)
FACTOR_ROWS = ((1, B_RANGE), (2, K_RANGE), (3, C_RANGE))


NS = 4  # [y, b, k, c], y = (x + 1) / c
# the lowest y: a resting chamber at 4 % of an atmosphere below ambient (the tables start at 5 %). A
# floor in y, not in the gas mass: the gas of a chamber at ambient is x + 1 = c, so a floor x >= -0.04
# would read as a pressure floor p_env (0.96 / c - 1) > 0 once the dead-volume factor falls below 0.96
# (8 kPa at c = 0.89): a venting chamber's estimate would be held kilopascals above its readings, and
# the next update would throw it to the factors' bounds
Y_MIN = 0.96


def _step_function(model: ChamberBank, s: ChamberEKFSettings) -> ca.Function:
    """Single-chamber EKF step (X[4], P[16], u[3], W, z, use, reopen) -> (X+[4], P+[16], h, p, nis,
    h_std, over, lam, x_top, r) with r the reading's signed innovation over its predicted std (before
    any gate re-opening widens it; 0 when not used). The state is ``[y, b, k, c]`` with ``y = (x + 1) / c`` (module doc).
    ``use`` 0 skips the update; a reading whose NIS exceeds ``gate_nis`` (``over`` 1) is gated (not
    used) unless ``reopen`` is 1: then the prior covariance is inflated until the NIS equals the gate
    (at most by INFLATION_MAX) and the reading is used."""
    xs, _, W, b, k, c = model.symbols
    w = model.u  # predict with what the plant was sent: a throttled pump's flow is not a q(1, p)
    xn = model.discrete_expr(s.sample_period, plant_inputs=True)
    fx = ca.Function("fx", [xs, w, W, b, k, c], [xn])
    he, pe, le = model.outputs_expr(xs, W, k, c)
    Ys = ca.SX.sym("Y", NS)
    yo = {xs: Ys[3] * Ys[0] - 1, k: Ys[2], c: Ys[3]}
    po, ho, lo = (ca.substitute([v], list(yo), list(yo.values()))[0] for v in (pe, he, le))
    meas = ca.Function("meas", [Ys, W], [po, ca.jacobian(po, Ys), ho, ca.jacobian(ho, Ys), lo])
    X = ca.SX.sym("X", NS)
    Pv = ca.SX.sym("P", NS * NS)
    wi = ca.SX.sym("wi", 3)
    Wi, z, use, reopen = ca.SX.sym("Wi"), ca.SX.sym("z"), ca.SX.sym("use"), ca.SX.sym("reopen")
    x_now = X[3] * X[0] - 1
    x_pred = fx(x_now, wi, Wi, X[1], X[2], X[3])
    y_pred = (x_pred + 1) / X[3]
    xm = ca.vertcat(y_pred, X[1], X[2], X[3])
    # one row is not the identity: its gradient alone (one reverse sweep, not a 4 x 4 Jacobian)
    A = ca.vertcat(ca.jacobian(y_pred, X), ca.horzcat(ca.DM.zeros(3, 1), ca.DM.eye(3)))
    P = ca.reshape(Pv, NS, NS)
    dx = x_pred - x_now
    # the gas mass's process noise, in y = (x + 1) / c
    Q = ca.diag(ca.vertcat((s.x_abs_std ** 2 + (s.x_rel_std * dx) ** 2) / X[3] ** 2,
                           s.b_rate_std ** 2 * s.sample_period, s.k_rate_std ** 2 * s.sample_period,
                           s.c_rate_std ** 2 * s.sample_period))
    Pm = A @ P @ A.T + Q
    p_pred, Hx, _, _, _ = meas(xm, Wi)
    R = s.noise_std ** 2 + (s.model_rel_std * p_pred) ** 2
    innov = z - p_pred
    S0 = Hx @ Pm @ Hx.T
    gate = s.gate_nis
    over = innov ** 2 / (S0 + R) > gate
    need = ca.fmin(ca.fmax(1.0, (innov ** 2 / gate - R) / ca.fmax(S0, 1e-300)), INFLATION_MAX)
    alpha = ca.if_else(reopen * over > 0, need, 1.0)
    Pm = alpha * Pm
    gated = use * over * (1 - reopen)
    use_eff = use * (1 - gated)
    S = alpha * S0 + R
    K = Pm @ Hx.T / S * use_eff
    xp = xm + K * innov
    IKH = ca.DM.eye(NS) - K @ Hx
    Pp = IKH @ Pm @ IKH.T + K @ K.T * R
    Pp = 0.5 * (Pp + Pp.T)
    p_post, _, h, G, lam = meas(xp, Wi)
    return ca.Function("ekf_bank_step", [X, Pv, wi, Wi, z, use, reopen],
                       [xp, ca.reshape(Pp, NS * NS, 1), h, p_post, innov ** 2 / S * use_eff,
                        ca.sqrt(ca.fmax(G @ Pp @ G.T, 0)), use * over, lam,
                        model.x_top_expr(Wi, xp[2], xp[3]), innov / ca.sqrt(S0 + R) * use])


def _readings(z, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) float readings (Pa) and a mask of entries that are not numbers at all (strings, objects:
    outliers; None is a dropout, NaN)."""
    try:
        if not any(isinstance(v, (str, bytes)) for v in np.ravel(np.asarray(z, dtype=object))):
            return np.asarray(z, dtype=float).reshape(n), np.zeros(n, dtype=bool)
    except (TypeError, ValueError):
        pass
    vals = np.ravel(np.asarray(z, dtype=object))
    if vals.size != n:
        raise ValueError(f"robot_ekf.step: {vals.size} readings for {n} chambers")
    out, bad = np.full(n, np.nan), np.zeros(n, dtype=bool)
    for i, v in enumerate(vals):
        if v is None:
            continue
        if isinstance(v, (str, bytes, bool)):
            bad[i] = True
            continue
        try:
            out[i] = float(v)
        except (TypeError, ValueError):
            bad[i] = True
    return out, bad


class ChamberEKFBank:
    """n per-chamber EKFs stepped together (see module doc).

    ``step(z, w, W, steps=1)``: z (n,) pressure readings Pa (NaN = missing), w the inputs the plant
    was sent during the last period: (3, n) [speed, inlet, outlet] (a throttled pump's speed
    included: its flow is predicted as sent) or (2, n) decisions [supply, outlet] with the pump at
    full speed (see :mod:`hbma_ctrl.models.bank`), W (n,) the
    loads N used over that period, ``steps`` the periods since the last step (bounded by
    ``max_gap``). Returns a dict of (n,) arrays: x, b, h (m, >= 0), p (Pa), h_std (m), lam (the
    membrane's stretch, -), nis, used (bool), outlier (bool: out of bounds or gated), beyond (bool:
    the gas mass at the top of the model's tables, where the height and stretch are the tables' last
    and the membrane may be anywhere above), lost (bool: beyond, or a factor at the edge of its
    range: the estimate says nothing reliable), k_std, and the factors b, k, c (-).
    """

    def __init__(self, model: ChamberBank, n: int, settings: ChamberEKFSettings | None = None):
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"robot_ekf.n = {n!r} must be an integer >= 1")
        self.settings = (settings or ChamberEKFSettings()).validate()
        self.model = model
        self.n = n
        step = model.cached(("ekf", self.settings), lambda: _step_function(model, self.settings))
        self._fun = model.mapped(step, n)
        # one call of the mapped step per period, through preallocated buffers (numpy -> DM
        # conversion of seven arguments costs more than the compiled map itself)
        self._call = FastFunction(self._fun, compile=False)
        self.X = None
        self.P = None
        self.last: dict = {}
        self.resets = 0
        s = self.settings
        self._bounds = physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel)
        self.max_steps = max(1, int(round(s.max_gap / s.sample_period)))
        self._gated_run = np.zeros(n, dtype=int)
        self.counts = {"outliers_bound": 0, "gated": 0, "gate_reopened": 0, "missing": 0, "time_jumps": 0,
                       "beyond_tables": 0, "factor_at_bound": 0}
        self._timing = CommandTiming(s.sample_period, s.valve_delay, s.sensor_delay)

    def _prior_cov(self) -> np.ndarray:
        """The initial covariance of one chamber (4 x 4)."""
        s = self.settings
        # y = (x + 1) / c is what a resting chamber's pressure gives (p = p_env (y - 1)): the first
        # reading pins it, independently of the dead volume
        sy = max(s.noise_std / self.model.actuator.p_env, 1e-3)
        return np.diag([sy ** 2, s.b0_std ** 2, s.k0_std ** 2, s.c0_std ** 2])

    def reset(self, p0, mask=None) -> None:
        """Start the filters (all, or those in ``mask``) at rest from readings p0 (n,) Pa (a flat
        membrane: y = 1 + p / p_env, factors at their priors)."""
        if mask is not None and self.X is not None:
            keep_X, keep_P = self.X.copy(), self.P.copy()
            self.reset(p0)
            m = np.asarray(mask, dtype=bool)
            self.X = np.where(m[None, :], self.X, keep_X)
            self.P = np.where(m[None, :], self.P, keep_P)
            return
        self.X = self.rest_state(p0)
        self.P = np.repeat(self._prior_cov().reshape(16, 1), self.n, 1)

    def rest_expr(self, p0) -> tuple:
        """:meth:`rest_state` and the prior covariance as casadi expressions for readings p0 (1 x n, Pa,
        already read as 0 where out of the physical range): (X 4 x n, P 16 x n), what a generated loop's
        restart of a filter writes."""
        one = ca.DM.ones(1, self.n)
        y0 = ca.fmax(1.0 + p0 / self.model.actuator.p_env, Y_MIN)
        P0 = ca.DM(self._prior_cov().reshape(NS * NS, 1, order="F"))
        return ca.vertcat(y0, self.settings.b0 * one, one, one), ca.repmat(P0, 1, self.n)

    @staticmethod
    def gas_mass(X: np.ndarray) -> np.ndarray:
        """The gas mass x (the model's, scaled: see the module doc) of filter states X (4, n)."""
        return X[3] * X[0] - 1

    def rest_state(self, p0) -> np.ndarray:
        """The state (4, n) the filters start from at rest with readings p0 (n,) Pa: y = 1 + p / p_env of
        a flat membrane (a reading out of the physical range read as 0), the factors at their priors."""
        p0 = np.asarray(p0, dtype=float).reshape(self.n)
        lo, hi = self._bounds
        p0 = np.where(np.isfinite(p0) & (p0 >= lo) & (p0 <= hi), p0, 0.0)
        y0 = np.maximum(1.0 + p0 / self.model.actuator.p_env, Y_MIN)
        return np.vstack([y0, np.full(self.n, self.settings.b0), np.ones(self.n), np.ones(self.n)])

    def step(self, z, w, W, steps: int = 1) -> dict:
        """One step after ``steps`` periods (see the class doc)."""
        z, not_number = _readings(z, self.n)
        s = self.settings
        lo, hi = self._bounds
        nan = np.isnan(z) & ~not_number
        outlier = not_number | np.isinf(z) | (np.isfinite(z) & ((z < lo) | (z > hi)))
        self.counts["missing"] += int(nan.sum())
        self.counts["outliers_bound"] += int(outlier.sum())
        if self.X is None:
            self.reset(np.where(outlier, np.nan, z))
        use = (np.isfinite(z) & ~outlier & (z < s.sensor_range)).astype(float)
        zz = np.where(use > 0, z, 0.0)
        Wv = self.model.clip_load(np.asarray(W, dtype=float).reshape(self.n))
        wv = np.asarray(w, dtype=float)
        if wv.size == 2 * self.n:  # decisions [a, o]: the pump at full speed, inlet duty a
            wv = wv.reshape(2, self.n)
            wv = np.vstack([np.ones((1, self.n)), wv])
        wv = wv.reshape(3, self.n)
        k = int(steps)
        if k < 1:
            raise ValueError(f"robot_ekf.step: steps = {steps!r} must be an integer >= 1")
        if self._timing.active:
            # the command as the chambers feel it and the sensors see it, averaged over the k periods
            wv = self._timing.acting(wv, k)
        jump = k > self.max_steps
        if jump:
            k = self.max_steps
            self.counts["time_jumps"] += 1
        zero = np.zeros(self.n)
        for _ in range(k - 1):  # the periods without a reading: predict only
            out = self._call(self.X, self.P, wv, Wv, zero, zero, zero)
            self.X, self.P = self._guard(self._cols(out[0], NS), self._cols(out[1], NS * NS), zz, out[8])
        if jump:
            self.P = self.P + self._prior_cov().reshape(16, 1)
        reopen = (self._gated_run >= s.gate_reopen - 1).astype(float)
        out = self._call(self.X, self.P, wv, Wv, zz, use, reopen)
        over = out[6] > 0.5
        gated = over & (reopen == 0)
        used = (use > 0) & ~gated
        nis = out[4].copy()
        reopened = over & (reopen > 0)
        # the gate stays open (the run goes on) until a reading passes it unaided
        self._gated_run = np.where(over, self._gated_run + 1, np.where(use > 0, 0, self._gated_run))
        self.counts["gated"] += int(gated.sum())
        self.counts["gate_reopened"] += int(reopened.sum())
        resets = self.resets
        Xn = self._cols(out[0], NS)
        # the gas mass at or past the top of the model's tables (for this chamber's factors): the model
        # cannot say where such a membrane is (its height and stretch are the tables' last), only that
        # it holds that much gas
        beyond = self.gas_mass(Xn) >= out[8]
        # a factor at the edge of its range: the filter explains the readings with a chamber far outside
        # any plausible mismatch (a far-branch membrane read as a near-branch one drives the flow factor
        # to its floor and the modulus to its ceiling while the truth grows on)
        at_bound = np.zeros(self.n, dtype=bool)
        for row, (lo, hi) in FACTOR_ROWS:
            at_bound |= (Xn[row] <= lo) | (Xn[row] >= hi)
        self.counts["beyond_tables"] += int(beyond.sum())
        self.counts["factor_at_bound"] += int(at_bound.sum())
        self.X, self.P = self._guard(Xn, self._cols(out[1], NS * NS), zz, out[8])
        X = self.X
        h, p, h_std, lam = out[2].copy(), out[3].copy(), out[5].copy(), out[7].copy()
        if self.resets > resets:  # a restarted filter reports its restart, not the diverged step
            bad = ~(np.isfinite(h) & np.isfinite(p) & np.isfinite(h_std))
            for i in np.nonzero(bad)[0]:
                hi, pi, li = self.model.out(self.gas_mass(X[:, i]), Wv[i], X[2, i], X[3, i])
                h[i], p[i], lam[i], h_std[i] = float(hi), float(pi), float(li), np.nan  # unknown right after a restart
        self.last = {"x": self.gas_mass(X), "b": X[1].copy(), "k": X[2].copy(), "c": X[3].copy(),
                     "h": np.maximum(h, 0.0), "p": p, "h_std": h_std, "lam": lam, "beyond": beyond,
                     "lost": beyond | at_bound,
                     "k_std": np.sqrt(np.maximum(self.P[2 * NS + 2], 0.0)), "nis": nis, "r": out[9].copy(),
                     "used": used, "outlier": outlier | gated}
        return self.last

    def _cols(self, flat: np.ndarray, rows: int) -> np.ndarray:
        """A mapped output (column-major, one column per chamber) as a (rows, n) array (a copy)."""
        return flat.reshape(self.n, rows).T.copy()

    def _guard(self, X: np.ndarray, Pn: np.ndarray, zz: np.ndarray,
               x_top: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Clip the states to their ranges (the gas mass to ``x_top``, the tables' top for each chamber's
        factors); a diverged filter restarts from its reading (``resets``)."""
        bad = ~(np.all(np.isfinite(X), 0) & np.all(np.isfinite(Pn), 0))
        self.resets += int(bad.sum())
        for row, rng in FACTOR_ROWS:
            X[row] = np.clip(X[row], *rng)
        # the gas mass x = c y - 1 at the tables' top in x1, not in x: a chamber with a larger dead
        # volume holds more gas at the same shape, and a clip at the nominal top pinned such an
        # estimate at a mid height while the membrane grew on (a 3-layer run: estimate 2.8 mm, truth
        # 20 mm and rising, pump on)
        top = np.where(np.isfinite(x_top), x_top, self.model.x_max)
        X[0] = np.clip(X[0], Y_MIN, (top + 1) / X[3])
        self.X, self.P = X, Pn
        if bad.any():
            self.reset(zz, bad)
        return self.X, self.P

    def stats(self) -> dict:
        """Counts since construction (over all chambers): ``outliers`` (readings not used as
        implausible: out of bounds or gated), ``outliers_bound``, ``gated``, ``gate_reopened``,
        ``missing`` (dropouts), ``time_jumps`` (gaps cut to max_gap), ``beyond_tables`` (chamber
        steps whose gas mass reached the top of the model's tables), ``factor_at_bound`` (chamber steps
        with a factor at the edge of its range) and ``resets``."""
        c = dict(self.counts)
        c["outliers"] = c["outliers_bound"] + c["gated"]
        c["resets"] = int(self.resets)
        return c


def bank_step_function(bank: ChamberEKFBank, name: str = "ekf_bank") -> ca.Function:
    """One normal step of ``bank`` (one period after the last, the bank started) as ONE casadi Function,
    what :meth:`ChamberEKFBank.step` does around its mapped call included, so a generated loop needs no
    Python (its bits are the bank's to rounding, ``tests/test_robot_loop_blocks.py``):

        ekf_bank(X[4 x n], P[16 x n], w[3 x n], W[1 x n], z[1 x n], gated_run[1 x n])
            -> (X_next, P_next, gated_run_next, h, p, h_std, lam, beyond, lost, nis, r, used,
                outlier, reset, k_std)   (every output 1 x n but the first two)

    ``w`` is the command acting over the period (after the valves' and sensors' delays:
    :func:`hbma_ctrl.models.actuation.acting_function` per chamber), ``W`` the loads (N; clipped to the
    tables' range here), ``z`` the readings (Pa; NaN = missing, +-inf or out of the physical bounds =
    outlier, at or above the sensor range = not used), ``gated_run`` the gated readings in a row per
    chamber. The flags (beyond, lost, used, outlier, reset: a diverged filter restarted from its
    reading) are 0 / 1; a restarted filter's ``h_std`` is NaN, as the bank's. The counts of
    :meth:`ChamberEKFBank.stats` follow from the flags. Not here: the first step (the bank starts from
    the readings) and a step after a gap of several periods."""
    s, n, model = bank.settings, bank.n, bank.model
    step = model.cached(("ekf", s), lambda: _step_function(model, s)).map(n)
    lo, hi = bank._bounds
    X, P = ca.SX.sym("X", NS, n), ca.SX.sym("P", NS * NS, n)
    w, W, z, run = ca.SX.sym("w", 3, n), ca.SX.sym("W", 1, n), ca.SX.sym("z", 1, n), ca.SX.sym("gated_run", 1, n)
    _, outlier, _, use = classify_expr(z, s.sensor_range, lo, hi)
    zz = ca.if_else(use, z, 0.0)
    Wc = model.clip_load(W)
    reopen = run >= s.gate_reopen - 1
    out = step(X, P, w, Wc, zz, use, reopen)
    over = out[6] > 0.5
    gated = ca.logic_and(over, ca.logic_not(reopen))
    used = ca.logic_and(use, ca.logic_not(gated))
    run_next = ca.if_else(over, run + 1, ca.if_else(use, 0.0, run))
    Xn, Pn, x_top = out[0], out[1], out[8]
    beyond = Xn[3, :] * Xn[0, :] - 1 >= x_top
    at_bound = 0
    for row, (a, b) in FACTOR_ROWS:
        at_bound = ca.logic_or(at_bound, ca.logic_or(Xn[row, :] <= a, Xn[row, :] >= b))
    # the guard: factors clipped, the gas mass to the tables' top; a diverged filter restarts at rest
    # from its reading (prior covariance)
    bad = 0
    for v in [Xn[i, :] for i in range(NS)] + [Pn[i, :] for i in range(NS * NS)]:
        bad = ca.logic_or(bad, ca.logic_not(is_finite(v)))
    rows = [Xn[i, :] for i in range(NS)]
    for row, (a, b) in FACTOR_ROWS:
        rows[row] = ca.fmin(ca.fmax(rows[row], a), b)
    top = ca.if_else(is_finite(x_top), x_top, model.x_max)
    rows[0] = ca.fmin(ca.fmax(rows[0], Y_MIN), (top + 1) / rows[3])
    X_rest, P_rest = bank.rest_expr(zz)
    X2 = ca.vertcat(*[ca.if_else(bad, X_rest[i, :], r1) for i, r1 in enumerate(rows)])
    P2 = ca.vertcat(*[ca.if_else(bad, P_rest[i, :], Pn[i, :]) for i in range(NS * NS)])
    h, p, h_std, lam = out[2], out[3], out[5], out[7]
    # a restarted filter reports its restart (the model's outputs at its new state, h_std unknown)
    # where the diverged step's outputs are not finite
    outputs_finite = ca.logic_and(ca.logic_and(is_finite(h), is_finite(p)), is_finite(h_std))
    redo = ca.logic_and(bad, ca.logic_not(outputs_finite))
    restart = [model.outputs_expr(X2[3, i] * X2[0, i] - 1, Wc[i], X2[2, i], X2[3, i]) for i in range(n)]
    h, p, lam = (ca.if_else(redo, ca.horzcat(*[o[j] for o in restart]), v) for j, v in enumerate((h, p, lam)))
    h_std = ca.if_else(redo, ca.DM.nan(1, n), h_std)
    k_std = ca.sqrt(ca.fmax(P2[2 * NS + 2, :], 0.0))
    h = ca.if_else(h < 0, 0.0, h)  # np.maximum(h, 0): a NaN passes (fmax would make it 0)
    return ca.Function(name, [X, P, w, W, z, run],
                       [X2, P2, run_next, h, p, h_std, lam, beyond, ca.logic_or(beyond, at_bound),
                        out[4], out[9], used, ca.logic_or(outlier, gated), bad, k_std],
                       ["X", "P", "w", "W", "z", "gated_run"],
                       ["X_next", "P_next", "gated_run_next", "h", "p", "h_std", "lam", "beyond", "lost", "nis",
                        "r", "used", "outlier", "reset", "k_std"])
