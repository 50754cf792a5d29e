"""Unit tests of the controllers: prediction model, MPC OCP and fallbacks, baselines, [controller] parsing.

The fallback chain and the pressure guard live in the runtime's supervisor; the tests of them step
the controllers through a :class:`ChamberLoop` (``control``: controller then supervisor)."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.controllers.baselines import (
    BangBangController,
    BangBangSettings,
    PIDController,
    PIDSettings,
)
from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.controllers.mpc_settings import MPCSettings, duty_to_on_time
from hbma_ctrl.controllers.mpc_solvers import _Problem
from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.interfaces import SAFE_COMMAND, Estimate, Reference
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.fidelity import make_fidelity
from hbma_ctrl.runtime.chamber import ChamberLoop
from hbma_ctrl.sim.simulate import Plant
from oracles.mpc_prep import lift_off_x, problem_reference, reachable_height

ACT, PN = Actuator(), Pneumatics()
W400 = 0.4 * 9.80665

def parse_section(raw: dict):
    """The [controller] table (edge units) -> its SI settings, through the scenario schema."""
    return parse_role("controller", raw)



@pytest.fixture(scope="module")
def model(cap_prediction_model):
    # the cap's tables, checked here against the cap's closed forms (the exact law's: test_exact_mpc.py)
    return cap_prediction_model  # PredictionModel(ACT, PN, membrane="cap")


@pytest.mark.slow
def test_poly_tables_equal_the_bspline_functions_with_their_jacobians(model):
    """functions('poly') (the tables as per-cell polynomials, what the RTI and IPOPT controllers use)
    equals the bspline Functions over the whole grid, its nodes, the flat rest below lift-off and off
    the grid (zero there, as the bspline): values and the Jacobians in x and W, and the RK4 step."""
    import casadi as ca

    g = model.grid
    rng = np.random.default_rng(3)
    xs = np.concatenate([rng.uniform(g.x[0], g.x[-1], 400), g.x, [g.x[0] - 0.1, g.x[-1] + 0.5]])
    Ws = np.concatenate([rng.uniform(0.0, model.load_max, 400), rng.choice(g.W, g.x.size), [0.0, 0.0]])
    x, W, dp, u = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("dp"), ca.SX.sym("u", 3)
    outs = []
    for form in ("bspline", "poly"):
        fn = model.functions(form)
        hp = ca.vertcat(fn.HP(x, W), fn.L(x, W))
        F = model.discrete(0.01, "rk4", 1, form)
        f = ca.Function("f", [x, W, u, dp], [hp, ca.jacobian(hp, ca.vertcat(x, W)), F(x, u, W, dp),
                                             ca.jacobian(F(x, u, W, dp), ca.vertcat(x, u))])
        outs.append([np.asarray(o) for o in f.map(xs.size)(xs, Ws, np.tile([[0.6], [1.0], [0.0]], xs.size),
                                                             np.full(xs.size, 500.0))])
    scale = [1e-12, 1e-9, 1e-12, 1e-9]
    for (a, b, tol) in zip(*outs, scale):
        assert np.all(np.isfinite(a))
        # row by row (h in m, p in Pa and their derivatives differ by orders of magnitude)
        for ra, rb in zip(a, b):
            assert np.max(np.abs(ra - rb)) <= tol * max(np.abs(rb).max(), 1e-300)
    # off the grid the tables read zero in both forms (callers clamp)
    assert np.all(outs[1][0][:, -2:] == 0.0) and np.all(outs[0][0][:, -2:] == 0.0)
    with pytest.raises(ValueError, match="form = 'spline'"):
        model.functions("spline")


def test_load_path_queries_read_the_grid_between_its_two_load_columns(model):
    """path(W), x_at_height and the reach (the NMPC's oracle) read one load path: the grid's two load columns around
    W mixed linearly, W clipped to [0, load_max]; checked against the grid itself over the whole range
    and beyond it at both ends."""
    g = model.grid
    for W in np.concatenate([[-1.0, 0.0], np.linspace(1e-3, model.load_max, 37), [model.load_max * 2]]):
        Wc = min(max(W, 0.0), model.load_max)
        j = min(max(int(np.searchsorted(g.W, Wc)), 1), len(g.W) - 1)
        s = (Wc - g.W[j - 1]) / (g.W[j] - g.W[j - 1])
        pth = model.path(W)
        for key, A in (("x", g.x_path), ("p", g.p_path), ("lam", g.lam_path)):
            np.testing.assert_array_equal(pth[key], (1 - s) * A[:, j - 1] + s * A[:, j])
        for h in (0.5e-3, 3e-3, 8e-3):
            assert model.x_at_height(h, W) == float(np.interp(h, g.h_path, pth["x"]))
        # reachable from the same path: below the pressure limit up to it, at it only past it
        r = reachable_height(model, W, 20e3, 4.0, 12e-3)
        assert 0.0 <= r <= 12e-3
        if r > 0.0:
            assert np.interp(r, g.h_path, pth["p"]) <= 20e3 * (1 + 1e-9)
    assert lift_off_x(model, -1.0) == 0.0 and np.isnan(model.path(float("nan"))["x"]).all()


def est(h=0.0, p=0.0, F=0.0, t=0.0, flags=()):
    return Estimate(t=t, h1=h, h2=0.0, h=h, F=F, p=p, flags=frozenset(flags))


def supervised(controller) -> ChamberLoop:
    """The controller behind the runtime's supervisor (no estimator: ``control`` takes the estimate)."""
    return ChamberLoop(None, controller)


# --- prediction model ----------------------------------------------------------------------------
def test_tables_agree_with_lead_physics(model):
    """Free inflation (W = 0): the table's pressure at a height is physics.pressure(h, 0)."""
    theta, P = model.chamber.symbols()
    import casadi as ca

    h1 = ca.SX.sym("h1")
    pf = ca.Function("p", [h1, theta], [ph.pressure(h1, 0, P)])
    for h in (2e-3, 5e-3, 8e-3, 12e-3):
        x = model.x_at_height(h, 0.0)
        assert float(model.H(x, 0.0)) == pytest.approx(h, abs=2e-5)
        assert float(model.Pp(x, 0.0)) == pytest.approx(float(pf(h, model.theta)), rel=0.01, abs=30)


def test_rest_until_lift_off(model):
    """Below the lift-off gas mass the platform rests (h = 0) and p = x p_env (V = V0)."""
    x_lo = lift_off_x(model, W400)
    assert x_lo == pytest.approx(W400 / (np.pi * ACT.r1 ** 2) / ACT.p_env)
    for frac in (0.2, 0.5, 0.8):
        x = frac * x_lo
        assert float(model.H(x, W400)) < 0.0  # virtual height below lift-off: a gradient to pump
        assert float(model.Pp(x, W400)) == pytest.approx(x * ACT.p_env, rel=0.03, abs=150)
    assert float(model.H(x_lo + 0.3, W400)) > 1e-3


def test_prediction_matches_quasi_static_plant(model):
    """One second of full pumping from rest under 400 g: the gas-mass model against the simulator's
    quasi-static plant (same nominal parameters)."""
    fid = make_fidelity("quasi_static", ACT.material, str(PN.csv_path))
    theta = fid.space.values(ACT, PN, Platform(load=0.4))
    plant = Plant(fid, theta[:, None], "rk4", 1e-3)
    F = model.discrete(0.02)
    x = 0.0
    for _ in range(50):
        plant.advance(np.array([[1.0], [1.0], [0.0]]), 0.02)
        x = float(F(x, [1, 1, 0], W400, 0.0))
    h_plant = float(plant.output("h")[0])
    assert h_plant > 3e-3
    assert float(model.H(x, W400)) == pytest.approx(h_plant, rel=0.03)
    assert float(model.Pp(x, W400)) == pytest.approx(float(plant.output("p")[0]), rel=0.03)


def test_reachable_height_respects_pressure_limit(model):
    h15 = reachable_height(model, W400, 15e3, 1.5, 0.02)
    pth = model.path(W400)
    assert float(np.interp(h15, pth["h"], pth["p"])) == pytest.approx(15e3, rel=0.01)
    assert reachable_height(model, W400, 35e3, 1.5, 0.02) > h15
    assert reachable_height(model, W400, 5e3, 1.5, 0.02) == 0.0  # cannot even lift off


# --- settings and parsing ------------------------------------------------------------------------
def test_settings_errors_name_field_and_range():
    with pytest.raises(ValueError, match="did you mean 'ipopt'"):
        MPCSettings(variant="ipop").validate()
    with pytest.raises(ValueError, match=r"mpc.horizon .* \[2, 200\]"):
        MPCSettings(horizon=1).validate()
    with pytest.raises(ValueError, match="mpc.p_max"):
        MPCSettings(p_max=-1.0).validate()


def test_parse_section_edge_units_and_typos():
    sec = parse_section({"variant": "ipopt", "horizon": 10, "sample_ms": 20, "p_max_kpa": 30,
                         "targets_mm": [[0, 2], [1, 4]], "load_steps_g": [[1.5, 600]]})
    assert sec.mpc.p_max == pytest.approx(30e3) and sec.pid.p_max == pytest.approx(30e3)
    assert sec.mpc.horizon == 10 and sec.reference(1.2) == pytest.approx(4e-3)
    assert sec.load_steps == ((1.5, 0.6),)
    with pytest.raises(ValueError, match="did you mean horizon"):
        parse_section({"horizn": 10, "targets_mm": [[0, 2]]})
    with pytest.raises(ValueError, match="targets_mm is required"):
        parse_section({"kind": "mpc"})
    with pytest.raises(ValueError, match="did you mean 'bang_bang'"):
        parse_section({"kind": "bangbang", "targets_mm": [[0, 2]]})


def test_reference_profiles():
    sec = parse_section({"targets_mm": [[0, 2], [2, 6]], "interpolation": "linear",
                         "sine_amplitude_mm": 1.0, "sine_period_s": 4.0, "sine_start_s": 2.0})
    assert sec.reference(1.0) == pytest.approx(4e-3)
    assert sec.reference(3.0) == pytest.approx(7e-3)  # 6 mm + 1 mm sin(pi/2)


def test_duty_to_on_time():
    assert duty_to_on_time(0.5, 0.02) == pytest.approx(0.01)
    assert duty_to_on_time(0.05, 0.02, min_on=0.004) == 0.0
    assert duty_to_on_time(0.15, 0.02, min_on=0.004) == pytest.approx(0.004)
    assert duty_to_on_time(0.95, 0.02, min_on=0.004) == pytest.approx(0.02)
    with pytest.raises(ValueError, match="duty"):
        duty_to_on_time(1.5, 0.02)


# --- the MPC -------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["rti_c_osqp", "rti_osqp", "ipopt"])
def test_mpc_pumps_below_and_vents_above_target(model, variant):
    s = MPCSettings(variant=variant, budget=5.0)
    c = NMPC(ACT, PN, s, model=model)
    up = c.step(0.0, est(h=2e-3, p=11.7e3, F=W400), Reference(6e-3))
    assert up.speed > 0.5 and up.inlet >= up.speed - 1e-6 and up.outlet < 0.05
    c.reset()
    down = c.step(0.0, est(h=8e-3, p=21.4e3, F=W400), Reference(4e-3))
    assert down.outlet > 0.5 and down.speed < 0.05
    c.reset()
    hold = c.step(0.0, est(h=5e-3, p=17.5e3, F=W400), Reference(5e-3))
    assert max(hold.speed, hold.outlet) < 0.1


@pytest.mark.slow
def test_rti_converges_to_ipopt_plan(model):
    """Iterated, the RTI's QPs converge to the same optimum as IPOPT on the same OCP."""
    s = MPCSettings(budget=5.0, rti_init_iterations=30)
    pr = _Problem(x0=model.x_at_height(4e-3, W400), W=W400, dh=0.0, dp=0.0, r=np.full(20, 5e-3), u_prev=np.zeros(3),
                  p_lim=33e3)
    rti = NMPC(ACT, PN, s, model=model).backend
    ipo = NMPC(ACT, PN, MPCSettings(variant="ipopt", budget=5.0), model=model).backend
    Xr, Ur = rti.solve(pr)
    Xi, Ui = ipo.solve(pr)
    h_r = [float(model.H(x, W400)) for x in Xr]
    h_i = [float(model.H(x, W400)) for x in Xi]
    assert np.max(np.abs(np.array(h_r) - h_i)) < 0.05e-3
    assert np.max(np.abs(Ur[:, 0] - Ui[:, 0])) < 0.1


def test_infeasible_target_is_clipped_and_reported(model):
    s = MPCSettings(p_max=15e3, p_margin=1e3, budget=5.0)
    c = NMPC(ACT, PN, s, model=model)
    c.step(0.0, est(h=2e-3, p=11.7e3, F=W400), Reference(8e-3))
    assert c.last["target_clipped"] and c.last["reference_used"] < 4e-3
    assert c.stats()["target_clipped_steps"] == 1


def test_fallback_chain_shifted_plan_then_safe(model):
    s = MPCSettings(budget=5.0, fail_window=(0.1, 10.0), fallback_plan_steps=3)
    c = NMPC(ACT, PN, s, model=model)
    loop = supervised(c)
    e = est(h=2e-3, p=11.7e3, F=W400)
    loop.control(0.0, e, Reference(6e-3))
    plan = c.plan.copy()
    cmds = [loop.control(0.02 * (k + 5), e, Reference(6e-3)) for k in range(5)]
    for k in range(3):
        assert cmds[k].as_array() == pytest.approx(plan[k + 1])
    assert cmds[3] == SAFE_COMMAND and cmds[4] == SAFE_COMMAND
    st = loop.stats()
    assert st["fallbacks"] == 5 and st["fallback_detail"]["solver_failed"] == 5
    assert st["fallback_detail"]["shifted_plan"] == 3 and st["fallback_detail"]["safe_command"] == 2


def test_overrun_counts_and_uses_shifted_plan(model):
    c = NMPC(ACT, PN, MPCSettings(budget=1e-9, enforce_budget=True), model=model)
    loop = supervised(c)
    e = est(h=2e-3, p=11.7e3, F=W400)
    loop.control(0.0, e, Reference(6e-3))  # cold start: exempt
    plan = c.plan.copy()
    cmd = loop.control(0.02, e, Reference(6e-3))
    assert loop.stats()["fallback_detail"]["overrun"] == 1
    assert cmd.as_array() == pytest.approx(plan[1])


def test_non_finite_estimate_is_a_fallback_not_a_crash(model):
    c = NMPC(ACT, PN, MPCSettings(budget=5.0), model=model)
    loop = supervised(c)
    cmd = loop.control(0.0, est(h=float("nan"), p=float("nan")), Reference(5e-3))
    assert cmd == SAFE_COMMAND and loop.stats()["fallbacks"] == 1


def test_guard_cuts_pump_at_the_limit(model):
    c = NMPC(ACT, PN, MPCSettings(budget=5.0, p_max=20e3), model=model)
    loop = supervised(c)
    cmd = loop.control(0.0, est(h=5e-3, p=19.9e3, F=W400), Reference(12e-3))
    assert cmd.speed == 0.0 and cmd.outlet == 1.0
    # the guard itself, on a command that would pump at the limit (e.g. a stale fallback plan)
    sup = loop.supervisor
    g = sup.apply(0.0, np.array([1.0, 1.0, 0.0]), 19.9e3)
    assert list(g) == [0.0, 0.0, 1.0] and loop.stats()["guard_activations"] >= 1
    assert list(sup.apply(0.0, np.array([1.0, 1.0, 0.0]), 15e3)) == [1.0, 1.0, 0.0]


@pytest.mark.slow
def test_instances_share_no_state(model):
    e1, e2 = est(h=2e-3, p=11.7e3, F=W400), est(h=6e-3, p=19e3, F=W400)
    a, b = NMPC(ACT, PN, MPCSettings(budget=5.0), model=model), NMPC(ACT, PN, MPCSettings(budget=5.0), model=model)
    ref = NMPC(ACT, PN, MPCSettings(budget=5.0), model=model)
    out_a = []
    for k in range(3):
        out_a.append(a.step(0.02 * k, e1, Reference(5e-3)).as_array())
        b.step(0.02 * k, e2, Reference(3e-3))
    out_ref = [ref.step(0.02 * k, e1, Reference(5e-3)).as_array() for k in range(3)]
    assert np.allclose(out_a, out_ref, atol=1e-6)


# --- baselines -----------------------------------------------------------------------------------
def test_pid_pumps_vents_and_guards():
    c = PIDController(settings=PIDSettings())
    assert c.step(0.0, est(h=2e-3, p=10e3), Reference(5e-3)).speed == 1.0
    c.reset()
    d = c.step(0.0, est(h=6e-3, p=10e3), Reference(5e-3))
    assert d.speed == 0.0 and d.outlet > 0
    c.reset()
    g = supervised(c).control(0.0, est(h=2e-3, p=34.8e3), Reference(5e-3))
    assert g.speed == 0.0 and g.outlet == 1.0


def test_bang_bang_hysteresis(model):
    c = BangBangController(ACT, PN, BangBangSettings(band=500.0), model=model)
    p_set = c.setpoint(5e-3, W400)
    assert p_set == pytest.approx(float(model.Pp(model.x_at_height(5e-3, W400), W400)), rel=0.02)
    assert c.step(0, est(h=4e-3, p=p_set - 1000, F=W400), Reference(5e-3)).speed == 1.0
    assert c.step(0, est(h=4e-3, p=p_set - 200, F=W400), Reference(5e-3)).speed == 1.0  # inside band: keep
    assert c.step(0, est(h=5e-3, p=p_set + 10, F=W400), Reference(5e-3)).speed == 0.0  # reached: hold
    assert c.step(0, est(h=5e-3, p=p_set + 1000, F=W400), Reference(5e-3)).outlet == 1.0


def test_preview_anticipates_a_coming_step(model):
    e = est(h=5e-3, p=17.5e3, F=W400)
    c = NMPC(ACT, PN, MPCSettings(budget=5.0), model=model)
    hold = c.step(0.0, e, Reference(5e-3))
    c.reset()
    pv = [5e-3] * 5 + [7e-3] * 15  # the target rises 0.1 s from now
    ahead = c.step(0.0, e, Reference(5e-3), preview=pv)
    assert hold.speed < 0.05 and ahead.speed > 0.5
    with pytest.raises(ValueError, match="preview"):
        c.step(0.02, e, Reference(5e-3), preview=[float("nan")])


@pytest.mark.parametrize("bad, index", [([5e-3, float("inf")], 1), ([5e-3, 5e-3, "6e-3"], 2), ([True], 0),
                                        ([5e-3, None], 1), ((5e-3, float("nan")), 1),
                                        (np.array([5e-3, np.nan]), 1)])
def test_bad_preview_entry_is_named(model, bad, index):
    """A preview entry that is not a finite number (inf, a string, a bool, None, NaN), in a list, a
    tuple or an array, is refused with its index named."""
    c = NMPC(Actuator(), Pneumatics(), MPCSettings(horizon=10), model=model)
    e = Estimate(t=0.0, h1=1e-3, h2=0.0, h=1e-3, F=0.0, p=2e3)
    with pytest.raises(ValueError, match=rf"preview\[{index}\]"):
        c.step(0.0, e, Reference(5e-3), preview=bad)


def test_every_settings_field_is_documented():
    from dataclasses import fields

    for cls in (MPCSettings, PIDSettings, BangBangSettings):
        doc = cls.__doc__
        for f in fields(cls):
            declared = f.metadata.get("setting")
            assert (declared is not None and declared.doc) or f"{f.name} :" in doc, \
                f"{cls.__name__}.{f.name} is undocumented"


@pytest.mark.slow
@pytest.mark.parametrize("membrane", ["cap", "exact"])
def test_compiled_problem_equals_the_python_reference_over_a_wandering_estimate(membrane):
    """The step's problem from one compiled mpc_prep call (NMPC._problem) equals the Python reference
    (load filter, path, reach, clipped targets, integral action) tick by tick: resting and lifted
    estimates, a non-finite force, a held reference (None), a preview, a target beyond reach and a
    target step, with the two controllers' states carried separately."""
    s = MPCSettings(membrane=membrane)
    a = NMPC(ACT, PN, s)
    b = NMPC(ACT, PN, s, model=a.model)
    rng = np.random.default_rng(7)
    clipped = held = 0
    for k in range(200):
        t = k * s.sample_period
        target = 5e-3 if k < 80 else (30e-3 if k < 120 else 7e-3)  # 30 mm: beyond reach, clipped
        h = float(rng.choice([0.0, max(target - 0.5e-3 + rng.normal(0, 0.3e-3), 0.0)]))
        F = float("nan") if k % 37 == 5 else float(rng.uniform(3.0, 4.5))
        flags = frozenset({"resting"}) if h == 0.0 else frozenset()
        e = Estimate(t=t, h1=h, h2=0.0, h=h, p=float(rng.uniform(5e3, 30e3)), F=F, flags=flags)
        ref = Reference(None) if 40 <= k < 50 else Reference(target)
        held += ref.height is None
        pv = [target + 1e-4 * j for j in range(s.horizon)] if k % 3 == 0 and ref.height is not None else None
        pa, pb = a._problem(t, e, ref, pv), problem_reference(b, t, e, ref, pv)
        for name in ("x0", "W", "dh", "dp", "p_lim"):
            assert getattr(pa, name) == pytest.approx(getattr(pb, name), rel=1e-12, abs=1e-12), (k, name)
        np.testing.assert_allclose(pa.r, pb.r, rtol=0, atol=1e-12)
        for key in ("reference", "reference_used", "integral_shift", "reachable_height", "target_clipped"):
            assert a.last[key] == pytest.approx(b.last[key], rel=1e-12, abs=1e-12), (k, key)
        clipped += a.last["target_clipped"]
        a._t_prev = b._t_prev = t
    assert a.clipped_count == b.clipped_count == clipped > 0 and held == 10
