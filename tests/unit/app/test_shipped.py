"""The shipped scenario files: listed, copied out, found by name."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli_checks import one_line_error
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.shipped import copy_scenario, resolve, shipped

REPO_SCENARIOS = Path(__file__).resolve().parents[3] / "scenarios"


def test_every_scenario_file_of_the_repository_is_shipped_under_its_stem():
    assert {n: p.read_bytes() for n, p in shipped().items()} == {
        p.stem: p.read_bytes() for p in REPO_SCENARIOS.glob("*.toml")}


def test_list_prints_one_line_per_shipped_scenario_starting_with_its_name():
    res = CliRunner().invoke(app, ["scenarios", "list"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert [ln.split()[0] for ln in lines] == list(shipped())


def test_resolve_finds_a_shipped_file_by_name_by_file_name_and_by_repository_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no scenarios/ folder here
    want = shipped()["track_height"]
    assert resolve("track_height") == resolve("track_height.toml") == resolve("scenarios/track_height.toml") == want


def test_resolve_keeps_an_existing_path_and_an_unknown_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    own = tmp_path / "track_height.toml"
    own.write_text("[scenario]\nname = 'mine'\n")
    assert resolve("track_height.toml") == Path("track_height.toml")
    assert resolve("elsewhere/nothing.toml") == Path("elsewhere/nothing.toml")


def test_copy_writes_the_shipped_file_into_a_folder_and_refuses_to_overwrite_it(tmp_path):
    out = copy_scenario("mpc_load_step", tmp_path)
    assert out == tmp_path / "mpc_load_step.toml" and out.read_bytes() == shipped()["mpc_load_step"].read_bytes()
    with pytest.raises(ValueError, match="already exists"):
        copy_scenario("mpc_load_step", tmp_path)
    out.write_text("edited")
    assert copy_scenario("mpc_load_step", tmp_path, overwrite=True).read_bytes() == shipped()["mpc_load_step"].read_bytes()


def test_copy_of_an_unknown_name_is_one_error_line_naming_the_closest_shipped_name(tmp_path):
    res = CliRunner().invoke(app, ["scenarios", "copy", "trak_height", "--to", str(tmp_path)])
    one_line_error(res, "trak_height", "did you mean 'track_height'")
    assert not list(tmp_path.iterdir())


def test_the_daemon_and_tune_read_a_shipped_scenario_by_name(tmp_path, monkeypatch):
    from hbma_ctrl.app.daemon.config import load_config

    monkeypatch.chdir(tmp_path)
    assert load_config("daemon_chamber", {"--rig": "sim"}).scenario.name == "daemon_chamber"
    # tune reads the shipped file past the scenario's checks: its [estimator] table is what is missing
    res = CliRunner().invoke(app, ["tune", "track_height", "--role", "estimator", "--out", str(tmp_path / "t")])
    one_line_error(res, "track_height.toml: no [estimator] table to tune")
