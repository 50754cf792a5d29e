"""The robot's generated closed loop (hbma_ctrl.app.codegen.robot): the C program against its Python
path (the same stages called from Python on the same library) and against the scene's own loop."""

from __future__ import annotations


import numpy as np
import pytest

from hbma_ctrl.core.loopgen_c import bench, find_compiler, read_c
from checkout import ROOT
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.runtime.safety import ZERO_TARGET

pytestmark = pytest.mark.slow

needs_cc = pytest.mark.skipif(find_compiler() is None, reason="no C compiler (cc, gcc or clang) on PATH")


@pytest.mark.compiling
@needs_cc
def test_the_robot_loop_in_c_equals_its_python_path_and_the_scenes_loop(tmp_path):
    """robot_bending (3 layers, one pump per chamber, the structured rig with valve timing, pump tilt and
    sensor lag) for 1.5 s: the C trajectory equals the Python path's exactly; the scene's own loop
    (RobotNMPCFunction, its numpy bank, loads, supervisor and valve classes) follows it within 1e-9 in
    heights (m), estimates and commands, 1e-6 Pa in pressures; the chambers rise and every step solves;
    the C run's robot metrics are the scene's metrics of its own trajectory."""
    from hbma_ctrl.app.codegen.robot import loop_run_metrics, robot_loop, scene_reference

    scn = load_scenario(ROOT / "scenarios" / "robot_bending.toml")
    spec = robot_loop(scn, 1.5)
    assert spec.n_ticks == 150 and "robot_rti_step" in [f.name() for f in spec.functions()]
    res = bench(spec, tmp_path)
    assert res["max_abs_diff_si_all"] == 0.0
    traj = read_c(tmp_path).trajectory
    col = {c: i for i, c in enumerate(spec.header())}
    h = traj[:, [col[f"h_{nm}_mm"] for nm in ("A1", "A2", "A3")]]
    assert h[-1].min() > 2.0  # mm: every chamber of layer A on its way to the 6 mm target
    assert np.all(traj[:, col["rti_status"]] == 0) and np.all(traj[:, col["failed"]] == 0)
    sc = scene_reference(scn, spec, traj)
    d = sc["max_abs_diff_si"]
    assert max(d["h"], d["h_est"], d["a"], d["o"]) < 1e-9, d
    assert max(d["p"], d["p_meas"]) < 1e-6, d
    assert sc["fallbacks"] == 0
    assert sc["c_chamber_height_rmse_mm"] == pytest.approx(sc["chamber_height_rmse_mm"], abs=1e-9)
    m = loop_run_metrics(scn, spec, traj)["robot"]
    assert m["controller"] == "mpc" and m["step_ms_median"] is None and m["n_layers"] == 3
    assert m["max_pressure_kpa"] == pytest.approx(float(traj[:, [col[f"p_{nm}_kpa"] for nm in scn.role("robot").design.names]].max()))


@pytest.mark.compiling
@needs_cc
def test_the_shared_pump_robot_loop_in_c_equals_its_python_path(tmp_path):
    """robot_sequential_closed (2 layers, one shared pump, layer B's zero target vented) for 0.3 s: the C
    trajectory equals the Python path's exactly, the vent rule holds layer B's outlets open, the pump's
    one speed is the same in every column, and the scene's loop follows it to rounding until the shared
    pump's speed search (16 bisections) turns a rounding difference into one of its steps (at 0.34 s)."""
    from hbma_ctrl.app.codegen.robot import robot_loop, scene_reference

    scn = load_scenario(ROOT / "scenarios" / "robot_sequential_closed.toml")
    spec = robot_loop(scn, 0.3)
    res = bench(spec, tmp_path)
    assert res["max_abs_diff_si_all"] == 0.0
    traj = read_c(tmp_path).trajectory
    col = {c: i for i, c in enumerate(spec.header())}
    names = scn.role("robot").design.names
    speeds = traj[:, [col[f"speed_{nm}"] for nm in names]]
    assert np.all(speeds == speeds[:, :1])
    assert np.all(traj[:, [col[f"outlet_{nm}"] for nm in names[3:]]] == 1.0)  # layer B vented
    zero = traj[:, [col[f"h_ref_{nm}_mm"] for nm in names]] <= ZERO_TARGET * 1e3
    assert zero[:, 3:].all() and np.array_equal(traj[:, col["ev_vent"]], zero.sum(axis=1))  # the vent rule's count
    sc = scene_reference(scn, spec, traj)
    assert sc["max_abs_diff_si"]["h"] < 1e-9, sc["max_abs_diff_si"]


def test_codegen_cli_writes_a_robot_loop_and_says_what_it_leaves_out(tmp_path):
    """``hbma-ctrl codegen`` on a robot scenario (no build): the sources, and a README.txt listing the
    robot's stages in the tick's order; the pressure-PID baseline the scenario compares is named as
    left out."""
    from typer.testing import CliRunner

    from hbma_ctrl.app.cli.main import app

    res = CliRunner().invoke(app, ["codegen", str(ROOT / "scenarios" / "robot_bending.toml"), "--out",
                                   str(tmp_path / "gen"), "--duration-s", "0.05"])
    assert res.exit_code == 0, res.output
    assert "left out" in res.output and "pressure-PID baseline" in res.output
    readme = (tmp_path / "gen" / "README.txt").read_text()
    order = [readme.index(f"  {name} ") for name in ("robot_sensor", "robot_ekf", "robot_pre", "robot_rti_step",
                                                     "robot_post", "robot_rig_step")]
    assert order == sorted(order) and "5 ticks of 10 ms" in readme and "-losqp" in readme
    data = (tmp_path / "gen" / "loop_data.h").read_text()
    assert "#define N_TICKS 5L" in data and "stream_goal" in data and "stream_f_tip" in data


@needs_cc
def test_the_daemons_robot_loop_with_slewed_targets_follows_the_scene(tmp_path):
    """daemon_robot.toml's loop (targets slewed at 3 mm/s, the daemon's NMPC weights) with its wall-time
    budget set to 0, on the Python path (casadi's virtual machine, no C build): the scene's loop follows
    it within 1e-9 m for 0.5 s, and the slewed targets move at most 3 mm/s x 10 ms per tick."""
    from hbma_ctrl.core.loopgen import run_python
    from hbma_ctrl.app.codegen.robot import robot_loop, scene_reference

    src = (ROOT / "scenarios" / "daemon_robot.toml").read_text()
    assert "mpc_budget = 0.8" in src and "target_rate_mm_s = 3.0" in src
    path = tmp_path / "daemon_robot.toml"
    path.write_text(src.replace("mpc_budget = 0.8", "mpc_budget = 0.0"))
    scn = load_scenario(path)
    spec = robot_loop(scn, 0.5)
    py = run_python(spec)
    col = {c: i for i, c in enumerate(spec.header())}
    href = py.trajectory[:, [col[f"h_ref_{nm}_mm"] for nm in scn.role("robot").design.names]]
    assert np.abs(np.diff(href, axis=0)).max() <= 3.0 * 0.01 + 1e-12  # mm per tick
    assert href[-1].max() < 6.0  # still on its way to the 6 mm start pose: the slew is in force
    sc = scene_reference(scn, spec, py.trajectory)
    assert max(sc["max_abs_diff_si"][k] for k in ("h", "h_est", "a", "o")) < 1e-9, sc["max_abs_diff_si"]
