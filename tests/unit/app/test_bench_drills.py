"""``hbma-ctrl bench drills``: fault drills through the daemon's own loop, and its bad input."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.bench.drills import DEFAULT_VALUE, check_drills, drill_fault
from hbma_ctrl.app.cli.main import app
from checkout import ROOT

ROBOT = ROOT / "scenarios" / "daemon_robot.toml"
cli = CliRunner()


@pytest.mark.slow
def test_two_burst_drills_on_the_robot_are_found_by_the_burst_test_named_and_timed(tmp_path):
    """Two outlets stuck fully open (the default leak drill) at seeded times and chambers in [2, 6] s:
    each found as a burst of the drilled chamber within 0.15 s, no false alarm, drills.json complete."""
    out = tmp_path / "drills"
    r = cli.invoke(app, ["bench", "drills", str(ROBOT), "--drills", "2", "--seed", "3", "--from-s", "2",
                         "--to-s", "6", "--after-s", "0.3", "--out", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads((out / "drills.json").read_text())
    assert res["kind"] == "leak" and res["value"] == DEFAULT_VALUE["leak"] == 1.0
    assert res["drills"] == res["judged"] == 2 and res["false_alarms"] == 0
    assert res["found"] == 2 and res["found_by_kind"] == {"burst": 2}, res["per_drill"]
    for row in res["per_drill"]:
        assert 2.0 <= row["start_s"] <= 6.0
        assert 0.0 <= row["delay_s"] <= 0.15
        assert row["cause"].startswith(f"{row['chamber']}: its readings fell")
        assert row["p_at_find_kpa"] < row["p_at_start_kpa"]
        assert row["monitor_margins"]["burst_sigma"] >= 50.0
    assert "found 2 of 2 (burst 2)" in r.output


@pytest.mark.parametrize("args, text", [
    (["--kind", "nope"], "--kind = 'nope': allowed dropout, frozen, offset"),
    (["--value", "2"], "--value (duty) = 2.0 is out of range [0, 1]"),
    (["--kind", "offset", "--value", "500"], "--value (offset_kpa) = 500.0 is out of range [-100, 100] kPa"),
    (["--kind", "offset"], "--value: kind 'offset' needs a value (offset_kpa)"),
    (["--kind", "dropout", "--value", "3"], "--value = 3: kind 'dropout' takes no value"),
    (["--from-s", "5", "--to-s", "1"], "--from-s = 5 and --to-s = 1: 0 <= from <= to is required (s)"),
    (["--drills", "0"], "--drills = 0 is out of range [1, 10000]"),
    (["--setpoint-every-s", "-1"], "--setpoint-every-s = -1 must be >= 0 s"),
    (["--after-s", "0"], "--after-s = 0 must be > 0"),
])
def test_bad_flags_are_one_error_naming_the_flag_exit_2_and_no_output_dir(args, text, tmp_path):
    out = tmp_path / "drills"
    r = cli.invoke(app, ["bench", "drills", str(ROBOT), *args, "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert text in r.output and "Traceback" not in r.output
    assert not any(tmp_path.iterdir())  # nothing written, not even a failed run's directory


def test_drill_fault_takes_the_kinds_default_value_and_checks_it_as_a_fault_table():
    assert drill_fault("leak", None, 3, 2.0, 9).value == 1.0
    assert drill_fault("stuck_inlet", None, 0, 0.0, 1).value == 0.0
    f = drill_fault("offset", -5.0, 2, 1.5, 9)
    assert (f.kind, f.chamber, f.start, f.value) == ("offset", 2, 1.5, pytest.approx(-5e3))
    with pytest.raises(ValueError, match=r"\[daemon.fault\[0\]\] chamber = 9 is out of range"):
        drill_fault("leak", None, 9, 0.0, 9)
    check_drills("leak", None, 0.0, 0.0)
