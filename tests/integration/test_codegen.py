"""Code generation: the plant step Function, the loop description, the generated C closed loop.

The C loop is built with the system compiler (skipped where there is none) and compared with the Python
path, which runs the same stages on the same compiled Functions from Python.
"""

from __future__ import annotations

import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from typer.testing import CliRunner

from cli_checks import one_line_error
from hbma_ctrl.app.cli.main import app
from checkout import ROOT
from hbma_ctrl.core.loopgen import LOG, LIBRARY, LogColumn, LoopSpec, Stage, run_python
from hbma_ctrl.core.loopgen_c import build_c, compare, find_compiler, run_c, write_c
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.models.fidelity import OUTPUTS
from hbma_ctrl.sim.plant_step import (
    initial_plant_state,
    plant_step_function,
    plant_step_support,
    sensor_lag_function,
    valve_line_function,
)
from hbma_ctrl.sim.rig import CAP_RIG, Rig, RigSettings
from oracles.mpc_prep import problem_reference

CC = find_compiler()
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH to build the generated loop")
TRACK = str(ROOT / "scenarios" / "track_height_cap.toml")
#: the default rig and models: the exact membrane, valve timing, pump tilt, sensor lag; the EKF's delays
#: and the controller's minimum on-time shaping
DEFAULT_TRACK = str(ROOT / "scenarios" / "track_height.toml")


def _commands(k: int, rng) -> np.ndarray:
    """Pump 1 s, vent 1 s, repeated, with a random command every 0.5 s: lift-offs and touch-downs."""
    if k % 50 == 0:
        return rng.random(3)
    return np.array([1.0, 1.0, 0.0]) if (k // 100) % 2 == 0 else np.array([0.0, 0.0, 1.0])


@pytest.mark.slow
@pytest.mark.parametrize("scenario", [TRACK, DEFAULT_TRACK])
def test_plant_step_equals_the_rig_sample_by_sample(scenario):
    """The rig's period as Functions (valve line, plant, sensor lag) equals :class:`Rig` bit for bit, on
    the cap rig and on the default rig (the exact membrane, valve delay and minimum opening, tilted pump
    map, sensor lag), through lift-offs and touch-downs."""
    scn = load_scenario(scenario)
    rs = scn.role("rig")
    rig = Rig(scn.actuator, scn.pneumatics, scn.platform, rs)
    fid, plant = rig._plant.fid, rig._plant
    assert fid.name == "platform"
    timed = rs.valve_delay > 0 or rs.valve_min_on > 0
    assert timed == (scenario == DEFAULT_TRACK) and (rs.sensor_tau > 0) == timed
    nsub = int(round(rs.sample_period / plant.dt))
    f = plant_step_function(fid, rs.integrator, plant.dt, nsub, per_substep=timed)
    line, lag = valve_line_function(rs, nsub), sensor_lag_function(rs)
    hist = np.zeros(line.nnz_in(1))
    theta = plant.thetas[:, 0].copy()
    x, mode, y = initial_plant_state(fid, theta)
    sensed = prev = float(y[OUTPUTS.index("p")])
    rng = np.random.default_rng(3)
    worst, modes = 0.0, set()
    for k in range(450):
        u = _commands(k, rng)
        if timed and k % 50 == 25:
            u = np.array([0.8, 0.1, 0.0])  # a duty under the 2 ms minimum opening: lengthened to it
        rig.apply(u)
        if timed:
            u_sub, hist = (np.asarray(v) for v in line(u, hist.reshape(3, -1, order="F")))
            hist = hist.ravel(order="F")
        else:
            u_sub = u
        x, m, y = (np.asarray(v).ravel() for v in f(x, mode, u_sub, theta))
        sensed, prev = (float(v) for v in lag(sensed, prev, y))
        mode = float(m[0])
        modes.add(mode)
        worst = max(worst, float(np.max(np.abs(y - rig._plant.y[:, 0]))), abs(mode - float(rig._plant.mode[0])),
                    abs(sensed - rig._p_sensed))
    assert any(name == "lift_off" for _, name in rig.events) and any(name == "touch_down" for _, name in rig.events)
    assert modes == {0.0, 1.0}
    assert worst == 0.0  # the same stages, projection and events in the same order: bitwise equal


def test_plant_step_support_refuses_only_the_quasi_static_snap_through():
    """Every membrane law, valve timing, pump map and sensor lag generates (the default rig has them
    all); the quasi-static rig's snap-through search does not, and the message names its key."""
    assert plant_step_support("platform", RigSettings()) is None
    assert plant_step_support("free", RigSettings(**CAP_RIG)) is None
    why = plant_step_support("quasi_static", RigSettings(fidelity="quasi_static"))
    assert why.startswith("[rig] fidelity = 'quasi_static'")


@pytest.mark.parametrize("valve_delay, sensor_delay", [(0.005, 0.003), (0.0, 0.003), (0.015, 0.0), (0.025, 0.007)])
@pytest.mark.parametrize("initialised", [True, False])
def test_acting_function_equals_the_command_timing(valve_delay, sensor_delay, initialised):
    """The EKF's acting command as a Function (for the C loop) gives CommandTiming.acting's bits, from an
    empty history or after a filter's first reading (k = 0), the history filling then rolling."""
    from hbma_ctrl.models.actuation import CommandTiming, acting_function

    tm = CommandTiming(0.01, valve_delay, sensor_delay)
    f = acting_function(tm)
    hist, fill = np.zeros(3 * tm._keep), 0.0
    if initialised:
        tm.acting(np.zeros(3), 0)
        fill = 1.0
    rng = np.random.default_rng(4)
    for _ in range(60):
        u = rng.random(3) * (rng.random(3) < 0.7)
        want = tm.acting(u, 1)
        got, hist, fill = (np.asarray(v).ravel(order="F") for v in f(u, hist.reshape(3, -1, order="F"), fill))
        assert np.array_equal(got, want)
    assert fill[0] == tm._keep


def _toy_spec(n: int = 60) -> LoopSpec:
    """A small loop that uses every stage option: every, gate / gate_off, repeat with stop_on, NaN data."""
    x, z, g = ca.SX.sym("x"), ca.SX.sym("z"), ca.SX.sym("g")
    seen = ca.logic_and(z > -ca.inf, z < ca.inf)  # NaN = no reading (casadi folds z == z to true)
    filt = ca.Function("filt", [x, z], [ca.if_else(seen, x + 0.5 * (z - x), x)])
    ctrl = ca.Function("ctrl", [x, g], [ca.sin(g - x), (g - x) > 0.5])
    it = ca.Function("iterate", [x], [0.5 * (x + 2.0 / x), ca.fabs(x * x - 2.0) < 1e-9])  # Newton for sqrt(2)
    seed = ca.Function("seed", [x], [1.0 + 0 * x, 0 * x])
    pair = ca.Function("pair", [x], [ca.vertcat(ca.SX(1, 1), 2 * x)])  # a structurally sparse output
    assert not pair.sparsity_out(0).is_dense()
    rng = np.random.default_rng(0)
    z = rng.standard_normal(n)
    z[::7] = np.nan
    return LoopSpec("toy", 0.01, n, {"x": [0.0], "z": [0.0], "g": [0.0], "u": [0.0], "far": [0.0], "root": [0.0],
                                     "done": [0.0], "pair": [0.0, 0.0]},
                    {"z": z, "g": np.linspace(0, 3, n)},
                    [Stage(filt, ["x", "z"], ["x"]), Stage(ctrl, ["x", "g"], ["u", "far"], every=3),
                     Stage(seed, ["x"], ["root", "done"], gate="far"),
                     Stage(it, ["root"], ["root", "done"], gate="far", repeat=50, stop_on="done"),
                     Stage(pair, ["x"], ["pair"]),
                     LOG, Stage(filt, ["x", "u"], ["x"], gate="far", gate_off=True)],
                    [LogColumn("x_mm", "x", 0, 1e3), LogColumn("u", "u"), LogColumn("root", "root"),
                     LogColumn("z", "z"), LogColumn("twice_x", "pair", 1)])


@pytest.mark.compiling
def test_loop_description_runs_the_same_in_python_and_in_c(tmp_path):
    spec = _toy_spec()
    py = run_python(spec)
    x = py.trajectory[:, 1] / 1e3
    assert np.all(np.isfinite(x)) and np.isnan(py.trajectory[:, 4]).any()  # NaN readings pass through the log
    roots = py.trajectory[:, 3]
    assert np.any(np.abs(roots - np.sqrt(2)) < 1e-12)  # the repeated stage iterated to its stop condition
    np.testing.assert_allclose(py.trajectory[:, 5], 2 * x, rtol=1e-14)  # the sparse output lands densified
    if CC is None:
        pytest.skip("no C compiler (cc, gcc or clang) on PATH to build the generated loop")
    write_c(spec, tmp_path)
    build_c(tmp_path, opt="-O0")
    c = run_c(tmp_path)
    assert c.header == spec.header()
    diff = compare(spec, py, c)
    assert max(diff.values()) == 0.0, diff
    # every call is timed: filt twice per tick where the gate is off, ctrl every third tick
    assert c.times["functions"]["ctrl"]["calls"] == len(range(0, spec.n_ticks, 3))
    lib = run_python(spec, tmp_path / LIBRARY)  # the library of the same object code
    assert np.array_equal(np.nan_to_num(lib.trajectory, nan=7.0), np.nan_to_num(c.trajectory, nan=7.0))


@pytest.mark.slow
def test_mpc_prep_matches_the_nmpc_problem():
    from hbma_ctrl.controllers.mpc import NMPC
    from hbma_ctrl.controllers.mpc_prep import problem_function
    from hbma_ctrl.core.interfaces import Estimate, Reference

    scn = load_scenario(TRACK)
    s = scn.role("controller").mpc
    nmpc = NMPC(scn.actuator, scn.pneumatics, s)
    prep = problem_function(nmpc.model, s)
    rng = np.random.default_rng(1)
    for _ in range(40):
        h = float(rng.choice([0.0, rng.uniform(0.0, 0.015)]))
        p, F, r = rng.uniform(0, 40e3), rng.uniform(0, 8), rng.uniform(0, 0.012)
        nmpc._W = None
        pr = problem_reference(nmpc, 0.0, Estimate(t=0.0, h1=h, h2=0.0, h=h, p=p, F=F), Reference(r))
        nmpc._int_target = None  # each draw a new step for both (mpc_prep's has_I = 0)
        pr = problem_reference(nmpc, 0.0, Estimate(t=0.0, h1=h, h2=0.0, h=h, p=p, F=F), Reference(r))
        out = [np.asarray(v).ravel() for v in prep(h, p, F, 0.0, np.full(s.horizon, r), r, 0.0, 0.0, 0.0, 0.0,
                                                   0.5, 0.0, 0.0, 0.0, s.sample_period)]
        got = np.array([out[0][0], out[1][0], out[2][0], out[3][0]])
        want = np.array([pr.x0, pr.W, pr.dh, pr.dp])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out[5], pr.r, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_mpc_prep_integral_action_matches_the_nmpc_over_a_held_target():
    """The integral action carried through mpc_prep's state (I, its target, has_I) equals the
    NMPC's over 60 controller periods at one target with the estimate wandering around it, then a
    target step that restarts it."""
    I_hist = _prep_against_nmpc(lambda t, k: 5e-3 if k < 60 else 7e-3, preview=False)
    assert 0.5e-3 < I_hist[59] <= 1e-3  # the standing 0.6 mm error was integrated (capped at 1 mm)
    assert I_hist[60] == 0.0  # the step restarted it


@pytest.mark.slow
def test_mpc_prep_integral_action_takes_the_target_now_not_the_preview():
    """With a preview (a ramp) the horizon's targets are the future ones but the integral action
    integrates the error to the target now, as the NMPC does: mpc_prep equals it tick by tick. (It
    took the preview's first target once, which parted the generated ramp loop from the scene's.)"""
    I_hist = _prep_against_nmpc(lambda t, k: 3e-3 + 1e-3 * t, preview=True)
    assert any(v != 0.0 for v in I_hist)


def _prep_against_nmpc(target, preview: bool) -> list:
    """mpc_prep's horizon targets and integral shift against NMPC._problem over 80 controller periods of
    ``target(t, k)`` (m), the estimate 0.6 mm under it with noise; returns mpc_prep's shifts."""
    from hbma_ctrl.controllers.mpc import NMPC
    from hbma_ctrl.controllers.mpc_prep import problem_function
    from hbma_ctrl.core.interfaces import Estimate, Reference

    scn = load_scenario(TRACK)
    s = scn.role("controller").mpc
    nmpc = NMPC(scn.actuator, scn.pneumatics, s)
    prep = problem_function(nmpc.model, s)
    rng = np.random.default_rng(2)
    I, I_t, has_I = 0.0, 0.0, 0.0
    shifts = []
    for k in range(80):
        t = k * s.sample_period
        r = target(t, k)
        pv = [target(t + s.sample_period * (j + 1), k) for j in range(s.horizon)] if preview else None
        h = r - 0.6e-3 + rng.normal(0.0, 0.2e-3)
        pr = problem_reference(nmpc, t, Estimate(t=t, h1=h, h2=0.0, h=h, p=20e3, F=3.9), Reference(r), pv)
        r_in = np.array(pv) if preview else np.full(s.horizon, r)
        out = [np.asarray(v).ravel() for v in prep(h, 20e3, 3.9, 0.0, r_in, r, 0.0, 0.0, 0.0, 0.0,
                                                   0.5, I, I_t, has_I, s.sample_period)]
        np.testing.assert_allclose(out[5], pr.r, rtol=0, atol=1e-12)
        I, I_t, has_I = float(out[10][0]), float(out[11][0]), float(out[12][0])
        assert I == pytest.approx(nmpc.last["integral_shift"], abs=1e-15)
        shifts.append(I)
    return shifts


@pytest.mark.slow
@pytest.mark.compiling
@needs_cc
@pytest.mark.parametrize("scenario, T", [(TRACK, 4.0), (DEFAULT_TRACK, 4.2)])
def test_generated_track_height_loop_equals_the_python_path_and_follows_the_scene(tmp_path, scenario, T):
    """On the cap rig and on the default one (its structure, the EKF's delays, the minimum on-time
    shaping), the C loop equals its Python path and follows the scene's own closed loop. 4 s: past the
    first target step (2 -> 8 mm at 3 s); the default's 4.2 s include its two failed solves at 4.1 s."""
    from dataclasses import replace

    from hbma_ctrl.app.codegen.chamber import scenario_loop
    from hbma_ctrl.app.scenes.controller import closed_loop
    from hbma_ctrl.system.roles import estimator_from_scenario

    scn = load_scenario(scenario)
    spec = scenario_loop(scn, duration=T)
    write_c(spec, tmp_path)
    for name in ("hbma_steps.c", "hbma_steps.h", "closed_loop.c", "loop_data.h", "Makefile", "README.txt"):
        assert (tmp_path / name).is_file()
    header = (tmp_path / "hbma_steps.h").read_text()
    for fn in ("plant_step", "ekf_step", "rti_step"):
        assert f"int {fn}(const casadi_real** arg" in header
    build_c(tmp_path, opt="-O0")
    c = run_c(tmp_path)
    py = run_python(spec, tmp_path / LIBRARY)
    diff = compare(spec, py, c)
    assert max(diff.values()) <= 1e-9, diff
    col = {n: i for i, n in enumerate(spec.header())}
    assert c.trajectory[:, col["h_true_mm"]].max() > 4.0  # lifted to 2 mm, then on its way to 8 mm: not trivial
    times = json.loads((tmp_path / "times.json").read_text())["functions"]
    assert times["plant_step"]["calls"] == spec.n_ticks and times["rti_step"]["calls"] >= spec.n_ticks // 2

    # the scene's own closed loop (Rig, EKF, NMPC calling the same RTI Function, ChamberLoop with its
    # supervisor), without the start-up calibration and with a budget no solve reaches (an overrun is
    # wall-clock dependent): the roles' Functions reproduce what the Python classes do around the steps
    sec = scn.role("controller")
    sec = replace(sec, mpc=replace(sec.mpc, variant="rti_fn_osqp", budget=10.0))
    rs = scn.role("rig")
    log = closed_loop(scn.actuator, scn.pneumatics, scn.platform, sec, T, rs,
                      estimator=estimator_from_scenario(scn, rs), calibrate=False)
    assert py.trajectory[-1, col["ekf_reference_events"]] == 0  # no step left to the EKF's reference path
    np.testing.assert_allclose(py.trajectory[:, col["h_true_mm"]] / 1e3, log.h_true, rtol=0, atol=1e-9)
    np.testing.assert_allclose(py.trajectory[:, col["h_est_mm"]] / 1e3, log.h_est, rtol=0, atol=1e-9)
    np.testing.assert_allclose(py.trajectory[:, col["p_est_kpa"]] * 1e3, log.p_est, rtol=0, atol=1e-6)
    got_u = py.trajectory[:, [col["speed"], col["inlet"], col["outlet"]]]
    np.testing.assert_allclose(got_u, log.u, rtol=0, atol=1e-9)
    failed = np.nonzero(py.trajectory[:, col["mpc_status"]])[0]
    # every QP solved to OSQP's own test is used (rti_step.usable_tolerance): none fails, in either loop
    assert len(failed) == 0 and len(log.supervisor_events) == 0

    # the C run's metrics.json objects are the scene's metrics of its own trajectory
    from hbma_ctrl.app.codegen.chamber import loop_run_metrics
    from hbma_ctrl.app.scenes.controller import loop_metrics

    m = loop_run_metrics(scn, spec, c.trajectory)
    want = loop_metrics(log, sec)
    assert m["controller"]["height_rmse_mm"] == pytest.approx(want["height_rmse_mm"], abs=1e-6)
    assert m["controller"]["steps_settled"] == want["steps_settled"] and m["controller"]["steps_total"] == 2
    assert m["controller"]["fallbacks"] == len(log.supervisor_events)
    assert m["controller"]["variant"] == "rti_fn_osqp" and m["controller"]["solve_ms_median"] is None
    assert m["estimator"]["height_rmse_mm"] == pytest.approx(want["height_est_rmse_mm"], abs=1e-6)
    assert m["estimator"]["reference_path_events"] == 0


def _cli(args):
    return CliRunner().invoke(app, args)


@pytest.mark.slow
def test_codegen_cli_bad_inputs_are_one_error_line(tmp_path):
    robot = str(ROOT / "scenarios" / "robot_bending.toml")
    one_line_error(_cli(["codegen", robot, "--out", str(tmp_path / "a"), "--estimator", "truth"]), "--estimator", "ekf")
    one_line_error(_cli(["codegen", robot, "--out", str(tmp_path / "a"), "--qp-solver", "qrqp"]), "--qp-solver", "osqp")
    one_line_error(_cli(["codegen", str(ROOT / "scenarios" / "robot_sequential.toml"), "--out", str(tmp_path / "a")]),
                   "mode = 'closed_loop'")
    pid = tmp_path / "pid.toml"
    pid.write_text(Path(robot).read_text().replace('controller = "mpc"', 'controller = "pressure_pid"'))
    one_line_error(_cli(["codegen", str(pid), "--out", str(tmp_path / "a")]), "[robot] controller = 'pressure_pid'")
    budget = tmp_path / "budget.toml"
    budget.write_text(Path(robot).read_text().replace('horizon = 15',
                                                       'horizon = 15\nmpc_budget = 0.7\nenforce_budget = true'))
    one_line_error(_cli(["codegen", str(budget), "--out", str(tmp_path / "a")]), "enforce_budget = true")
    enforced = tmp_path / "enforced.toml"
    enforced.write_text(Path(TRACK).read_text().replace("[controller]\n", "[controller]\nenforce_budget = true\n", 1))
    one_line_error(_cli(["codegen", str(enforced), "--out", str(tmp_path / "a")]), "enforce_budget = true")
    one_line_error(_cli(["codegen", TRACK, "--out", str(tmp_path / "b"), "--duration-s", "-1"]),
                   "--duration-s = -1", "(0, 3600] s")
    one_line_error(_cli(["codegen", TRACK, "--out", str(tmp_path / "c"), "--estimator", "ukf"]), "--estimator", "ekf")
    one_line_error(_cli(["codegen", str(ROOT / "scenarios" / "open_loop_fig7.toml"), "--out", str(tmp_path / "d")]), "[controller]")
    bad = tmp_path / "qs.toml"
    bad.write_text(Path(TRACK).read_text().replace("[rig]\n", "[rig]\nfidelity = \"quasi_static\"\n"))
    one_line_error(_cli(["codegen", str(bad), "--out", str(tmp_path / "e")]), "qs.toml", "[rig] fidelity")
    assert not any((tmp_path / d).exists() for d in "abcde")


@pytest.mark.slow
def test_codegen_cli_writes_the_sources(tmp_path):
    res = _cli(["codegen", TRACK, "--out", str(tmp_path / "gen"), "--duration-s", "0.1", "--estimator", "truth"])
    assert res.exit_code == 0, res.output
    names = {p.name for p in (tmp_path / "gen").iterdir()}
    assert {"hbma_steps.c", "hbma_steps.h", "loop_data.h", "closed_loop.c", "Makefile", "README.txt"} <= names
    readme = (tmp_path / "gen" / "README.txt").read_text()
    assert "cc -O1 -std=c99" in readme and "-losqp" in readme  # the default QP solver's library is linked
    assert "-losqp" in (tmp_path / "gen" / "Makefile").read_text()


@pytest.mark.compiling
@needs_cc
def test_a_call_that_fails_reads_as_failed_in_c_and_in_python(tmp_path):
    """A Function that returns non-zero (here an assertion; in the RTI step a QP solver that gives up)
    leaves its outputs unwritten: the ``fails_to`` signal then reads NaN on exactly those ticks, in the
    C loop and in the Python path on the same library, not the last good call's value."""
    x = ca.MX.sym("x")
    guarded = ca.Function("guarded", [x], [2 * (x * 1).attachAssert(x > 0, "x must be positive"), x + 1],
                          ["x"], ["status", "y"])
    n = 40
    xs = np.where(np.arange(n) % 10 == 7, -1.0, 1.0)  # every tenth call fails
    spec = LoopSpec("fails", 0.01, n, {"x": [0.0], "status": [0.0], "y": [0.0]}, {"x": xs},
                    [Stage(guarded, ["x"], ["status", "y"], fails_to="status")],
                    [LogColumn("status", "status")])
    write_c(spec, tmp_path)
    build_c(tmp_path, opt="-O0")
    c = run_c(tmp_path)
    py = run_python(spec, tmp_path / LIBRARY)
    for run in (c, py):
        status = run.trajectory[:, 1]
        assert np.array_equal(np.isnan(status), xs < 0)
        assert np.all(status[xs > 0] == 2.0)
    assert c.times["functions"]["guarded"]["nonzero_returns"] == int(np.sum(xs < 0))
    with pytest.raises(ValueError, match="fails_to"):
        LoopSpec("bad", 0.01, 1, {"x": [0.0], "status": [0.0], "y": [0.0]}, {},
                 [Stage(guarded, ["x"], ["status", "y"], fails_to="x")], []).validate()


@pytest.mark.slow
@pytest.mark.compiling
@needs_cc
def test_codegen_check_writes_the_c_runs_metrics(tmp_path):
    """``codegen --check`` runs the C loop: its metrics.json holds the controller and estimator objects."""
    res = _cli(["codegen", TRACK, "--out", str(tmp_path / "gen"), "--duration-s", "0.5", "--check", "--opt", "-O0"])
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "gen" / "metrics.json").read_text())
    assert set(m) == {"controller", "estimator"}
    assert m["controller"]["pressure_limit_respected"] is True and m["controller"]["steps_total"] == 1
    assert m["estimator"]["height_rmse_mm"] >= 0.0


@pytest.mark.slow
def test_codegen_cli_says_the_start_up_calibration_is_left_out(tmp_path):
    """The default scenario calibrates before its loop closes; the generated loop does not, and says so
    (on the console and in README.txt) rather than leave a user to find the EKF's prior differs."""
    res = _cli(["codegen", DEFAULT_TRACK, "--out", str(tmp_path / "gen"), "--duration-s", "0.1"])
    assert res.exit_code == 0, res.output
    flat = " ".join(res.output.split())
    assert "left out of the generated loop: the start-up calibration ([controller] calibrate = true)" in flat
    assert "left out: the start-up calibration" in (tmp_path / "gen" / "README.txt").read_text()


@pytest.mark.compiling
@needs_cc
def test_times_json_holds_every_function_and_the_tick(tmp_path):
    spec = _toy_spec(30)
    write_c(spec, tmp_path)
    build_c(tmp_path, opt="-O0")
    times = run_c(tmp_path).times
    assert set(times["functions"]) == {"filt", "ctrl", "iterate", "seed", "pair"}
    assert times["tick"]["calls"] == 30
    for row in list(times["functions"].values()) + [times["tick"]]:
        assert 0 <= row["median_us"] <= row["p99_us"] <= row["max_us"]
