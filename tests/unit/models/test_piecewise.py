"""The piecewise-polynomial form of a cubic B-spline table (hbma_ctrl.models.piecewise) against the
casadi bspline interpolant it replaces: values and derivatives equal to rounding, on the exact
membrane's own contact table and on a small synthetic one, in one and two coordinates."""

import casadi as ca
import numpy as np
import pytest

from hbma_ctrl.core.materials import make_material
from hbma_ctrl.models.fidelity_exact import _normalised, exact_contact_table
from hbma_ctrl.models.piecewise import PiecewiseCubic


@pytest.fixture(scope="module")
def contact():
    t = exact_contact_table(_normalised(make_material("nh")))
    grid = [np.asarray(t["u"]), np.sqrt(np.asarray(t["s"]))]
    return PiecewiseCubic("ratios", grid, [t["Rp"], t["Rv"], t["lam0"]]), grid


def _pair(pw, dim):
    """(polynomial, spline) Functions of c -> (values, Jacobian, Hessian of the first output)."""
    c = ca.SX.sym("c", dim)
    out = []
    for vals in (ca.vertcat(*pw(c)), ca.vertcat(*[sp(c) for sp in pw.splines])):
        out.append(ca.Function("f", [c], [vals, ca.jacobian(vals, c), ca.hessian(vals[0], c)[0]]))
    return out


def _points(grid, n, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.vstack([rng.uniform(g[0], g[-1], n) for g in grid])
    # the nodes themselves (cell edges: the index switches there)
    nodes = np.array(np.meshgrid(*grid, indexing="ij")).reshape(len(grid), -1)
    return np.hstack([pts, nodes])


def test_exact_contact_table_values_and_derivatives_equal_the_bspline(contact):
    pw, grid = contact
    pts = _points(grid, 3000)
    fp, fs = (f.map(pts.shape[1]) for f in _pair(pw, 2))
    got, ref = fp(pts), fs(pts)
    for g, r, tol in zip(got, ref, (1e-12, 1e-9, 1e-7)):
        g, r = np.asarray(g), np.asarray(r)
        assert np.all(np.isfinite(g))
        # relative to the output's scale: derivatives of the ratios reach O(100) at the flat edge
        assert np.max(np.abs(g - r)) <= tol * max(1.0, np.max(np.abs(r)))


def test_one_coordinate_table_reproduces_its_spline_and_a_cubic_exactly():
    x = np.array([0.0, 0.1, 0.25, 0.5, 0.6, 0.9, 1.3])
    cubic = 2 - x + 0.5 * x**2 - 0.3 * x**3  # a cubic spline through a cubic is that cubic
    pw = PiecewiseCubic("cubic", [x], [cubic])
    c = ca.SX.sym("c")
    f = ca.Function("f", [c], [pw(c)[0], ca.jacobian(pw(c)[0], c)])
    q = np.linspace(0, 1.3, 57)
    v, d = (np.asarray(o).ravel() for o in f.map(q.size)(q))
    assert np.allclose(v, 2 - q + 0.5 * q**2 - 0.3 * q**3, atol=1e-12)
    assert np.allclose(d, -1 + q - 0.9 * q**2, atol=1e-10)


def test_numeric_and_mx_arguments_give_the_symbolic_result(contact):
    pw, _ = contact
    c = [0.73, 0.41]
    num = [float(v) for v in pw(ca.DM(c))]
    m = ca.MX.sym("c", 2)
    mx = ca.Function("g", [m], [ca.vertcat(*pw(m))])
    assert np.allclose(np.asarray(mx(c)).ravel(), num, rtol=0, atol=1e-14)
    assert np.allclose(num, [float(sp(c)) for sp in pw.splines], rtol=1e-12)


def test_more_than_two_coordinates_is_refused():
    g = np.linspace(0, 1, 4)
    with pytest.raises(ValueError, match="1 or 2 coordinates"):
        PiecewiseCubic("t", [g, g, g], [np.zeros((4, 4, 4))])


def test_zero_outside_the_grid_as_the_bspline():
    g1, g2 = np.linspace(0, 1, 5), np.linspace(-1, 2, 4)
    V = np.add.outer(g1**2, np.cos(g2)) + 3.0
    pw = PiecewiseCubic("t", [g1, g2], [V])
    outside = [(-0.01, 0.5), (1.01, 0.5), (0.5, -1.2), (0.5, 2.5)]
    for c in outside:
        assert float(pw(ca.DM(c))[0]) == 0.0 == float(pw.splines[0](c))
    assert float(pw(ca.DM([1.0, 2.0]))[0]) == pytest.approx(float(pw.splines[0]([1.0, 2.0])), rel=1e-11)
