"""Code generation: the plant step Function, the loop description, the generated C closed loop.

The C loop is built with the system compiler (skipped where there is none) and compared with the Python
path, which runs the same stages on the same compiled Functions from Python.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from typer.testing import CliRunner

from cli_checks import one_line_error
from hbma_ctrl.app.cli import app
from hbma_ctrl.app.codegen import LOG, LIBRARY, LogColumn, LoopSpec, Stage, build_c, compare, find_compiler, \
    run_c, run_python, write_c
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.sim.plant_step import initial_plant_state, plant_step_function, plant_step_support
from hbma_ctrl.sim.rig import CAP_RIG, Rig, RigSettings

CC = find_compiler()
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH to build the generated loop")
ROOT = Path(__file__).resolve().parents[1]
TRACK = str(ROOT / "scenarios" / "track_height_cap.toml")


def _commands(k: int, rng) -> np.ndarray:
    """Pump 1 s, vent 1 s, repeated, with a random command every 0.5 s: lift-offs and touch-downs."""
    if k % 50 == 0:
        return rng.random(3)
    return np.array([1.0, 1.0, 0.0]) if (k // 100) % 2 == 0 else np.array([0.0, 0.0, 1.0])


def test_plant_step_equals_the_rig_sample_by_sample():
    scn = load_scenario(TRACK)
    rs = scn.role("rig")
    rig = Rig(scn.actuator, scn.pneumatics, scn.platform, rs)
    fid, plant = rig._plant.fid, rig._plant
    assert fid.name == "platform"
    nsub = int(round(rs.sample_period / plant.dt))
    f = plant_step_function(fid, rs.integrator, plant.dt, nsub)
    theta = plant.thetas[:, 0].copy()
    x, mode, y = initial_plant_state(fid, theta)
    rng = np.random.default_rng(3)
    worst, modes = 0.0, set()
    for k in range(450):
        u = _commands(k, rng)
        rig.apply(u)
        x, m, y = (np.asarray(v).ravel() for v in f(x, mode, u, theta))
        mode = float(m[0])
        modes.add(mode)
        worst = max(worst, float(np.max(np.abs(y - rig._plant.y[:, 0]))), abs(mode - float(rig._plant.mode[0])))
    assert any(name == "lift_off" for _, name in rig.events) and any(name == "touch_down" for _, name in rig.events)
    assert modes == {0.0, 1.0}
    assert worst == 0.0  # the same stages, projection and events in the same order: bitwise equal


@pytest.mark.parametrize("kw, needle", [
    ({"fidelity": "quasi_static"}, "[rig] fidelity = 'quasi_static'"),
    ({"valve_delay": 0.005}, "[rig] valve_delay_ms = 5 ms"),
    ({"sensor_tau": 0.003}, "[rig] sensor_tau_ms = 3 ms"),
    ({"membrane": "exact"}, "[rig] membrane = 'exact'"),
])
def test_plant_step_support_names_the_key_it_cannot_generate(kw, needle):
    rs = RigSettings(**{**CAP_RIG, **kw})  # the cap rig with one key changed: that key, alone
    why = plant_step_support(rs.fidelity, rs)
    assert why.startswith(needle) and "; " not in why
    assert plant_step_support("platform", RigSettings(**CAP_RIG)) is None


def test_plant_step_support_names_every_key_of_the_default_rig_at_once():
    """The default rig differs from the cap in five keys; one message names them all (a user
    should not fix them one run at a time)."""
    why = plant_step_support("platform", RigSettings())
    for needle in ("[rig] membrane = 'exact'", "[rig] valve_delay_ms = 5 ms", "[rig] valve_min_on_ms = 2 ms",
                   "[rig] sensor_tau_ms = 3 ms", "[rig] compressor_tilt = 0.2"):
        assert needle in why
    assert why.count("; ") == 4


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


def test_mpc_glue_matches_the_nmpc_problem():
    from controllers.mpc import NMPC
    from hbma_ctrl.app.codegen_scene import mpc_glue
    from hbma_ctrl.core.interfaces import Estimate, Reference
    from hbma_ctrl.runtime.chamber import chamber_supervisor

    scn = load_scenario(TRACK)
    s = scn.role("controller").mpc
    nmpc = NMPC(scn.actuator, scn.pneumatics, s)
    prep, _, _ = mpc_glue(nmpc.model, s, chamber_supervisor(s).settings)
    rng = np.random.default_rng(1)
    for _ in range(40):
        h = float(rng.choice([0.0, rng.uniform(0.0, 0.015)]))
        p, F, r = rng.uniform(0, 40e3), rng.uniform(0, 8), rng.uniform(0, 0.012)
        nmpc._W = None
        pr = nmpc._problem(0.0, Estimate(t=0.0, h1=h, h2=0.0, h=h, p=p, F=F), Reference(r))
        nmpc._int_target = None  # each draw a new step for both (the glue's has_I = 0)
        pr = nmpc._problem(0.0, Estimate(t=0.0, h1=h, h2=0.0, h=h, p=p, F=F), Reference(r))
        out = [np.asarray(v).ravel() for v in prep(h, p, F, 0.0, np.full(s.horizon, r), 0.0, 0.0, 0.0, 0.0, 0.5,
                                                   0.0, 0.0, 0.0, s.sample_period)]
        got = np.array([out[0][0], out[1][0], out[2][0], out[3][0]])
        want = np.array([pr.x0, pr.W, pr.dh, pr.dp])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out[5], pr.r, rtol=0, atol=1e-12)


def test_mpc_glue_integral_action_matches_the_nmpc_over_a_held_target():
    """The integral action carried through the glue's state (I, its target, has_I) equals the
    NMPC's over 60 controller periods at one target with the estimate wandering around it, then a
    target step that restarts it."""
    from controllers.mpc import NMPC
    from hbma_ctrl.app.codegen_scene import mpc_glue
    from hbma_ctrl.core.interfaces import Estimate, Reference
    from hbma_ctrl.runtime.chamber import chamber_supervisor

    scn = load_scenario(TRACK)
    s = scn.role("controller").mpc
    nmpc = NMPC(scn.actuator, scn.pneumatics, s)
    prep, _, _ = mpc_glue(nmpc.model, s, chamber_supervisor(s).settings)
    rng = np.random.default_rng(2)
    I, I_t, has_I = 0.0, 0.0, 0.0
    shifts = []
    for k in range(80):
        t = k * s.sample_period
        r = 5e-3 if k < 60 else 7e-3
        h = r - 0.6e-3 + rng.normal(0.0, 0.2e-3)
        pr = nmpc._problem(t, Estimate(t=t, h1=h, h2=0.0, h=h, p=20e3, F=3.9), Reference(r))
        out = [np.asarray(v).ravel() for v in prep(h, 20e3, 3.9, 0.0, np.full(s.horizon, r), 0.0, 0.0, 0.0, 0.0,
                                                   0.5, I, I_t, has_I, s.sample_period)]
        np.testing.assert_allclose(out[5], pr.r, rtol=0, atol=1e-12)
        I, I_t, has_I = float(out[10][0]), float(out[11][0]), float(out[12][0])
        assert I == pytest.approx(nmpc.last["integral_shift"], abs=1e-15)
        shifts.append(I)
    assert 0.5e-3 < shifts[59] <= 1e-3  # the standing 0.6 mm error was integrated (capped at 1 mm)
    assert shifts[60] == 0.0  # the step restarted it


@needs_cc
def test_generated_track_height_loop_equals_the_python_path_and_follows_the_scene(tmp_path):
    from dataclasses import replace

    from hbma_ctrl.app.codegen_scene import scenario_loop
    from hbma_ctrl.app.scene_controller import closed_loop, estimator_from_scenario

    T = 4.0  # the first target step (2 -> 8 mm) is at 3 s
    scn = load_scenario(TRACK)
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
    # wall-clock dependent): the glue Functions reproduce what the Python classes do around the steps
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


def _cli(args):
    return CliRunner().invoke(app, args)


def test_codegen_cli_bad_inputs_are_one_error_line(tmp_path):
    one_line_error(_cli(["codegen", str(ROOT / "scenarios" / "robot_bending.toml"), "--out", str(tmp_path / "a")]), "[robot]")
    one_line_error(_cli(["codegen", TRACK, "--out", str(tmp_path / "b"), "--duration-s", "-1"]),
                   "--duration-s = -1", "(0, 3600] s")
    one_line_error(_cli(["codegen", TRACK, "--out", str(tmp_path / "c"), "--estimator", "ukf"]), "--estimator", "ekf")
    one_line_error(_cli(["codegen", str(ROOT / "scenarios" / "open_loop_fig7.toml"), "--out", str(tmp_path / "d")]), "[controller]")
    bad = tmp_path / "qs.toml"
    bad.write_text(Path(TRACK).read_text().replace("[rig]\n", "[rig]\nfidelity = \"quasi_static\"\n"))
    one_line_error(_cli(["codegen", str(bad), "--out", str(tmp_path / "e")]), "qs.toml", "[rig] fidelity")
    assert not any((tmp_path / d).exists() for d in "abcde")


def test_codegen_cli_writes_the_sources(tmp_path):
    res = _cli(["codegen", TRACK, "--out", str(tmp_path / "gen"), "--duration-s", "0.1", "--estimator", "truth"])
    assert res.exit_code == 0, res.output
    names = {p.name for p in (tmp_path / "gen").iterdir()}
    assert {"hbma_steps.c", "hbma_steps.h", "loop_data.h", "closed_loop.c", "Makefile", "README.txt"} <= names
    readme = (tmp_path / "gen" / "README.txt").read_text()
    assert "cc -O1 -std=c99" in readme and "-losqp" in readme  # the default QP solver's library is linked
    assert "-losqp" in (tmp_path / "gen" / "Makefile").read_text()


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


@pytest.mark.parametrize("table, key, value", [("controller", "valve_min_on_ms", 2.0),
                                               ("estimator", "valve_delay_ms", 5.0)])
def test_codegen_refuses_what_the_generated_loop_does_not_do_naming_the_key(table, key, value, tmp_path):
    """The minimum on-time shaping and the EKF's delays are not in the generated C loop: a scenario
    that sets them is refused with the key named, not generated into a loop that differs."""
    from hbma_ctrl.app.codegen_scene import scenario_loop

    text = Path(TRACK).read_text()
    if f"\n{key} = " in text:
        text = re.sub(rf"\n{key} = [^\n]*", f"\n{key} = {value}", text, count=1)
    elif f"[{table}]\n" in text:
        text = text.replace(f"[{table}]\n", f"[{table}]\n{key} = {value}\n", 1)
    else:
        text += f"\n[{table}]\n{key} = {value}\n"
    path = tmp_path / "s.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=key):
        scenario_loop(load_scenario(path), duration=0.1)
