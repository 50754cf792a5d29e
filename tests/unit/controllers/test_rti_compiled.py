"""The RTI step as one casadi Function (hbma_ctrl.controllers.rti_step) and the fatrop variant, against their references.

- the Function's first input equals the reference OSQP path's (solved tightly) on a few states;
- fatrop and IPOPT (same OCP) give the same first input;
- a short closed loop with the one-Function RTI tracks within 1 % of IPOPT's RMSE.
No timing is asserted (``hbma-ctrl bench mpc`` measures it).
"""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.controllers.mpc_solvers import _Fatrop, _Ipopt, _Problem
from hbma_ctrl.controllers.rti_c import _RtiOsqp
from hbma_ctrl.controllers.rti_step import _RtiFunction, rti_step_function
from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics

ACT, PN = Actuator(), Pneumatics()
W400 = 0.4 * 9.80665
# (height now, target) m: pumping up hard, a small rise, venting down
CASES = [(5.0e-3, 5.3e-3), (5.0e-3, 5.05e-3), (6.0e-3, 5.6e-3)]


@pytest.fixture(scope="module")
def model(cap_prediction_model):
    return cap_prediction_model  # the OCP on the cap chamber


def _problem(model, s, h, r, u_prev=(0.3, 0.5, 0.1)):
    x0 = model.x_at_height(h, W400)
    return _Problem(x0, W400, 1e-4, 300.0, np.full(s.horizon, r), np.array(u_prev), s.p_max - s.p_margin)


def test_function_signature_is_numeric_and_named(model):
    """The Function has the documented named inputs and outputs, all dense (codegen needs that)."""
    s = MPCSettings(horizon=6)
    f = rti_step_function(model, s, "hpipm")
    assert f.name_in() == ["x0", "W", "dh", "dp", "u_prev", "p_lim", "r", "X_guess", "U_guess",
                           "lam_x_guess", "lam_a_guess", "shift"]
    assert f.name_out() == ["u0", "X_plan", "U_plan", "lam_x", "lam_a", "status", "residual", "cost"]
    assert f.size_in("r") == (6, 1) and f.size_in("U_guess") == (3, 6) and f.size_out("u0") == (3, 1)
    assert all(f.sparsity_in(i).is_dense() for i in range(f.n_in()))
    assert f.nnz_in("lam_x_guess") == 8 * 6 + 4 and f.nnz_in("lam_a_guess") == 11 * 6


@pytest.mark.parametrize("qp_solver", ["hpipm", "osqp"])
@pytest.mark.parametrize("h, r", CASES)
def test_function_first_input_equals_reference_osqp_path(model, qp_solver, h, r):
    """Cold start (rti_init_iterations QPs) then one shifted step: the one-Function RTI's first input
    equals the reference _RtiOsqp's (OSQP at 1e-8) within the IPM's tolerance."""
    s = MPCSettings(codegen=False, qp_eps=1e-8, qp_max_iter=100000, budget=10.0).validate()
    ref, fn = _RtiOsqp(model, s), _RtiFunction(model, s, qp_solver)
    pr = _problem(model, s, h, r)
    _, U_ref = ref.solve(pr)
    _, U_fn = fn.solve(pr)
    assert np.abs(U_fn[0] - U_ref[0]).max() < 3e-3
    X1 = ref.X[1]
    pr2 = replace(pr, x0=X1, u_prev=U_ref[0].copy())
    _, U_ref2 = ref.solve(pr2)
    _, U_fn2 = fn.solve(pr2)
    assert np.abs(U_fn2[0] - U_ref2[0]).max() < 3e-3


def test_function_reports_a_bad_state_as_failure_not_a_command(model):
    """A non-finite state gives status 1 (the NMPC turns it into a solver failure)."""
    s = MPCSettings(horizon=5)
    f = rti_step_function(model, s, "hpipm")
    N = s.horizon
    out = f(np.nan, W400, 0.0, 0.0, [0.2, 0.3, 0.0], 34e3, np.full(N, 5e-3), np.full(N + 1, 1.0),
            ca.DM.zeros(3, N), np.zeros(f.nnz_in(9)), np.zeros(f.nnz_in(10)), 0.0)
    assert float(out[5]) == 1.0


@pytest.mark.parametrize("h, r", CASES[::2])
def test_fatrop_and_ipopt_give_the_same_first_input(model, h, r):
    """fatrop on the stage-form OCP and IPOPT on the original give the same first input."""
    s = MPCSettings(variant="ipopt", codegen=False, budget=10.0).validate()
    pr = _problem(model, s, h, r)
    _, U_ip = _Ipopt(model, s).solve(pr)
    _, U_fa = _Fatrop(model, s).solve(pr)
    assert np.abs(U_fa[0] - U_ip[0]).max() < 1e-2


def _same_plans(model, s, gen, vm, atol: float, rtol: float) -> None:
    """A generated solver (mode "c", no statistics) and the same on the virtual machine give the same
    first inputs (atol) and state plans (rtol), warm-started over CASES."""
    assert (gen.mode, vm.mode) == ("c", "vm")
    for h, r in CASES:
        X1, U1 = gen.solve(_problem(model, s, h, r))
        X2, U2 = vm.solve(_problem(model, s, h, r))
        np.testing.assert_allclose(U1, U2, atol=atol)
        np.testing.assert_allclose(X1, X2, rtol=rtol)
    assert gen.iterations is None and vm.iterations > 0


@pytest.mark.slow
@pytest.mark.compiling
def test_generated_fatrop_equals_the_virtual_machines(model, monkeypatch):
    """fatrop generated as C (``codegen``, built once and cached) gives the first input and plan of the
    same solver on casadi's virtual machine, warm-started over three steps, also with other weights
    (which the same library serves); a solve that does not converge (an iteration cap of 2) is a
    _SolverFailure in both modes. N = 6 keeps the build short."""
    from hbma_ctrl.controllers.mpc_solvers import _SolverFailure
    from hbma_ctrl.core.codegen import OPT_ENV, has_compiler

    if not has_compiler():
        pytest.skip("no C compiler on this machine: fatrop runs on casadi's virtual machine only")
    # what the generated solver computes does not depend on the optimisation (no level enables
    # fast-math): built unoptimised, in seconds instead of a minute
    monkeypatch.setenv(OPT_ENV, "-O0")
    s = MPCSettings(variant="fatrop", horizon=6, budget=10.0).validate()
    gen, vm = _Fatrop(model, s), _Fatrop(model, replace(s, codegen=False))
    _same_plans(model, s, gen, vm, atol=1e-8, rtol=1e-9)
    # other weights (a tuning study's trial): the same library, their own optimum
    w = dict(w_terminal=2.0, w_rate=(0.05, 0.004, 0.01), c_input=(0.03, 0.0, 0.01))
    gen2, vm2 = _Fatrop(model, replace(s, **w)), _Fatrop(model, replace(s, codegen=False, **w))
    assert gen2.solver is gen.solver
    X1, U1 = gen2.solve(_problem(model, s, *CASES[0]))
    X2, U2 = vm2.solve(_problem(model, s, *CASES[0]))
    np.testing.assert_allclose(U1, U2, atol=1e-8)
    assert np.abs(U1 - gen.solve(_problem(model, s, *CASES[0]))[1]).max() > 1e-6  # the weights count
    capped = replace(s, ipopt_max_iter=2)
    for b in (_Fatrop(model, capped), _Fatrop(model, replace(capped, codegen=False))):
        with pytest.raises(_SolverFailure, match="fatrop"):
            b.solve(_problem(model, s, *CASES[0]))


@pytest.mark.slow
@pytest.mark.compiling
def test_generated_ipopt_equals_the_virtual_machines(model, monkeypatch):
    """IPOPT generated as C (``bench mpc --ipopt-c``) gives the virtual machine's plan, warm-started over
    the cases, and refuses a solve capped at 2 iterations as a _SolverFailure. N = 4 keeps the build short."""
    from hbma_ctrl.controllers.mpc_solvers import _SolverFailure
    from hbma_ctrl.core.codegen import OPT_ENV, has_compiler

    if not has_compiler():
        pytest.skip("no C compiler on this machine: IPOPT runs on casadi's virtual machine only")
    # what the generated solver computes does not depend on the optimisation (no level enables
    # fast-math): built unoptimised, in seconds instead of a minute
    monkeypatch.setenv(OPT_ENV, "-O0")
    s = MPCSettings(variant="ipopt", horizon=4, budget=10.0).validate()
    gen, vm = _Ipopt(model, s, generate=True), _Ipopt(model, s)
    _same_plans(model, s, gen, vm, atol=1e-7, rtol=1e-8)
    with pytest.raises(_SolverFailure, match="ipopt"):
        _Ipopt(model, replace(s, ipopt_max_iter=2), generate=True).solve(_problem(model, s, *CASES[0]))


def test_bench_summary_compares_fatrop_with_both_ipopts():
    """bench mpc's summary: fatrop's speed-up over the shipped IPOPT and, with --ipopt-c, over IPOPT
    generated as C as fatrop is."""
    from hbma_ctrl.app.bench.mpc import summarize

    def row(name, ms, rmse):
        return {"controller": name, "solve_ms_median": ms, "solve_ms_p99": 2 * ms, "height_rmse_mm": rmse}

    rows = [row("ipopt N=20", 32.0, 1.359), row("fatrop N=20", 5.0, 1.348), row("ipopt_c N=20", 16.0, 1.359)]
    out = summarize({"rows": rows})
    assert out["ipopt_over_fatrop_speed"] == pytest.approx(6.4) and out["fatrop_5x_faster_than_ipopt"]
    assert out["ipopt_c_over_fatrop_speed"] == pytest.approx(3.2) and not out["fatrop_5x_faster_than_ipopt_c"]
    assert out["fatrop_rmse_within_1pct"]
    assert "ipopt_c_over_fatrop_speed" not in summarize({"rows": rows[:2]})


def test_bench_ipopt_c_without_a_compiler_is_one_error_line_before_any_row(tmp_path, monkeypatch):
    """``bench mpc --ipopt-c`` on a machine without a C compiler: exit 2, one error line naming the flag,
    and no run directory (nothing measured, nothing lost)."""
    from typer.testing import CliRunner

    from hbma_ctrl.app.cli.main import app
    from hbma_ctrl.core import codegen

    monkeypatch.setattr(codegen, "has_compiler", lambda: False)
    out = tmp_path / "b"
    res = CliRunner().invoke(app, ["bench", "mpc", "--horizons", "20", "--variants", "rti_c_osqp", "--no-baselines",
                                   "--no-dompc", "--ipopt-c", "--out", str(out)])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: --ipopt-c") and "C compiler" in lines[0]
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_unknown_qp_solver_is_refused(model):
    """A solver name outside QP_SOLVERS is a ValueError naming it."""
    with pytest.raises(ValueError, match="qp_solver = 'gurobi'"):
        rti_step_function(model, MPCSettings(), "gurobi")


@pytest.mark.slow
def test_closed_loop_rmse_within_one_percent_of_ipopt(model):
    """2.5 s of the track-height loop (400 g, 2 -> 5 mm, EKF, mismatched noisy rig): the one-Function
    RTI (HPIPM) and fatrop track within 1 % of IPOPT's height RMSE. On the cap rig with the cap
    models, where the solvers' equivalence was measured (bench mpc): on the default rig the same
    three runs spread by 1.3 %, the loop's noise and shaping, not the OCP."""
    from hbma_ctrl.estimators.ekf import EKF, EKFSettings
    from hbma_ctrl.app.scenes.controller import closed_loop, loop_metrics
    from hbma_ctrl.models.defaults import CAP_CHAMBER
    from hbma_ctrl.sim.rig import CAP_RIG, RigSettings

    sec = parse_role("controller", {"kind": "mpc", "variant": "ipopt", "horizon": 20, "sample_ms": 20.0,
                                    "targets_mm": [[0.0, 2.0], [1.2, 5.0]]})
    rmse = {}
    for v in ("ipopt", "rti_fn_hpipm", "fatrop"):
        mpc = replace(sec.mpc, variant=v, budget=10.0, codegen=False).validate()
        c = NMPC(ACT, PN, mpc, model=model)
        rs = RigSettings(seed=1, **CAP_RIG)
        est = EKF(ACT, PN, EKFSettings(sample_period=rs.sample_period, noise_std=rs.noise_std, **CAP_CHAMBER))
        log = closed_loop(ACT, PN, Platform(load=0.4), replace(sec, mpc=mpc, valve_min_on=0.0), 2.5, rs,
                          estimator=est, controller=c)
        m = loop_metrics(log, sec)
        assert m["fallbacks"] == 0, v
        rmse[v] = m["height_rmse_mm"]
    assert rmse["rti_fn_hpipm"] == pytest.approx(rmse["ipopt"], rel=0.01)
    assert rmse["fatrop"] == pytest.approx(rmse["ipopt"], rel=0.01)


@pytest.mark.slow
@pytest.mark.compiling
def test_generated_c_of_the_step_equals_the_function(model):
    """The step as generated C (OSQP, compiled once and cached) gives the Function's outputs to 1e-9
    over a few chained steps (skipped without a C compiler or OSQP's shipped headers)."""
    from hbma_ctrl.controllers.rti_step import compiled_step
    from hbma_ctrl.core.codegen import FastFunction

    s = MPCSettings(horizon=8).validate()
    f = rti_step_function(model, s, "osqp")
    c = compiled_step(f, "osqp")
    if c is None:
        pytest.skip("no C compiler, or the OSQP headers shipped with casadi are missing")
    N, nz, nc = s.horizon, f.nnz_in("lam_x_guess"), f.nnz_in("lam_a_guess")
    x0 = model.x_at_height(5e-3, W400)
    runs = []
    for fun in (f, c):
        F = FastFunction(fun, compile=False)
        X, U, lx, la, sh, x, up = np.full(N + 1, x0), np.tile([0.3, 0.5, 0.1], N), np.zeros(nz), np.zeros(nc), 0.0, \
            x0, np.array([0.3, 0.5, 0.1])
        u0s = []
        for k in range(4):
            o = F(x, W400, 1e-4, 300.0, up, 34e3, np.full(N, 5.4e-3), X, U, lx, la, sh)
            assert o[5][0] == 0.0
            X, U, lx, la = (o[i].copy() for i in range(1, 5))
            up, x, sh = o[0].copy(), X[1], 1.0
            u0s.append(up)
        runs.append(np.array(u0s))
    np.testing.assert_allclose(runs[1], runs[0], atol=1e-9, rtol=0)
