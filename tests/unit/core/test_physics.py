"""The physics pinned to published values (the paper, README Model), to closed forms and to the energy principle it comes from."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.materials import (
    MATERIALS,
    Gent,
    MooneyRivlin,
    NeoHookean,
    make_material,
)
from hbma_ctrl.core.params import Actuator, Pneumatics

MATS = [cls() for cls in MATERIALS.values()]


def _funcs(mat):
    """Numeric casadi Functions of (h1, h2, theta) for one material family."""
    space = ph.ParamSpace.for_material(mat)
    theta, P = space.symbols()
    h1, h2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    g = ph.geometry(h1, h2, P)
    p = ph.pressure(h1, h2, P)
    f = ca.Function("eq", [h1, h2, theta], [p, ca.pi * g["a2"] * p, g["lam"], g["V"], g["a2"]])
    return space, f


def _eval(mat, r1, t0, h1, h2, V0=3e-6):
    space, f = _funcs(mat)
    th = space.values(Actuator(r1=r1, t0=t0, V0=V0, material=mat))
    return [float(v) for v in f(h1, h2, th)]


def _free_peak(mat, r1, t0):
    space, f = _funcs(mat)
    th = space.values(Actuator(r1=r1, t0=t0, material=mat))
    hs = np.linspace(1e-6, 3 * r1, 20001)
    p = np.array(f.map(hs.size)(hs[None, :], np.zeros((1, hs.size)), np.repeat(th[:, None], hs.size, 1))[0]).ravel()
    i = int(np.argmax(p))
    return p[i], hs[i]


@pytest.mark.parametrize("r1,t0,peak_kpa", [(7.5e-3, 3e-3, 31.96), (12.5e-3, 2e-3, 12.78), (4.5e-3, 2e-3, 35.5)])
def test_nh_free_inflation_limit_point_matches_spec(r1, t0, peak_kpa):
    p, h1 = _free_peak(NeoHookean(), r1, t0)
    assert p / 1e3 == pytest.approx(peak_kpa, abs=0.01 if peak_kpa != 35.5 else 0.05)
    assert h1 / r1 == pytest.approx(1.26, abs=0.005)
    lam = np.sqrt(1 + (h1 / r1) ** 2)
    assert lam == pytest.approx(1.61, abs=0.01)


def test_robot_chamber_peak_near_5p7_mm_and_mr_later_and_higher():
    p, h1 = _free_peak(NeoHookean(), 4.5e-3, 2e-3)
    assert h1 == pytest.approx(5.7e-3, abs=0.05e-3)
    p_mr, h1_mr = _free_peak(MooneyRivlin(), 7.5e-3, 3e-3)
    p_nh, h1_nh = _free_peak(NeoHookean(), 7.5e-3, 3e-3)
    assert h1_mr / 7.5e-3 == pytest.approx(1.33, abs=0.01)
    assert p_mr > p_nh
    p_mr_robot, _ = _free_peak(MooneyRivlin(), 4.5e-3, 2e-3)
    assert p_mr_robot / 1e3 == pytest.approx(38.0, abs=0.5)  # README Model §8: about 38 kPa


@pytest.mark.parametrize("h1", [1e-4, 2e-3, 7.5e-3, 20e-3])
def test_flat_limit_matches_closed_form_and_is_continuous(h1):
    r1, t0, E = 7.5e-3, 3e-3, 130.6e3
    exact = 8 * E * t0 * h1**3 / (r1**2 * (h1**2 + r1**2))
    at, *_ = _eval(NeoHookean(), r1, t0, h1, h1)
    near, *_ = _eval(NeoHookean(), r1, t0, h1, h1 * (1 - 1e-7))
    assert at == pytest.approx(exact, rel=1e-12)
    assert near == pytest.approx(exact, rel=1e-5)


@pytest.mark.parametrize("mat", MATS, ids=lambda m: m.name)
def test_regular_form_equals_energy_principle(mat):
    """p = Vm W'(lam)(lam_h1 + lam_h2)/(V_h1 + V_h2) from eq. 6, with W' by automatic differentiation."""
    r1, t0, V0 = 7.5e-3, 3e-3, 3e-6
    h1, h2, lam_s = ca.SX.sym("h1"), ca.SX.sym("h2"), ca.SX.sym("lam")
    lam = ca.sqrt((h1**2 + r1**2 - h2**2) / r1**2)
    h = h1 - h2
    a2 = h2 * ((h1**2 + r1**2) / h1 - h2)
    V = V0 + ca.pi / 6 * h * (3 * r1**2 + 3 * a2 + h**2)  # eq. (1) as printed
    dW = ca.Function("dW", [lam_s], [ca.jacobian(mat.W(lam_s), lam_s)])
    Vm = t0 * ca.pi * r1**2
    num = Vm * dW(lam) * (ca.jacobian(lam, h1) + ca.jacobian(lam, h2))
    den = ca.jacobian(V, h1) + ca.jacobian(V, h2)
    energy = ca.Function("pe", [h1, h2], [num / den])
    for H1, H2 in [(3e-3, 0.0), (9e-3, 0.0), (6e-3, 2e-3), (12e-3, 8e-3), (15e-3, 1e-3)]:
        ref = float(energy(H1, H2)) if H2 > 0 else float(energy(H1, 1e-12))
        got = _eval(mat, r1, t0, H1, H2)[0]
        assert got == pytest.approx(ref, rel=1e-6), (H1, H2)


@pytest.mark.parametrize("mat", MATS, ids=lambda m: m.name)
def test_q_is_w_prime_over_lam_minus_one(mat):
    lam = ca.SX.sym("lam")
    dW = ca.Function("dW", [lam], [ca.jacobian(mat.W(lam), lam)])
    Q = ca.Function("Q", [lam], [mat.Q(lam)])
    for x in [1.001, 1.2, 1.61, 2.5]:
        assert float(Q(x)) * (x - 1) == pytest.approx(float(dW(x)), rel=1e-9)
    # at rest every model reduces to the same small-strain modulus: Q(1) = W''(1) = 4 mu0... (NH: 4E/3*3)
    d2W = ca.Function("d2W", [lam], [ca.hessian(mat.W(lam), lam)[0]])
    assert float(Q(1.0)) == pytest.approx(float(d2W(1.0)), rel=1e-6)


def test_free_inflation_reduces_to_thin_shell_formula():
    mat = NeoHookean()
    r1, t0 = 10e-3, 2e-3
    for h1 in [1e-3, 5e-3, 12e-3, 25e-3]:
        lam = np.sqrt(1 + (h1 / r1) ** 2)
        dW = mat.E / 6 * (4 * lam - 4 * lam**-5)
        classical = 2 * t0 * h1 * dW / (lam * (h1**2 + r1**2))
        assert _eval(mat, r1, t0, h1, 0.0)[0] == pytest.approx(classical, rel=1e-12)


def test_geometry_matches_paper_equations():
    r1, t0 = 7.5e-3, 3e-3
    h1, h2 = 9e-3, 3e-3
    p, F, lam, V, a2 = _eval(NeoHookean(), r1, t0, h1, h2)
    a2_paper = h2 * ((h1**2 + r1**2) / h1 - h2)
    V_paper = 3e-6 + np.pi / 6 * (h1 - h2) * (3 * r1**2 + 3 * a2_paper + (h1 - h2) ** 2)
    assert a2 == pytest.approx(a2_paper, rel=1e-12)
    assert V == pytest.approx(V_paper, rel=1e-12)
    assert F == pytest.approx(np.pi * a2_paper * p, rel=1e-12)
    assert lam == pytest.approx(np.sqrt((h1**2 + r1**2 - h2**2) / r1**2), rel=1e-12)
    # flat: the contact disc is the whole membrane and the plate carries pi r1^2 p
    p, F, lam, V, a2 = _eval(NeoHookean(), r1, t0, 5e-3, 5e-3)
    assert a2 == pytest.approx(r1**2) and V == pytest.approx(3e-6) and lam == pytest.approx(1.0)


def test_origin_is_finite_and_zero():
    for mat in MATS:
        p, F, lam, V, a2 = _eval(mat, 7.5e-3, 3e-3, 0.0, 0.0)
        assert np.isfinite([p, F, lam, V, a2]).all()
        assert p == 0.0 and F == 0.0


_DW: dict = {}


def _dW(mat):
    """W'(lam) of one material by automatic differentiation (independent of the package's Q form)."""
    if mat.name not in _DW:
        lam = ca.SX.sym("lam")
        _DW[mat.name] = ca.Function("dW", [lam], [ca.jacobian(mat.W(lam), lam)])
    return _DW[mat.name]


_F: dict = {}


def _eval_cached(mat, r1, t0, h1, h2, V0=3e-6):
    if mat.name not in _F:
        _F[mat.name] = _funcs(mat)
    space, f = _F[mat.name]
    th = space.values(Actuator(r1=r1, t0=t0, V0=V0, material=mat))
    return [float(v) for v in f(h1, h2, th)]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(MATS), st.floats(0.0, 4.0), st.floats(0.0, 1.0), st.sampled_from([4.5e-3, 7.5e-3, 12.5e-3]),
       st.sampled_from([2e-3, 3e-3]))
def test_pressure_force_volume_and_stretch_match_the_cap_closed_forms_over_the_chart(mat, h1_r, frac, r1, t0):
    """Whole (h1, h2) chart, 0 <= h2 <= h1 <= 4 r1, extremes included (flat, origin, large stretch),
    against the closed forms of README Model §1/§3 written out here in numpy: the cap's contact
    radius, volume (eq. 1), stretch (eq. 3), F = pi a^2 p (eq. 2), and for the free cap the Laplace
    law p = 2 t sigma / Rs (sphere radius Rs = (h1^2 + r1^2)/(2 h1), current thickness t = t0/lam^2,
    equi-biaxial Cauchy stress sigma = lam W'(lam)/2), in contact its extension eq. 6 form
    p = 2 t0 h1^2 W' / (lam (h1 - h2)(h1^2 + r1^2))."""
    h1 = h1_r * r1
    h2 = frac * h1
    V0 = 3e-6
    lam_ref = np.sqrt((h1**2 + r1**2 - h2**2) / r1**2)
    if isinstance(mat, Gent) and 2 * lam_ref**2 + lam_ref**-4 - 3 >= mat.Jm * 0.999:
        return  # beyond the Gent locking stretch the energy is undefined by construction
    p, F, lam, V, a2 = _eval_cached(mat, r1, t0, h1, h2, V0)
    assert np.isfinite([p, F, lam, V, a2]).all()
    a2_ref = frac * (h1**2 + r1**2) - h2**2  # = h2 ((h1^2 + r1^2)/h1 - h2) with h2 = frac h1, finite at h1 = 0
    h = h1 - h2
    V_ref = V0 + np.pi / 6 * h * (3 * r1**2 + 3 * a2_ref + h**2)
    if h1 > ph._EPS_H:  # below the guard height (sub-nm) the contact radius fades to 0: there p = F = 0 anyway
        assert a2 == pytest.approx(a2_ref, rel=1e-9, abs=1e-18)
    assert V == pytest.approx(V_ref, rel=1e-12)
    assert lam == pytest.approx(lam_ref, rel=1e-12)
    assert F == pytest.approx(np.pi * a2_ref * p, rel=1e-9, abs=1e-12)
    assert p >= 0
    if lam_ref - 1 > 1e-6:  # below that the closed forms lose digits to cancellation (h1 - h2, lam - 1)
        dW = float(_dW(mat)(lam_ref))
        if h2 == 0.0:
            Rs = (h1**2 + r1**2) / (2 * h1)
            t = t0 / lam_ref**2
            sigma = lam_ref * dW / 2
            assert p == pytest.approx(2 * t * sigma / Rs, rel=1e-7)
        else:
            assert p == pytest.approx(2 * t0 * h1**2 * dW / (lam_ref * h * (h1**2 + r1**2)), rel=1e-6)


def test_flat_inverse_round_trip():
    mat = make_material("mr")
    space = ph.ParamSpace.for_material(mat)
    theta, P = space.symbols()
    p = ca.SX.sym("p")
    inv = ca.Function("inv", [p, theta], [ph.flat_h1_from_pressure(p, P)])
    th = space.values(Actuator(r1=7.5e-3, t0=3e-3, material=mat))
    _, f = _funcs(mat)
    for h1 in [1e-5, 1e-3, 5e-3, 3e-2]:
        pf = float(f(h1, h1, th)[0])
        assert float(inv(pf, th)) == pytest.approx(h1, rel=1e-9)
    assert float(inv(0.0, th)) == 0.0
    assert float(inv(-5.0, th)) == 0.0  # no negative flat pressure: the membrane is simply at rest


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(st.one_of(st.just(0.0), st.floats(-1e4, 0.0), st.floats(1e-9, 1.0), st.floats(1.0, 2e5)))
def test_flat_inverse_slope_is_finite_everywhere(p_pa):
    """d h1 / d p of the flat inverse is finite at every pressure, zero and below included: an
    infinite slope there (a root of zero) made the EKF's Jacobian columns NaN."""
    mat = make_material("nh")
    space = ph.ParamSpace.for_material(mat)
    theta, P = space.symbols()
    p = ca.SX.sym("p")
    h = ph.flat_h1_from_pressure(p, P)
    f = ca.Function("f", [p, theta], [h, ca.jacobian(h, p), ca.jacobian(h, theta)])
    th = space.values(Actuator(r1=12.5e-3, t0=3e-3, material=mat))
    out = [np.asarray(v, dtype=float) for v in f(p_pa, th)]
    assert all(np.all(np.isfinite(v)) for v in out)
    assert out[0].item() >= 0.0 and out[1].item() >= 0.0


def _flow_fun():
    pu, pd = ca.SX.sym("pu"), ca.SX.sym("pd")
    return ca.Function("q", [pu, pd], [ph.orifice_flow(pu, pd, 2e-10, 0.3, 0.995, 293.15)])


def test_orifice_flow_iso6358_regimes():
    q = _flow_fun()
    choked = float(q(300e3, 50e3))
    assert choked == pytest.approx(2e-10 * ph.RHO0_ISO * 300e3, rel=1e-12)  # ratio < b: choked
    assert float(q(100e3, 100e3)) == 0.0
    assert float(q(100e3, 130e3)) == pytest.approx(-float(q(130e3, 100e3)))
    # continuous across b and across the laminar blend, and monotone in the upstream pressure
    ps = np.linspace(100e3, 400e3, 3001)
    qs = np.array([float(q(x, 100e3)) for x in ps])
    assert np.all(np.diff(qs) >= 0)
    assert np.max(np.abs(np.diff(qs))) < 0.01 * qs.max()


def test_compressor_table_is_read_and_bad_tables_are_named(tmp_path):
    s, p, grid = ph.load_compressor_table(Pneumatics().csv_path)
    assert s[0] == 0 and s[-1] == 1 and grid[0].max() == 0 and grid[-1, 0] > 0
    bad = tmp_path / "bad.csv"
    bad.write_text("speed,pressure_pa,mass_flow_kgs\n0,0,0\n1,0,1e-6\n1,1000,1e-6\n")
    with pytest.raises(ValueError, match="full grid"):
        ph.load_compressor_table(bad)
    bad.write_text("speed,pressure,flow\n0,0,0\n")
    with pytest.raises(ValueError, match="columns"):
        ph.load_compressor_table(bad)
    bad.write_text("speed,pressure_pa,mass_flow_kgs\n0,0,0\n0,1,0\n1,0,-1\n1,1,0\n")
    with pytest.raises(ValueError, match=">= 0"):
        ph.load_compressor_table(bad)


def test_material_errors_name_the_field():
    with pytest.raises(ValueError, match="did you mean 'ogden'"):
        make_material("ogdn")
    with pytest.raises(ValueError, match="unknown parameter 'e'"):
        make_material("nh", e=1.0)
    with pytest.raises(ValueError, match="E must be > 0"):
        make_material("nh", E=-1.0)
    with pytest.raises(ValueError, match="actuator.r1"):
        Actuator(r1=-1.0).validate()


@pytest.mark.parametrize("mat", MATS, ids=lambda m: m.name)
def test_scaled_material_scales_the_pressure_and_keeps_exponents(mat):
    r1, t0 = 7.5e-3, 3e-3
    base = _eval(mat, r1, t0, 9e-3, 2e-3)[0]
    stiff = _eval(mat.scaled(1.15), r1, t0, 9e-3, 2e-3)[0]
    assert stiff == pytest.approx(1.15 * base, rel=1e-12)
    for name in type(mat).dimensionless:
        assert getattr(mat.scaled(1.15), name) == getattr(mat, name)
