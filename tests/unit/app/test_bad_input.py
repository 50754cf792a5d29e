"""Bad input, each reported defect: one line 'error: ...' naming the key or flag as written, exit code 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

import hbma_ctrl.app.cli.sim as cli_mod
from hbma_ctrl.app.cli import args as cli_args
from hbma_ctrl.app.cli.main import app
from checkout import ROOT
from hbma_ctrl.app.scenario import load_scenario

runner = CliRunner()


def _one_line_error(res, *needles: str, code: int = 2) -> str:
    assert res.exit_code == code, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "Traceback" not in res.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def _run_file(tmp_path: Path, body: str | bytes, name: str = "s.toml"):
    p = tmp_path / name
    if isinstance(body, bytes):
        p.write_bytes(body)
    else:
        p.write_text(body, encoding="utf-8")
    return runner.invoke(app, ["run", str(p), "--out", str(tmp_path / "o")])


# 1. wrong-shaped material parameters -------------------------------------------------------------
@pytest.mark.parametrize(
    "args,needles",
    [
        (["--param", "E=1,2"], ["--param E", "one number"]),
        (["--material", "yeoh", "--param", "C=1e4,1,1,1"], ["--param C", "1 to 3"]),
        (["--material", "ogden", "--param", "mu=1e4"], ["--param mu", "same"]),
        (["--material", "gent", "--param", "Jm=1,2"], ["--param Jm", "one number"]),
    ],
)
def test_equilibrium_wrong_shaped_param(args, needles):
    _one_line_error(runner.invoke(app, ["equilibrium", "--h1-mm", "5", *args]), *needles)


def test_equilibrium_single_yeoh_term_is_a_list_of_one():
    res = runner.invoke(app, ["equilibrium", "--h1-mm", "5", "--material", "yeoh", "--param", "C=2e4", "--json"])
    assert res.exit_code == 0, res.output
    assert '"C": [20000.0]' in res.stdout


@pytest.mark.parametrize(
    "params,needles",
    [
        ("E = [1.0, 2.0]", ["[actuator.material_params]", "E must be one number"]),
        ("C = 2e4", ["[actuator.material_params]", "C ="]),
    ],
)
def test_scenario_wrong_shaped_param(tmp_path, params, needles):
    material = "nh" if params.startswith("E") else "yeoh"
    body = f"[actuator]\nmaterial = '{material}'\n[actuator.material_params]\n{params}\n"
    if params.startswith("C"):  # a bare number for a Yeoh C is one term: accepted, so test a string instead
        body = body.replace("C = 2e4", "C = ['a']")
    _one_line_error(_run_file(tmp_path, body), *needles)


# 8. a strain energy with negative pressure ------------------------------------------------------
def test_equilibrium_negative_pressure_material_refused():
    res = runner.invoke(app, ["equilibrium", "--h1-mm", "5", "--material", "yeoh", "--param", "C=2e4,-1e6,10"])
    _one_line_error(res, "--param C", "C = [20000, -1e+06, 10]", ">= 0", "[1, 4]")


def test_scenario_negative_pressure_material_refused(tmp_path):
    body = "[actuator]\nmaterial = 'yeoh'\n[actuator.material_params]\nC = [2e4, -1e6, 10]\n"
    _one_line_error(_run_file(tmp_path, body), "s.toml", "[actuator.material_params]", "C = [20000, -1e+06, 10]")


# 2. encodings and binary content --------------------------------------------------------------
@pytest.mark.parametrize(
    "body,needles",
    [
        ("[scenario]\nname = 'caf\u00e9'\n".encode("latin-1"), ["not UTF-8", "0xe9", "line 2"]),
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", ["binary content"]),
        ("\ufeff\ufeff[scenario]\n".encode("utf-8"), ["not valid TOML"]),
    ],
)
def test_scenario_bad_bytes_name_the_file(tmp_path, body, needles):
    _one_line_error(_run_file(tmp_path, body, "bytes.toml"), "bytes.toml", *needles)


def test_scenario_with_utf8_bom_is_accepted(tmp_path):
    # a BOM is what Windows editors write in front of UTF-8: dropped, the rest parsed as usual
    text = (ROOT / "scenarios" / "open_loop_fig7.toml").read_text(encoding="utf-8")
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    got, ref = load_scenario(p), load_scenario(ROOT / "scenarios" / "open_loop_fig7.toml")
    assert (got.name, got.kind, got.actuator, got.duration, got.sim) == (ref.name, ref.kind, ref.actuator,
                                                                           ref.duration, ref.sim)


# 3. empty scenario file -----------------------------------------------------------------------
@pytest.mark.parametrize("body", ["", "\n\n", "# only a comment\n"])
def test_empty_scenario_file_refused(tmp_path, body):
    _one_line_error(_run_file(tmp_path, body, "empty.toml"), "empty.toml", "empty")


# 5. a pressure limit above the sensor range ---------------------------------------------------
_CTRL = "[controller]\ntargets_mm = [[0.0, 5.0]]\n"


@pytest.mark.parametrize(
    "body,needles",
    [
        (f"{_CTRL}p_max_kpa = 40.0\n", ["[controller] p_max_kpa = 40.0", "(0, 35] kPa",
                                         "[sim] sensor_range_kpa"]),
        (f"[rig]\n{_CTRL}p_max_kpa = 36.0\n", ["[controller] p_max_kpa = 36.0", "[rig] sensor_range_kpa = 35"]),
        (f"[rig]\nsensor_range_kpa = 20.0\n{_CTRL}", ["p_max_kpa = 35.0", "(0, 20] kPa",
                                                     "[rig] sensor_range_kpa = 20"]),
        (f"[sim]\nsensor_range_kpa = 30.0\n{_CTRL}p_max_kpa = 31.0\n", ["(0, 30] kPa", "[sim] sensor_range_kpa = 30"]),
    ],
)
def test_controller_limit_above_sensor_range_refused(tmp_path, body, needles):
    _one_line_error(_run_file(tmp_path, body), *needles)


# 10. a run whose every trial diverges ---------------------------------------------------------
def test_run_with_every_trial_diverged_exits_1_and_keeps_failed_outputs(tmp_path):
    text = (ROOT / "scenarios" / "open_loop_fig7.toml").read_text(encoding="utf-8")
    # so stiff that the fixed step blows the pressure up to ~1e289 kPa: it used to report status "ok"
    p = tmp_path / "stiff.toml"
    p.write_text(text.replace("E = 130.6e3", "E = 1e300"), encoding="utf-8")
    res = runner.invoke(app, ["run", str(p), "--out", str(tmp_path / "o")])
    line = _one_line_error(res, "the trial diverged", "partial results in", code=1)
    assert not (tmp_path / "o").exists()
    (failed,) = tmp_path.glob("o.failed-*")
    manifest = json.loads((failed / "manifest.json").read_text())
    assert manifest["status"] == "failed" and "diverged" in manifest["error"]
    assert json.loads((failed / "metrics.json").read_text())["plant"]["status"] == "diverged"
    assert str(failed) in line


# 9. whole-number options and the worker count -------------------------------------------------
@pytest.mark.parametrize(
    "args,needles",
    [
        (["robot", "workspace", "--layers", "1.5"], ["--layers"]),
        (["bench", "robot", "--layers", "1,2.5"], ["--layers", "'2.5' is not a whole number in [1, 6]"]),
        (["bench", "robot", "--layers", "7"], ["--layers", "[1, 6]"]),
    ],
)
def test_int_option_given_a_float_is_refused_not_truncated(tmp_path, args, needles):
    _one_line_error(runner.invoke(app, [*args, "--out", str(tmp_path / "o")]), *needles)
    assert not (tmp_path / "o").exists()


def test_workers_above_core_count_capped_with_a_note(monkeypatch, tmp_path):
    calls = []

    def fake_run_protocol(material, out, integrator, dt, fidelity, workers, **kw):
        calls.append(workers)
        return [{"status": "ok", "max_height_mm": 1.0, "max_pressure_kpa": 2.0}]

    monkeypatch.setattr(cli_mod, "run_protocol", fake_run_protocol)
    monkeypatch.setattr(cli_args.os, "cpu_count", lambda: 2)
    res = runner.invoke(app, ["protocol", "--workers", "200", "--no-plots", "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert calls == [2]
    notes = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert notes == ["note: --workers = 200 is above this machine's 2 cores; using 2"]


# 4. a string where a number belongs in [robot.inputs] ------------------------------------------
@pytest.mark.parametrize(
    "row,needles",
    [
        ('[[0.0, "100", 1.0, 0.0]]', ["[robot.inputs] A1[0].speed_pct = '100' must be a number in [0, 100] %"]),
        ('[[0.0, 100.0, "open", 0.0]]', ["[robot.inputs] A1[0].inlet_duty = 'open' must be a number in [0, 1]"]),
        ('[["0", 100.0, 1.0, 0.0]]', ["[robot.inputs] A1[0].t_s = '0' must be a number in [0, 1e+06] s"]),
    ],
)
def test_robot_inputs_string_for_number(tmp_path, row, needles):
    body = "[robot]\nmode = 'open_loop'\nlayers = 1\n[robot.inputs]\nA1 = " + row + "\n"
    _one_line_error(_run_file(tmp_path, body, "robot.toml"), "robot.toml", *needles)


# 6. a key the scene ignores -------------------------------------------------------------------
@pytest.mark.parametrize(
    "body,used",
    [
        (f"[rig]\n{_CTRL}", "[rig] sensor_range_kpa"),
        ("[estimator]\n", "[rig] sensor_range_kpa"),
        ("[robot]\nlayers = 1\n[robot.inputs]\nA1 = [[0.0, 100.0, 1.0, 0.0]]\n", "[robot] sensor_range_kpa"),
    ],
)
def test_sim_sensor_range_ignored_by_the_scene_is_refused(tmp_path, body, used):
    res = _run_file(tmp_path, "[sim]\nsensor_range_kpa = 30.0\n" + body)
    _one_line_error(res, "[sim] sensor_range_kpa is not used", used)


def test_sim_sensor_range_used_by_a_closed_loop_without_rig_is_accepted(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(f"[sim]\nsensor_range_kpa = 30.0\n{_CTRL}p_max_kpa = 30.0\n", encoding="utf-8")
    assert load_scenario(p).sim.sensor_range == pytest.approx(30e3)


# 7. a log period longer than the run --------------------------------------------------------
def test_log_dt_longer_than_the_run_refused(tmp_path):
    # a 19 mm inflation used to report a 0 mm peak: the only logged row was t = 0
    text = (ROOT / "scenarios" / "open_loop_fig7.toml").read_text(encoding="utf-8")
    res = _run_file(tmp_path, text.replace("log_dt_ms = 10.0", "log_dt_ms = 10000.0"))
    _one_line_error(res, "[sim] log_dt_ms = 10000.0", "[0.01, 6000] ms", "[scenario] duration_s = 6 s")


def test_log_dt_equal_to_the_run_accepted(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text("[scenario]\nduration_s = 2.0\n[inputs]\nschedule = [[0.0, 100.0, 1.0, 0.0]]\n"
                 "[sim]\nlog_dt_ms = 2000.0\n", encoding="utf-8")
    assert load_scenario(p).sim.log_dt == pytest.approx(2.0)


# 8. a step so small the run would take hours -------------------------------------------------
def test_a_step_that_needs_more_than_the_most_steps_is_refused_with_the_smallest_allowed(tmp_path):
    text = (ROOT / "scenarios" / "open_loop_fig7.toml").read_text(encoding="utf-8")
    res = _run_file(tmp_path, text.replace("[sim]", "[sim]\ndt_ms = 1e-4"))
    _one_line_error(res, "[sim] dt_ms = 0.0001", "[0.0006, 100] ms", "duration_s = 6 s", "60,000,000 steps")
    res = runner.invoke(app, ["protocol", "--dt-ms", "1e-4", "--out", str(tmp_path / "p")])
    _one_line_error(res, "--dt-ms = 0.0001", "[0.0006, 100] ms", "--duration-s")
    assert not (tmp_path / "o").exists() and not (tmp_path / "p").exists()


def test_the_smallest_allowed_step_is_accepted(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text("[scenario]\nduration_s = 2.0\n[inputs]\nschedule = [[0.0, 100.0, 1.0, 0.0]]\n"
                 "[sim]\ndt_ms = 0.0002\n", encoding="utf-8")
    assert load_scenario(p).sim.dt == pytest.approx(2e-7)


def test_robot_target_rate_out_of_range_names_the_key_and_range(tmp_path):
    body = ("[robot]\nmode = 'closed_loop'\nlayers = 1\ntarget_rate_mm_s = -1.0\n"
            "[robot.targets]\nall = [[0.0, 6.0, 0.0, 0.0]]\n")
    _one_line_error(_run_file(tmp_path, body, "robot.toml"), "robot.toml", "[robot] target_rate_mm_s = -1",
                    "[0, 1000] mm/s")


def test_robot_mpc_w_slack_out_of_range_names_the_key_and_range(tmp_path):
    body = ("[robot]\nmode = 'closed_loop'\nlayers = 1\nmpc_w_slack = -1.0\n"
            "[robot.targets]\nall = [[0.0, 6.0, 0.0, 0.0]]\n")
    _one_line_error(_run_file(tmp_path, body, "robot.toml"), "robot.toml", "[robot] mpc_w_slack = -1",
                    "[0, 1e+06] 1/kPa")


@pytest.mark.parametrize("key", ["membrane = 'exact'", "sensor_range_kpa = 40.0", "dropout_prob = 0.1"])
def test_robot_rig_key_the_robot_does_not_have_is_refused_not_ignored(tmp_path, key):
    """The robot's rig is the cap, its sensors' range set by [robot]: a single-chamber [rig] key it has
    no use for is one error naming it and the keys it takes, before any work."""
    body = ("[robot]\nmode = 'closed_loop'\nlayers = 1\n[robot.targets]\nall = [[0.0, 6.0, 0.0, 0.0]]\n"
            f"[rig]\nseed = 1\n{key}\n")
    _one_line_error(_run_file(tmp_path, body, "robot.toml"), "robot.toml", f"[rig] {key.split(' ')[0]}",
                    "a robot's [rig] takes fidelity, modulus_scale")
    assert not (tmp_path / "o").exists()
