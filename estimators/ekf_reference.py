"""The EKF's step on its separate-call path (:class:`ReferenceSteps`, a base of :class:`hbma_ctrl.estimators.ekf.EKF`).

The normal step is one compiled Function (:mod:`hbma_ctrl.estimators.ekf_step`); these methods are the path it
falls back to for the rare steps the Function flags (a model failure, a covariance at its floor, a
re-opened gate, a lift-off replayed from past samples) and what ``EKF.step_reference`` runs: the
prediction over k periods and the gated update (the model's predict and update Functions, called one
by one), the lift-off and load-change detectors, the replay of the samples since a detected lift-off,
the covariance bookkeeping of the load state and of a time gap; the step ends with the compiled step's
own finish (:func:`hbma_ctrl.estimators.ekf_step._finish_function`: the flat-load bound, clamps, outputs
and their covariance, touch-down). The state, settings and Functions are the EKF's (see its module
docstring for the model and the modes).
"""

from __future__ import annotations

import math

import numpy as np

from hbma_ctrl.estimators.common import MEAS_SATURATED, guard_cov, nis_gate
from hbma_ctrl.estimators.ekf_step import (
    CENSOR_SIGMAS,
    EXCESS_DRIFT,
    EXCESS_THRESHOLD,
    LIFT_LOAD_ABS_STD,
    LIFT_RISE_DRIFT,
    LIFT_START_DRIFT,
    NO_LOAD_SIGMAS,
)
from hbma_ctrl.core.interfaces import Estimate
from hbma_ctrl.models.chamber import NX, OUT_NAMES, REST_EPS

__all__ = ["ReferenceSteps", "OUTPUT_INDEX", "OUTPUT_KEYS"]

#: index of each observer output (``OUT_NAMES``) in the outputs Function's vector
OUTPUT_INDEX = {n: i for i, n in enumerate(OUT_NAMES)}
_Y = OUTPUT_INDEX
_KEEP_ALL = np.ones(NX)
_KEEP_NO_FACTORS = np.array([1.0, 1.0, 0.0, 0.0, 0.0])  # hold b, k and c
#: outputs whose covariance the filters report (rows of ``output_cov``)
OUTPUT_KEYS = ("h1", "h2", "h", "F", "p")


class ReferenceSteps:
    """The EKF's separate-call step methods (module doc); mixed into :class:`hbma_ctrl.estimators.ekf.EKF`."""

    def _predict(self, u: np.ndarray) -> None:
        s = self.settings
        qv = self._qv_rest if self.resting else self._qv_move  # resting, the flow error is b's job
        hold = float(self.resting)
        out = self._pred(hold, self.x, self.s, u, self._theta_arg(self._pred), hold, self.P, qv)
        xn = out[0].copy()
        Pn = out[5].reshape(NX, NX, order="F").copy()
        if not math.isfinite(float(xn.sum() + out[3].sum() + Pn.sum())):  # any NaN/inf propagates
            # the projection failed (e.g. across a fold): hold the state, widen the covariance
            self.P = guard_cov(self.P + np.diag([(1e-7) ** 2, s.load_std ** 2, 0.0, 0.0, 0.0]), s.cov_floor)
            self._A_flat = np.eye(NX).ravel()
            self._events.add("model_failure")
            return
        self._A_flat = out[1].copy()
        self.s = out[2].copy()
        self._p_pred = float(out[3][_Y["p"]])
        self._H = out[4].copy()
        if not self.resting and out[3][_Y["rest"]] > 0.5:
            self.resting = True  # touch-down: the contact model reached the flat membrane
            self._events.add("touch_down")
        self.x = xn
        self.P = Pn if out[6][0] > 0 else guard_cov(Pn, s.cov_floor)

    def _update(self, z: float, R: float) -> float:
        innov = z - self._p_pred
        out = self._upd(self.x, self.P, self._H, innov, R, self.settings.cov_floor, self._keep())
        S = float(out[2][0])
        if not (S > 0 and math.isfinite(S)):
            raise FloatingPointError(f"estimator: innovation variance {S} is not positive")
        self.x = out[0].copy()
        P = out[1].reshape(NX, NX, order="F").copy()
        self.P = P if out[3][0] > 0 else guard_cov(P, self.settings.cov_floor)
        self._innov = innov
        self._sqrt_S = math.sqrt(S)
        return innov / self._sqrt_S

    def _keep(self) -> np.ndarray:
        """Which states an update may move (1) or must hold (0)."""
        if self.resting and self.x[1] < REST_EPS:
            # flat with no load is the model's stand-in for the singular origin (a free membrane
            # is never flat at positive pressure): its flat dynamics lack the cap's compliance,
            # so its innovations say nothing about the pump or the dead volume
            return _KEEP_NO_FACTORS
        return _KEEP_ALL

    def _meas_var(self, p: float) -> float:
        # the flat membrane's pressure is the gas law in V0 (no modulus): sensor noise only
        s = self.settings
        rel = 0.0 if self.resting else s.model_rel_std
        return s.noise_std ** 2 + (rel * max(p, 0.0)) ** 2

    def _advance(self, t: float, measurement, kind: str, u: np.ndarray, k: int, detect: bool,
                 jump: bool = False) -> None:
        """Predict k periods with u, then update with the measurement (and run the detectors)."""
        s = self.settings
        self._pumping = bool(u[0] > 0.0 and u[1] > 0.0)
        for _ in range(k):
            self._predict(u)
        if jump:
            self._widen_after_gap()
        self.t = float(t)
        self.last_nis = None
        self.last_innovation = None
        if kind == "ok":
            z = float(measurement)
            R = self._meas_var(self._p_pred)
            nis, alpha = nis_gate(z - self._p_pred, float(self._H @ self.P @ self._H), R, s.gate_nis)
            reopen = False
            if alpha > 1.0:
                self._gated += 1
                if self._gated < s.gate_reopen:
                    # an outlier: predict only (its innovation would drag the state off by the
                    # reading's error, e.g. -1e9 Pa -> a 60 mm cap for seconds)
                    self._events.add("gated")
                    self.last_nis = nis
                    if detect:
                        self.counts["gated"] += 1
                    return
                # gate_reopen in a row: a real transient, not a glitch; use it with the prior widened
                # (the gate stays open until a reading passes it unaided)
                self.P = guard_cov(self.P * alpha, s.cov_floor)
                self._events.add("gate_reopened")
                if detect:
                    self.counts["gate_reopened"] += 1
                reopen = True
            else:
                self._gated = 0
            prior = (self.x.copy(), self.P.copy(), self._p_pred)
            r = self._update(z, R)
            self.last_innovation = r
            self.last_nis = r * r
            if detect and not reopen and self._detect(r):
                # a load change: redo this update with the load's variance widened, so the jump
                # goes to the load rather than to the gas mass and the modulus
                self.x, self.P, self._p_pred = prior
                self.P[1, 1] += s.change_std ** 2
                self._update(z, R)
        elif kind == MEAS_SATURATED and self._p_pred < s.sensor_range:
            # one-sided: the true pressure is at least the range; pull the prediction up to it.
            # On either branch: past the model's limit point (dp/dm < 0) the pull takes gas out
            # and stiffens the membrane, which is what a rig still saturated there says (its
            # peak is higher; left alone the model runs away along its far branch)
            self._update(s.sensor_range, s.saturation_std ** 2 + self._meas_var(s.sensor_range))

    def _replay_from_snapshot(self, snap: tuple, replay: list) -> None:
        """Re-filter the samples ``replay`` since the posterior ``snap`` with the membrane lifted:
        since the detector's sum left zero, or (a lift-off the factors' ratio showed) since the last
        posterior at ambient pressure.

        The detector needs several samples to be sure; filtered as flat, those samples push the
        lifted membrane's extra volume into the flow factor and the modulus (which then bias the
        height for as long as nothing excites them again). From the posterior before the lift-off,
        the lift-off is applied there and the samples are replayed with the contact model."""
        if not replay:
            return
        W, PW = float(self.x[1]), float(self.P[1, 1])
        self.x, self.P, self.s, self.t, self._p_pred, self._H, self._p_post = snap
        self.x, self.P, self.s = self.x.copy(), self.P.copy(), self.s.copy()
        self._lift_off(detected=False, load=(W, PW))
        events = self._events
        for (t, z, kind, u, k) in replay:
            self._advance(t, z, kind, u, k, detect=False)
            self._finish()
        self._events = events | {"lift_off_replayed"}
        self._snap, self._replay, self._rise, self._rise_replay = None, [], None, []

    def _detect(self, r: float) -> bool:
        """Lift-off detector (resting) and load-change detector (contact) on the innovation r.

        Returns True when a load change was declared (the caller redoes the update)."""
        s = self.settings
        if self.resting:
            self._excess = 0.0
            if self._p_pred + self._innov > s.sensor_range - CENSOR_SIGMAS * s.noise_std:
                return False  # a reading near the range is a sample biased low (ekf_step.CENSOR_SIGMAS): hold
            if not self._pumping or self._p_pred <= self._p_post:
                # the pump is not filling the chamber (venting, holding): a membrane cannot lift
                # off; a shortfall here is the vent model's error near zero pressure
                self._lift = self._lift_start = 0.0
                return False
            if self._lift_start == 0.0:
                # a lift-off seen from here on happened after the last posterior: mid-interval,
                # up to the reading (the flat prediction overshoots a lifted membrane: a free cap
                # at the pump's first sample reads 0 kPa where a flat chamber would reach 1 kPa).
                # The time comes from a second sum with a larger drift: the detector's own sum can
                # linger above zero for a while on the flow factor's slow learning, and its start
                # then dates the lift-off far too early (a 200 g load taken as 0.1 N)
                z = self._p_pred + self._innov
                self._p_lift = 0.5 * (self._p_post + min(self._p_pred, z))
            self._lift_start = max(0.0, self._lift_start - r - LIFT_START_DRIFT)
            # the drift grows with the flat prediction's rise (ekf_step.LIFT_RISE_DRIFT)
            drift = s.lift_drift + LIFT_RISE_DRIFT * max(self._p_pred - self._p_post, 0.0) / self._sqrt_S
            self._lift = max(0.0, self._lift - r - drift)
            if self._lift > s.lift_threshold:
                self._lift = self._lift_start = 0.0
                if self._lift_load() < self._lift_floor:
                    # the load's prior rules it out (ekf_step.LIFT_PRIOR_SIGMAS): stay flat
                    self._events.add("lift_off_implausible")
                    return False
                self._lift_off(detected=True)
                # replay only a no-load lift-off (it starts at zero pressure, so the whole
                # detection delay was filtered as flat); a loaded one's sum may have started on
                # the flow factor's early learning, and a lift-off put there contradicts the data
                if self._snap is not None and self.x[1] == 0.0:
                    self._replay_now = (self._snap, self._replay)
            elif self._lift_floor == 0.0 and self.x[2] < self._ratio_min * self.x[4]:
                # a flat chamber fits the readings only with b / c far below its prior: the membrane
                # has lifted (ekf_step.FLAT_RATIO_SIGMAS), with no load to date; re-filtered from
                # the last posterior at ambient pressure, before the factors took up the shortfall
                self._lift = self._lift_start = 0.0
                self._lift_off(detected=False, load=(0.0, LIFT_LOAD_ABS_STD ** 2))
                self._events.add("lift_off_ratio")
                if self._rise is not None:
                    self._replay_now = (self._rise, self._rise_replay)
        else:
            self._cusum = max(0.0, self._cusum + r * r - s.change_drift)
            # the excess sum (ekf_step.EXCESS_THRESHOLD): a pressure rising persistently above the
            # contact model's, as after a false lift-off
            rising = self._p_pred > self._p_post
            self._excess = max(0.0, self._excess + r - EXCESS_DRIFT) if rising else 0.0
            excess = rising and self._excess > EXCESS_THRESHOLD
            if self._cusum > s.change_threshold or excess:
                self._cusum = self._excess = 0.0
                self._events.add("load_change")
                if excess:
                    self._events.add("load_excess")
                return True
        return False

    def _lift_load(self) -> float:
        """The load (N) of a detected lift-off: the membrane lifted when the detector's sum started
        to grow, W = pi r1^2 p then (at most the flat chamber's pressure now)."""
        out = self._outf(1.0, self.x, self.s, self._theta_arg(self._outf), 1.0, self.P)
        return self.model.area * max(min(float(out[1][_Y["p"]]), self._p_lift), 0.0)

    def _lift_off(self, detected: bool, load: tuple | None = None) -> None:
        """Leave rest. ``detected``: the load is set from the lift-off pressure; ``load`` = (W, var):
        set it to that (a replay re-applies the detected load at the earlier lift-off point)."""
        s = self.settings
        if load is None and detected:
            W = self._lift_load()
            W_res = self.model.area * NO_LOAD_SIGMAS * s.noise_std
            # a lift-off within a few sensor sigmas of zero pressure cannot be told from a free
            # membrane (no load): start from none, with the resolution as the spread -- a load
            # taken as p_lift there is a phantom that bends the cap into a contact shape
            load = (0.0 if W < W_res else W, (s.lift_load_rel_std * W) ** 2 + LIFT_LOAD_ABS_STD ** 2)
        if load is not None:
            self._decouple(1, load[0], load[1])
        self.resting = False
        self._cusum = 0.0
        self._events.add("lift_off")

    def _decouple(self, i: int, mean: float, var: float) -> None:
        """Set state i to ``mean`` with variance ``var``, uncorrelated with the others (a re-start
        of that component: its old correlations no longer hold)."""
        self.x[i] = mean
        P = self.P.copy()
        P[i, :] = P[:, i] = 0.0
        P[i, i] = var
        self.P = guard_cov(P, self.settings.cov_floor)

    def _widen_after_gap(self) -> None:
        """After a bounded time jump: add the initial spread of every state (the commands and loads
        during the gap are unknown; the next readings pin the gas mass again)."""
        s = self.settings
        self.P = guard_cov(self.P + np.diag(s.prior_var()), s.cov_floor)

    def _finish(self) -> Estimate:
        """The step's end, the compiled step's own (:func:`hbma_ctrl.estimators.ekf_step._finish_function`):
        the flat-load bound, the clamps, the outputs and their covariance, touch-down."""
        flags = self._events
        out = self._finish_fn(self.x, self.P, self.s, self._theta_arg(self._finish_fn), float(self.resting),
                              float("touch_down" in flags), float(self._pumping), float(MEAS_SATURATED in flags))
        x, P, s, y, est, std, C, H, resting, lift_b, clamped, td, not_conv = out
        if lift_b[0] > 0.5:
            self._cusum = 0.0
            flags.add("lift_off")
        self.resting = bool(resting[0] > 0.5)
        for name, raised in (("clamped", clamped), ("touch_down", td), ("not_converged", not_conv),
                             ("resting", resting)):
            if raised[0] > 0.5:
                flags.add(name)
        if not self.resting:
            # the ratio test holds only until the membrane first leaves rest: the factors' posterior
            # is no longer the prior its threshold was set from (ekf_step.FLAT_RATIO_SIGMAS)
            self._ratio_min = 0.0
        self.x = x.copy()
        self.P = P.reshape(NX, NX, order="F").copy()
        self.s = s.copy()
        self._p_pred = self._p_post = float(y[_Y["p"]])
        self._H = H.copy()
        self.last_output_cov = C.reshape(5, 5, order="F").copy()
        h1, h2, h, F, p = est.tolist()
        return Estimate(t=self.t, h1=h1, h2=h2, h=h, F=F, p=p, mean=self.x.copy(), cov=self.P.copy(),
                        state_names=self.state_names, std=dict(zip(OUTPUT_KEYS, std.tolist())), flags=frozenset(flags))
