"""The shared least-squares identification against the closed forms of a linear model."""

from __future__ import annotations

import numpy as np
from scipy.stats import t as t_dist

from hbma_ctrl.core.identify import Coordinates, central_jacobian, identify, summary

X = np.linspace(0.0, 1.0, 20)
A = np.column_stack([np.ones_like(X), X])  # y = a + b x


def _data(seed: int = 0) -> np.ndarray:
    return A @ np.array([2.0, -3.0]) + np.random.default_rng(seed).normal(0.0, 0.1, X.size)


def test_estimate_is_ordinary_least_squares_with_its_covariance_and_t_intervals():
    y = _data()
    est = identify(lambda p: A @ p - y, [np.zeros(2)], (-np.inf, np.inf))
    beta, *_ = np.linalg.lstsq(A, y, rcond=None)
    s2 = np.sum((A @ beta - y) ** 2) / (X.size - 2)
    assert np.allclose(est.x, beta, atol=1e-10)
    assert np.allclose(est.cov, s2 * np.linalg.inv(A.T @ A), rtol=1e-6)
    ci, _, weak = summary(est, Coordinates.scaled(np.ones(2)), est.x, ["a", "b"], "this data", "")
    half = t_dist.ppf(0.975, X.size - 2) * np.sqrt(np.diag(s2 * np.linalg.inv(A.T @ A)))
    assert np.allclose(np.array([ci["a"], ci["b"]]), np.column_stack([beta - half, beta + half]), rtol=1e-6)
    assert weak == []


def test_prior_gives_the_gaussian_posterior():
    y, sigma = _data(1), 0.1
    mean, std = np.array([1.0, -1.0]), np.array([0.5, 0.2])
    est = identify(lambda p: (A @ p - y) / sigma, [mean.copy()], (-np.inf, np.inf), jac=lambda p: A / sigma,
                   prior=(mean, std))
    info = A.T @ A / sigma ** 2 + np.diag(1.0 / std ** 2)
    post = np.linalg.solve(info, A.T @ y / sigma ** 2 + mean / std ** 2)
    assert np.allclose(est.x, post, atol=1e-8)
    assert np.allclose(est.cov, np.linalg.inv(info), rtol=1e-10)


def test_parameters_that_only_act_together_are_named_as_a_trade_off():
    y = _data(2)
    B = np.column_stack([np.ones_like(X), X, X])  # b and c: only b + c is determined
    est = identify(lambda p: B @ p - y, [np.array([0.0, 1.0, 1.0])], (-np.inf, np.inf))
    _, _, weak = summary(est, Coordinates.scaled(np.ones(3)), est.x, ["a", "b", "c"], "this data", "fix one")
    assert len(weak) == 1 and "b and c trade off in this data" in weak[0]


def test_coordinates_round_trip_on_log_and_linear_scales():
    coords = Coordinates.about(np.array([3e-6, -240.0, 0.0]))
    v = np.array([4e-6, -100.0, 5.0])
    assert list(coords.log) == [True, False, False]
    assert np.allclose(coords.values(coords.coordinates(v)), v, rtol=1e-14)
    assert np.allclose(coords.coordinates(v), [np.log(4 / 3), 140.0 / 240.0, 5.0])


def test_central_difference_is_cut_at_a_bound_and_divided_by_the_width_taken():
    def square(P):
        return P ** 2

    J = central_jacobian(square, np.array([1.0]), 1e-3, np.array([0.0]), np.array([1.0]))
    assert np.isclose(J[0, 0], 2.0 - 1e-3, rtol=1e-12)  # one-sided: (1 - (1 - h)^2) / h
    assert np.isclose(central_jacobian(square, np.array([0.5]), 1e-3)[0, 0], 1.0, rtol=1e-12)
