"""Keys renamed so that the chamber's and the robot's tables name one thing once: the old name is still
read with a one-line notice on stderr naming the old key, the new one and the file; the new name is
read silently; both at once are one clear error; the shipped scenarios use the new names."""

from __future__ import annotations

import tomllib

import pytest

from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.app.schema.reference import table_markdown
from hbma_ctrl.app.schema.robot import RobotTable
from checkout import SCENARIOS

ROBOT = """[scenario]
name = "r"
duration_s = 4.0
[robot]
layers = 1
{keys}
"""


def _file(tmp_path, name: str, keys: str):
    path = tmp_path / name
    path.write_text(ROBOT.format(keys=keys))
    return path


@pytest.mark.parametrize("old, new, value, field", [("mpc_horizon", "horizon", "10", "mpc_horizon"),
                                                     ("mpc_enforce_budget", "enforce_budget", "true",
                                                      "mpc_enforce_budget")])
def test_old_name_still_loads_with_a_one_line_notice(tmp_path, capsys, old, new, value, field):
    path = _file(tmp_path, f"{old}.toml", f"{old} = {value}")
    settings = load_scenario(path).settings["robot"]
    assert getattr(settings, field) == tomllib.loads(f"v = {value}")["v"]
    err = capsys.readouterr().err.splitlines()
    assert err == [f"{path}: [robot] {old} is deprecated: write {new}"]


def test_new_name_loads_silently(tmp_path, capsys):
    path = _file(tmp_path, "new.toml", "horizon = 10\nenforce_budget = true")
    settings = load_scenario(path).settings["robot"]
    assert settings.mpc_horizon == 10 and settings.mpc_enforce_budget
    assert capsys.readouterr().err == ""


def test_both_names_at_once_are_one_error(tmp_path):
    path = _file(tmp_path, "both.toml", "mpc_horizon = 10\nhorizon = 12")
    with pytest.raises(ValueError) as exc:
        load_scenario(path)
    assert str(exc.value) == ("both.toml: [robot] mpc_horizon and horizon are one key (mpc_horizon is its old "
                              "name): keep horizon only")


def test_keys_page_names_the_old_names():
    section = table_markdown("robot")
    for old, new in RobotTable.renamed.items():
        row = next(r for r in section.splitlines() if r.startswith(f"| {new} |"))
        assert f"(old name {old}, still read)" in row


def test_shipped_scenarios_use_the_new_names():
    for path in sorted(SCENARIOS.glob("*.toml")):
        robot = tomllib.loads(path.read_text()).get("robot", {})
        assert not RobotTable.renamed.keys() & robot.keys(), path.name
