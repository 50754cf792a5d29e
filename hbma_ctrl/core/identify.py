"""Least-squares identification of model parameters: the one solve, covariance and report of the static
and dynamic fits (:mod:`hbma_ctrl.app.tuning.fit`, :mod:`hbma_ctrl.app.tuning.fit_dynamic`) and the
start-up calibration (:mod:`hbma_ctrl.runtime.calibrate`). Each caller owns its model, its residuals
(dimensionless: divided by a channel's span or by the sensor's sigma) and its data; this module the rest.

- :class:`Coordinates`: where the solver works. Each parameter relative to a reference: on a log scale
  (``log(value / reference)``), or linear, as an offset from the reference or from zero in units of
  ``|reference|``.
- :func:`identify`: ``scipy.optimize.least_squares`` from each start, the lowest cost kept
  (:func:`solve`), then the Jacobian at the optimum (the caller's, else central differences,
  :func:`central_jacobian`) and the covariance of the coordinates (:func:`estimate`). Without a prior
  the residuals' noise is unknown: the covariance is ``s^2 (J^T J)^+`` with the residual variance
  ``s^2 = |r|^2 / (n - m)`` (a pseudo-inverse: an undetermined direction is named by
  :func:`weak_directions`, not a failure). With a Gaussian prior (means and sigmas of the
  coordinates) the residuals must be in units of their noise's sigma, the prior's rows are appended
  to them, and the covariance is the Gauss-Newton posterior ``(J^T J + diag(1 / sigma^2))^-1``.
- :func:`summary`: the 95 % intervals (a t quantile with n - m degrees of freedom) in the parameters'
  units, the correlation matrix and the directions the data cannot determine, in words.

What the data cannot separate (:func:`weak_directions`) is judged on two things that a correlation alone
does not tell: the sensitivity of the fit along each right singular vector of the Jacobian in relative
units (a combination whose 100 % change moves the model by less than :data:`SENS_MIN` of the data's
span, RMS, is not determined whatever the noise), and the width of each 95 % interval relative to its
value (above :data:`REL_CI_MAX`: not determined by these points; named as a trade-off with the
parameter it is correlated with beyond :data:`CORR_LIMIT`). A correlation of -0.985 between two
parameters whose intervals are both narrow is not reported.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import t as t_dist

#: residuals of a parameter vector (or of parameter sets as columns)
Residuals = Callable[[np.ndarray], np.ndarray]

__all__ = ["SENS_MIN", "REL_CI_MAX", "CORR_LIMIT", "BAD_RESIDUAL", "finite_residuals", "Coordinates", "Estimate",
           "central_jacobian", "solve", "estimate", "identify", "summary", "weak_directions"]

#: RMS change of the model, as a fraction of the data's span, per 100 % change of a parameter
#: combination, below which that combination is not determined by the data (noise-free criterion)
SENS_MIN = 1e-3
#: 95 % half-width relative to the value above which a parameter is reported as not determined
REL_CI_MAX = 1.0
#: |correlation| above which a poorly determined parameter is named with its partner
CORR_LIMIT = 0.98
#: residual given to a point the model cannot evaluate (a diverged simulation, a non-physical
#: material), in units of the channel's span: far off, yet finite for the solver
BAD_RESIDUAL = 10.0

#: the largest log half-width whose exp is a float (exp(709) ~ 8e307)
_LOG_HALF_MAX = 700.0


def finite_residuals(r: np.ndarray) -> np.ndarray:
    """``r`` with every non-finite entry replaced by :data:`BAD_RESIDUAL`."""
    return np.where(np.isfinite(r), r, BAD_RESIDUAL)


@dataclass(frozen=True)
class Coordinates:
    """The solver's coordinates z of parameter values v, one entry per parameter: ``v = origin * exp(z)``
    where ``log``, else ``v = origin + scale * z``."""

    origin: np.ndarray
    scale: np.ndarray
    log: np.ndarray

    @classmethod
    def scaled(cls, reference: np.ndarray) -> "Coordinates":
        """Linear, in units of ``|reference|`` (1 where it is zero), from zero: ``z = v / |reference|``."""
        reference = np.asarray(reference, dtype=float)
        return cls(np.zeros_like(reference), np.where(np.abs(reference) > 0, np.abs(reference), 1.0),
                   np.zeros(reference.shape, dtype=bool))

    @classmethod
    def about(cls, nominal: np.ndarray) -> "Coordinates":
        """Offsets from ``nominal``: ``log(v / nominal)`` for a positive nominal, else ``(v - nominal) /
        |nominal|`` (1 for a zero one): a signed parameter on a linear scale."""
        nominal = np.asarray(nominal, dtype=float)
        return cls(nominal, np.where(nominal != 0, np.abs(nominal), 1.0), nominal > 0)

    def _cols(self, z: np.ndarray) -> tuple:
        return tuple(a.reshape(a.shape + (1,) * (z.ndim - 1)) for a in (self.origin, self.scale, self.log))

    def values(self, z: np.ndarray) -> np.ndarray:
        """Parameter values of coordinates ``z``: one vector, or one column per parameter set."""
        z = np.asarray(z, dtype=float)
        o, s, lg = self._cols(z)
        return np.where(lg, o * np.exp(np.where(lg, z, 0.0)), o + s * z)

    def coordinates(self, values: np.ndarray) -> np.ndarray:
        """The coordinates of parameter ``values`` (the inverse of :meth:`values`)."""
        v = np.asarray(values, dtype=float)
        o, s, lg = self._cols(v)
        return np.where(lg, np.log(np.where(lg, v, 1.0) / np.where(lg, o, 1.0)), (v - o) / s)

    def intervals(self, values: np.ndarray, sd: np.ndarray, tq: float) -> tuple[list, np.ndarray]:
        """Intervals ``[lo, hi]`` of parameters at ``values`` whose coordinates have standard errors ``sd``,
        ``tq`` of them either side (symmetric in the coordinates: a log one's is ``v exp(+-tq sd)``), and
        each half-width relative to its value (inf at a zero value); ``[None, None]`` for an unknown
        (non-finite) width."""
        ci, rel = [], np.empty(len(values))
        for j, (v, s, sc, lg) in enumerate(zip(values, sd, self.scale, self.log)):
            half = tq * s if lg else tq * (s * sc)
            if lg and half > _LOG_HALF_MAX:  # a width beyond any float: as unknown as an infinite one
                half = float("inf")
            lo, hi = (v * math.exp(-half), v * math.exp(half)) if lg else (v - half, v + half)
            ci.append([float(lo), float(hi)] if math.isfinite(half) else [None, None])
            rel[j] = math.expm1(half) if lg else half / abs(v) if v != 0 else float("inf")
        return ci, rel


@dataclass(frozen=True)
class Estimate:
    """A least-squares optimum in the solver's coordinates: ``x``, the data residuals ``r`` and their
    Jacobian ``J`` there (without a prior's rows), the covariance ``cov`` of ``x`` and the degrees of
    freedom ``dof`` (residuals minus parameters)."""

    x: np.ndarray
    r: np.ndarray
    J: np.ndarray
    cov: np.ndarray
    dof: int


def central_jacobian(fun_cols: Residuals, x: np.ndarray, step, lo=None, hi=None) -> np.ndarray:
    """Central differences of residuals at ``x``, every column from one call of ``fun_cols`` (parameter
    sets as columns, residuals as rows). ``step``: per parameter or one for all. With bounds a step is
    cut at them and the difference divided by the width taken; without, by ``2 step``."""
    n = x.size
    up, dn, width = x + step, x - step, 2 * step
    if lo is not None:
        up, dn = np.minimum(up, hi), np.maximum(dn, lo)
        width = up - dn
    X = np.repeat(x[:, None], 2 * n, axis=1)
    X[np.arange(n), np.arange(n)] = up
    X[np.arange(n), n + np.arange(n)] = dn
    R = fun_cols(X)
    return (R[:, :n] - R[:, n:]) / width


def solve(fun: Residuals, starts: Sequence[np.ndarray], bounds, *, jac: Residuals | None = None,
          prior: tuple | None = None, **options) -> np.ndarray:
    """The least-squares optimum of ``fun`` (dimensionless residuals of the coordinates) from each of
    ``starts`` within ``bounds`` (lo, hi), the lowest cost kept (the first of equals); ``options`` go to
    ``scipy.optimize.least_squares``. ``jac``: the residuals' Jacobian (None: the solver's forward
    differences). ``prior``: (means, sigmas) of the coordinates, with residuals in units of their
    noise's sigma (module doc)."""
    f, df = fun, jac
    if prior is not None:
        mean, std = (np.asarray(a, dtype=float) for a in prior)

        def with_prior(x):
            return np.concatenate([fun(x), (x - mean) / std])

        def jac_with_prior(x):
            return np.vstack([jac(x), np.diag(1.0 / std)])

        f, df = with_prior, (None if jac is None else jac_with_prior)
    best = None
    for x0 in starts:
        sol = least_squares(f, x0, jac="2-point" if df is None else df, bounds=bounds, **options)
        if best is None or sol.cost < best.cost:
            best = sol
    return best.x


def estimate(fun: Residuals, x: np.ndarray, bounds, *, jac: Residuals | None = None,
             prior: tuple | None = None) -> Estimate:
    """The :class:`Estimate` at the optimum ``x`` of :func:`solve` with the same ``fun``, ``bounds``,
    ``jac`` (None: central differences of relative step 1e-6, cut at the bounds) and ``prior``."""
    r = fun(x)
    if jac is not None:
        J = jac(x)
    else:
        lo, hi = (np.broadcast_to(np.asarray(b, dtype=float), x.shape) for b in bounds)
        J = central_jacobian(lambda X: np.column_stack([fun(c) for c in X.T]), x,
                             1e-6 * np.maximum(np.abs(x), 1.0), lo, hi)
    dof = r.size - x.size
    if prior is None:
        s2 = float(r @ r) / dof if dof > 0 else float("nan")
        cov = np.linalg.pinv(J.T @ J) * s2
    else:
        cov = np.linalg.inv(J.T @ J + np.diag(1.0 / np.asarray(prior[1], dtype=float) ** 2))
        cov = 0.5 * (cov + cov.T)
    return Estimate(x=x, r=r, J=J, cov=cov, dof=dof)


def identify(fun: Residuals, starts: Sequence[np.ndarray], bounds, *, jac: Residuals | None = None,
             prior: tuple | None = None, **options) -> Estimate:
    """:func:`solve` then :func:`estimate` at its optimum."""
    x = solve(fun, starts, bounds, jac=jac, prior=prior, **options)
    return estimate(fun, x, bounds, jac=jac, prior=prior)


def summary(est: Estimate, coords: Coordinates, values: np.ndarray, names: Sequence[str], where: str,
            hint: str) -> tuple[dict, dict, list[str]]:
    """What a fit reports for its fitted parameters ``names`` at ``values`` (coordinates ``coords``):
    the 95 % intervals ``{name: [lo, hi]}`` (a t quantile), the correlations ``{a: {b: r}}`` (of the
    normalised information ``J^T J`` without degrees of freedom) and the weak directions in words (:func:`weak_directions` with ``where`` and ``hint``)."""
    tq = float(t_dist.ppf(0.975, est.dof)) if est.dof > 0 else float("nan")
    ci, rel_half = coords.intervals(values, np.sqrt(np.clip(np.diag(est.cov), 0, None)), tq)
    if np.all(np.isfinite(est.cov)):
        cd = np.sqrt(np.clip(np.diag(est.cov), 1e-300, None))
        corr = np.clip(est.cov / np.outer(cd, cd), -1.0, 1.0)
    else:  # no degrees of freedom: the normalised information
        JtJ = est.J.T @ est.J
        d = np.sqrt(np.clip(np.diag(JtJ), 1e-300, None))
        corr = JtJ / np.outer(d, d)
    correlation = {a: {b: float(corr[i, j]) for j, b in enumerate(names)} for i, a in enumerate(names)}
    return dict(zip(names, ci)), correlation, weak_directions(list(names), est.J, corr, rel_half, where, hint)


def _join(names: list[str] | tuple[str, ...]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + f" and {names[-1]}"


def weak_directions(names: list[str], J: np.ndarray, corr: np.ndarray, rel_half: np.ndarray, where: str,
                    hint: str) -> list[str]:
    """The parameter combinations the data cannot separate, in words.

    ``J``: Jacobian of the residuals (each divided by its channel's span) with respect to the
    parameters in relative units (a column = the change per 100 % change of that parameter's
    reference value); ``corr``: their correlation matrix; ``rel_half``: each 95 % half-width divided
    by the value (NaN when unknown); ``where``: the data in words ("this run"); ``hint``: what to do
    about a trade-off. See the module docstring for the two criteria.
    """
    out: list[str] = []
    named: set = set()
    n = max(J.shape[0], 1)
    _, S, Vt = np.linalg.svd(J, full_matrices=False)
    for k in range(len(S)):
        sens = float(S[k]) / math.sqrt(n)
        if sens >= SENS_MIN:
            continue
        v = Vt[k] / np.max(np.abs(Vt[k]))
        # members: the direction's large components, and what they are strongly correlated with
        # (a small component can carry a large relative change when the defaults differ in size)
        big = [i for i in range(len(names)) if abs(v[i]) > 0.1]
        part = tuple(names[i] for i in range(len(names))
                     if i in big or any(abs(corr[i, j]) > CORR_LIMIT for j in big))
        named |= set(part)
        if len(part) == 1:
            out.append(f"{part[0]} is not determined by {where} (a 100 % change moves the fit by {sens:.1e} "
                       "of the data's span)")
        else:
            out.append(f"{_join(part)} trade off in {where}: only a combination is determined (changing it "
                       f"by 100 % moves the fit by {sens:.1e} of the data's span); {hint}")
    for i, a in enumerate(names):
        if a in named or not (rel_half[i] > REL_CI_MAX):
            continue
        partners = [names[j] for j in range(len(names)) if j != i and names[j] not in named
                    and abs(corr[i, j]) > CORR_LIMIT and rel_half[j] > REL_CI_MAX]
        if partners:
            j = names.index(partners[0])
            named |= {a, partners[0]}
            out.append(f"{a} and {partners[0]} trade off in {where} (correlation {corr[i, j]:+.3f}, 95 % intervals "
                       f"+-{100 * rel_half[i]:.0f} % and +-{100 * rel_half[j]:.0f} %); {hint}")
        else:
            named.add(a)
            out.append(f"{a} is not determined by {where} (95 % interval +-{100 * rel_half[i]:.0f} % of its value)")
    return out
