"""Scenario loader: valid files, closest-name suggestions, ranges in edge units, role dispatch."""

from __future__ import annotations

from pathlib import Path

import pytest

from checkout import ROOT
from hbma_ctrl.app.scenario import load_scenario


BASE = """
[scenario]
name = "t"
duration_s = 2.0

[actuator]
r1_mm = 7.5
t0_mm = 3.0

[inputs]
schedule = [[0.0, 50.0, 1.0, 0.0], [1.0, 0.0, 0.0, 1.0]]
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


def test_open_loop_fig7_file_loads_in_si():
    scn = load_scenario(ROOT / "scenarios" / "open_loop_fig7.toml")
    assert scn.kind == "single"
    assert scn.actuator.r1 == pytest.approx(12.5e-3)
    assert scn.actuator.t0 == pytest.approx(3e-3)
    assert scn.actuator.V0 == pytest.approx(3e-6)
    assert scn.actuator.material.E == pytest.approx(130.6e3)
    assert scn.platform.mass == 0.0
    assert scn.schedule.rows == ((0.0, 1.0, 1.0, 0.0), (3.0, 0.0, 0.0, 1.0))
    assert scn.sim.sensor_range == pytest.approx(35e3)
    (trial,) = scn.trials()
    assert trial.duration == 6.0 and trial.default_fidelity() == "free"


def test_loaded_file_converts_grams_and_keeps_fidelity():
    scn = load_scenario(ROOT / "scenarios" / "open_loop_loaded.toml")
    assert scn.fidelity == "platform"
    assert scn.platform.load == pytest.approx(0.4)
    assert scn.platform.own_mass == pytest.approx(0.02)


def test_sim_units_converted(tmp_path):
    scn = load_scenario(_write(tmp_path, BASE + "[sim]\ndt_ms = 2.0\nlog_dt_ms = 20\nintegrator = 'euler'\n"))
    assert scn.sim.dt == pytest.approx(2e-3)
    assert scn.sim.log_dt == pytest.approx(0.02)
    assert scn.sim.integrator == "euler"


def test_unknown_key_names_field_and_suggests_closest(tmp_path):
    with pytest.raises(ValueError, match=r"\[actuator\] r1_mmm.*did you mean r1_mm"):
        load_scenario(_write(tmp_path, BASE.replace("r1_mm = 7.5", "r1_mmm = 7.5")))


def test_misspelt_required_key_is_named_as_written(tmp_path):
    """A required key misspelt: the error names what the user wrote and suggests the key, instead of
    saying the key they did not write is required."""
    text = (ROOT / "scenarios" / "mpc_ramp_sine.toml").read_text().replace("targets_mm =", "ttargets_mm =")
    with pytest.raises(ValueError, match=r"\[controller\] ttargets_mm: unknown key; did you mean targets_mm"):
        load_scenario(_write(tmp_path, text))


def test_unknown_table_suggests_closest_role(tmp_path):
    with pytest.raises(ValueError, match=r"\[estimater\].*did you mean \[estimator\]"):
        load_scenario(_write(tmp_path, BASE + "[estimater]\nkind = 'ekf'\n"))


def test_bad_choice_suggests(tmp_path):
    with pytest.raises(ValueError, match=r"\[sim\] fidelity = 'quasistatic'.*'quasi_static'"):
        load_scenario(_write(tmp_path, BASE + "[sim]\nfidelity = 'quasistatic'\n"))


@pytest.mark.parametrize(
    "old,new,pattern",
    [
        ("r1_mm = 7.5", "r1_mm = 0.0", r"\[actuator\] r1_mm = 0\.0 is out of range \(0\.5, 100\] mm"),
        ("t0_mm = 3.0", "t0_mm = 50.0", r"\[actuator\] t0_mm = 50\.0 is out of range \(0\.05, 20\] mm"),
        ("duration_s = 2.0", "duration_s = -1.0", r"\[scenario\] duration_s = -1\.0 is out of range \(0, 3600\] s"),
        ("[1.0, 0.0, 0.0, 1.0]", "[1.0, 150.0, 0.0, 1.0]",
         r"\[inputs\] schedule\[1\]\.speed_pct = 150\.0 is out of range \[0, 100\] %"),
    ],
)
def test_out_of_range_names_field_and_range(tmp_path, old, new, pattern):
    assert old in BASE
    with pytest.raises(ValueError, match=pattern):
        load_scenario(_write(tmp_path, BASE.replace(old, new)))


def test_load_range_and_type(tmp_path):
    with pytest.raises(ValueError, match=r"\[load\] mass_g = -5\.0 is out of range \[0, 50000\] g"):
        load_scenario(_write(tmp_path, BASE + "[load]\nmass_g = -5.0\n"))
    with pytest.raises(ValueError, match=r"\[load\] mass_g = 'heavy' must be a number"):
        load_scenario(_write(tmp_path, BASE + "[load]\nmass_g = 'heavy'\n"))


def test_free_fidelity_with_a_load_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"\[sim\] fidelity = 'free' ignores the load"):
        load_scenario(_write(tmp_path, BASE + "[load]\nmass_g = 200.0\n[sim]\nfidelity = 'free'\n"))


def test_unknown_material_parameter(tmp_path):
    text = BASE + "[actuator.material_params]\nEE = 1e5\n"
    with pytest.raises(ValueError, match=r"\[actuator\.material_params\] EE.*did you mean E"):
        load_scenario(_write(tmp_path, text))


def test_protocol_kind_builds_grid(tmp_path):
    text = """
[scenario]
kind = "protocol"
duration_s = 2.0
[protocol]
loads_g = [0.0, 200.0]
speeds_pct = [50.0, 100.0]
t0_mm = [3.0]
r1_mm = [7.5]
t_inflate_s = 1.0
"""
    trials = load_scenario(_write(tmp_path, text)).trials()
    assert [t.name for t in trials] == ["t3_r7.5_m0_s50", "t3_r7.5_m0_s100", "t3_r7.5_m200_s50", "t3_r7.5_m200_s100"]
    assert all(t.duration == 2.0 and t.schedule.rows[1][0] == 1.0 for t in trials)
    with pytest.raises(ValueError, match=r"\[inputs\] is only allowed"):
        load_scenario(_write(tmp_path, text + "[inputs]\nschedule = [[0.0, 1.0, 1.0, 0.0]]\n"))


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_scenario(_write(tmp_path, "[scenario\nname = 1"))


@pytest.mark.parametrize("path", sorted((ROOT / "scenarios").glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_scenario_loads(path):
    """Every scenario file the README points to parses and validates (names, ranges, roles)."""
    scn = load_scenario(path)
    assert scn.name and scn.kind
