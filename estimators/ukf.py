"""Unscented Kalman filter on the same model and state as the EKF, for the speed/accuracy trade.

Same state ``[m, W, b, k, c]``, same modes (sticky rest, lift-off and load-change detectors), same
measurement handling and guards as :class:`hbma_ctrl.estimators.ekf.EKF`; only the propagation of the mean
and covariance differs: 2n + 1 = 11 scaled sigma points (filterpy's
:class:`~filterpy.kalman.MerweScaledSigmaPoints`, alpha 0.5, beta 2, kappa 0: ``UKF_ALPHA``) are pushed
through the discrete model in one batched casadi call (the model Function ``map``-ped over the
points and compiled), and the update uses the propagated points' pressures (no Jacobians). The
square root is a guarded Cholesky factorisation (symmetrised, eigenvalue-floored, never
unchecked), the update a linear solve, the covariance re-guarded after every step. The output
covariance (h1, h2, h, F, p) is mapped by the implicit-function Jacobian at the mean, as in the EKF.

filterpy is wrapped (its sigma-point generator and :func:`~filterpy.kalman.unscented_transform`),
not subclassed.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform

from hbma_ctrl.estimators.common import STATE_SCALE, FilterSettings, guard_cov
from hbma_ctrl.estimators.ekf import EKF
from hbma_ctrl.estimators.ekf_step import observer_functions
from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.chamber import NX, OUT_NAMES

__all__ = ["UKF", "UKFSettings", "UKF_ALPHA", "UKF_BETA", "UKF_KAPPA"]

UKF_ALPHA, UKF_BETA, UKF_KAPPA = 0.5, 2.0, 0.0  # spread, Gaussian prior, secondary scaling
_P = OUT_NAMES.index("p")


class UKFSettings(FilterSettings):
    """UKF settings: the fields of :class:`hbma_ctrl.estimators.common.FilterSettings` (documented there)."""


def _guarded_sqrt(floor: float):
    def sqrt(P: np.ndarray) -> np.ndarray:
        G = guard_cov(P, floor, STATE_SCALE)
        return np.linalg.cholesky(G).T  # filterpy wants the upper factor (rows are offsets)
    return sqrt


class UKF(EKF):
    """Unscented Kalman filter with the :class:`~hbma_ctrl.estimators.ekf.EKF` step API (SI)."""

    compiled_step = False  # its predict and update are the sigma points', not the EKF's Function

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings | None = None):
        super().__init__(actuator, pneumatics, settings or UKFSettings())
        s = self.settings
        self._points = MerweScaledSigmaPoints(NX, UKF_ALPHA, UKF_BETA, UKF_KAPPA,
                                              sqrt_method=_guarded_sqrt(max(s.cov_floor, 1e-14)))
        prop = observer_functions(actuator, pneumatics, s)[3]
        self._nsig = 2 * NX + 1
        self._prop = FastFunction(prop.map(self._nsig), s.compile, HOT_OPT, HOT_FLAGS)
        self._sig_p: np.ndarray | None = None
        self._sig_x: np.ndarray | None = None

    def _predict(self, u: np.ndarray) -> None:
        s = self.settings
        sig = self._points.sigma_points(self.x, self.P)  # (2n+1, n)
        n = self._nsig
        out = self._prop(sig.T, np.repeat(self.s[:, None], n, 1), np.repeat(u[:, None], n, 1),
                         np.repeat(self.theta[:, None], n, 1), np.full((1, n), float(self.resting)))
        X = out[0].reshape(NX, n, order="F").T.copy()
        Y = out[2].reshape(len(OUT_NAMES), n, order="F")
        S2 = out[1].reshape(2, n, order="F")
        if not np.all(np.isfinite(X)) or not np.all(np.isfinite(Y[_P])):
            # fall back on the EKF predict for this sample (e.g. a point across a fold)
            self._sig_p = None
            return super()._predict(u)
        xm = X.T @ self._points.Wm
        rel = 0.0 if self.resting else s.flow_rel_std
        q = s.walk_var()
        q[0] += (rel * abs(xm[0] - self.x[0])) ** 2
        x, P = unscented_transform(X, self._points.Wm, self._points.Wc, np.diag(q))
        self.x, self.P = x, guard_cov(P, s.cov_floor)
        self._sig_x, self._sig_p = X, Y[_P].copy()
        self._p_pred = float(Y[_P] @ self._points.Wm)
        self.s = S2[:, 0].copy()  # the mean point's shape: the next warm start
        if not self.resting and Y[OUT_NAMES.index("rest"), 0] > 0.5:
            self.resting = True
            self._events.add("touch_down")

    def _update(self, z: float, R: float) -> float:
        if self._sig_p is None:
            return super()._update(z, R)
        Wc = self._points.Wc
        dz = self._sig_p - self._p_pred
        dx = self._sig_x - self.x
        S = float(Wc @ (dz * dz)) + R
        if not S > 0:
            raise FloatingPointError(f"innovation variance {S} is not positive")
        Pxz = (Wc * dz) @ dx  # (n,)
        K = np.linalg.solve(np.array([[S]]), Pxz[None, :])[0] * self._keep()
        innov = z - self._p_pred
        self._innov = innov
        self.x = self.x + K * innov
        # P - K S K^T only for the optimal gain; with held states (keep), the general form
        # P - K Pxz^T - Pxz K^T + K S K^T
        self.P = guard_cov(self.P - np.outer(K, Pxz) - np.outer(Pxz, K) + S * np.outer(K, K),
                           self.settings.cov_floor)
        self._sig_p = None
        return innov / np.sqrt(S)
