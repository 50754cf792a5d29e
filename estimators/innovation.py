"""Innovation tests of a filter run: does the model's form fit the plant? (dimensionless statistics)

A consistent Kalman filter's normalised innovations ``r_k = nu_k / sqrt(S_k)`` are white with unit
variance. The usual check, the NIS over a window (``mean r^2``, chi-square with n degrees of freedom
over n), does not see a model-form error here: the filter's random-walk factor states (pump flow,
modulus, dead volume) and the gas mass's process noise absorb a wrong membrane law, and the model
error term in the measurement variance (``model_rel_std``) keeps ``r`` small (the cap EKF's NIS is
0.68 on the exact rig, 0.85 on its own cap rig). What the absorbing leaves is a bias that persists
for a while: runs of innovations of one sign, small against their variance but long.

:func:`window_mean_stat` is the statistic that sees it: over a sliding window of n valid samples,

    T = (sum r)^2 / sum r^2

a self-normalised mean (the scale of r, i.e. the filter's own S, cancels: a filter over- or
under-confident by a constant factor scores the same). For white Gaussian innovations of any
variance, T / n ~ Beta(1/2, (n - 1)/2) exactly (the share of a chi-square's one mean direction in its
n directions), close to chi-square(1) for large n: :func:`window_mean_bound`. A persistent bias b
in innovations of spread s raises T to about n b^2 / (b^2 + s^2).

:func:`innovation_test` scores one run: the largest T over its windows against a threshold. On the
rigs simulated here the cap EKF's innovations are not white even on its own cap rig (the platform's
dynamics, the lift-off detector's delay and the factors' learning leave runs of their own), so the
white-noise bound flags most runs (58 % of the cap EKF's 150 protocol trials on the cap rig); the
default ``threshold`` is therefore calibrated on the cap rig's protocol (about its 95th percentile over
the 150 trials, noise seed 0), i.e. it flags what the filter's own model form does not explain.
Measured (protocol, 150 trials, ``innovation_flag_rate`` in the estimator metrics): cap EKF on the cap
rig 5.3 % (seed 0) and 6.0 % (seed 1, not used to calibrate); cap EKF on the exact membrane 41 % and
42 % (44 % of the loaded trials), with the structural mismatches too 37 %; the exact EKF on the exact
rig 6.0 %, on the structured one 4.7 %. The free-inflation trials are flagged at 17-33 % whatever
the filter and rig (the lift-off and the factors' first learning), the loaded ones at 0-2 % when the
filter's law is the rig's and at 40-44 % when it is not. :func:`windowed_nis` and
:func:`windowed_nis_bounds` are the classic windowed NIS with its chi-square bounds, kept for
comparison: its largest window leaves the bounds in 56 % of the cap rig's runs and 17 % of the exact
rig's (it points the wrong way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from hbma_ctrl.core.settings import Settings, setting

__all__ = ["InnovationTestSettings", "window_mean_stat", "window_mean_bound", "windowed_nis",
           "windowed_nis_bounds", "innovation_test"]


@dataclass(frozen=True)
class InnovationTestSettings(Settings):
    """Settings of :func:`innovation_test` (each field's unit, range and one-line doc are in its declaration).

    window : 100 is 1 s at the rig's 10 ms (a bias the factors absorb within a second or two).
    threshold : 45 is the 95th percentile of the cap EKF on the cap rig's protocol, seed 0.
    min_fill : saturated or missing readings have no innovation.
    """

    WHERE = "innovation"

    window: int = setting(100, integer=True, lo=10, hi=10000, unit="samples", doc="samples per window")
    threshold: float = setting(45.0, lo=0.0, hi=10000.0, lo_open=True,
                               doc="a run is flagged when its largest window statistic exceeds this (at most window)")
    min_fill: float = setting(0.8, lo=0.0, hi=1.0, lo_open=True,
                              doc="a window counts only when at least this share of its samples has an innovation")
    alpha: float = setting(1e-3, lo=0.0, hi=0.5, lo_open=True, hi_open=True,
                           doc="tail probability of the white-noise bound reported beside the statistic")

    def check_rules(self) -> None:
        self.within("threshold", hi=self.window)


def _sums(r, window: int):
    r = np.asarray(r, dtype=float).ravel()
    if r.size < window:  # no full window (np.convolve's 'valid' would swap the operands)
        r = r[:0]
    ok = np.isfinite(r)
    rr = np.where(ok, r, 0.0)
    k = np.ones(window)
    if rr.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return (np.convolve(rr, k, "valid"), np.convolve(rr * rr, k, "valid"), np.convolve(ok * 1.0, k, "valid"))


def window_mean_stat(r, window: int, min_fill: float = 0.8) -> np.ndarray:
    """T = (sum r)^2 / sum r^2 (-) over every sliding window of ``window`` samples of the normalised
    innovations r (NaN = no update, skipped); NaN where fewer than ``min_fill`` of the window's
    samples have one. In [0, count]; white Gaussian r: T / count ~ Beta(1/2, (count - 1)/2)."""
    s, q, c = _sums(r, window)
    T = np.where(q > 0, s * s / np.where(q > 0, q, 1.0), 0.0)
    return np.where(c >= min_fill * window, T, np.nan)


def window_mean_bound(window: int, alpha: float) -> float:
    """The (1 - alpha) quantile of T (:func:`window_mean_stat`) over one window of ``window`` white
    Gaussian innovations of any variance: ``window * Beta.ppf(1 - alpha, 1/2, (window - 1)/2)``."""
    return float(window * stats.beta.ppf(1.0 - alpha, 0.5, 0.5 * (window - 1)))


def windowed_nis(r, window: int, min_fill: float = 0.8) -> np.ndarray:
    """Mean NIS ``mean r^2`` (-) over every sliding window of ``window`` samples (NaN skipped; NaN
    where fewer than ``min_fill`` of the samples have an innovation)."""
    _, q, c = _sums(r, window)
    return np.where(c >= min_fill * window, q / np.maximum(c, 1.0), np.nan)


def windowed_nis_bounds(window: int, alpha: float) -> tuple[float, float]:
    """Two-sided (1 - alpha) bounds of the mean NIS over ``window`` white unit innovations:
    chi-square(window) quantiles alpha/2 and 1 - alpha/2, over window."""
    lo = stats.chi2.ppf(0.5 * alpha, window) / window
    hi = stats.chi2.ppf(1.0 - 0.5 * alpha, window) / window
    return float(lo), float(hi)


def innovation_test(r, settings: InnovationTestSettings | None = None) -> dict:
    """Score one run's normalised innovations r (-, NaN where no update).

    Returns ``stat`` (the largest window statistic T, NaN when no window is full enough), ``flag``
    (stat > threshold), ``threshold``, ``white_bound`` (T's (1 - alpha) quantile for one window of
    white innovations), ``nis_window_max`` (the largest windowed NIS) and ``nis_bounds`` (its
    two-sided chi-square bounds).
    """
    s = (settings or InnovationTestSettings()).validate()
    T = window_mean_stat(r, s.window, s.min_fill)
    N = windowed_nis(r, s.window, s.min_fill)
    stat = float(np.nanmax(T)) if np.any(np.isfinite(T)) else math.nan
    return {
        "stat": stat,
        "flag": bool(stat > s.threshold),
        "threshold": s.threshold,
        "white_bound": window_mean_bound(s.window, s.alpha),
        "nis_window_max": float(np.nanmax(N)) if np.any(np.isfinite(N)) else math.nan,
        "nis_bounds": windowed_nis_bounds(s.window, s.alpha),
    }
