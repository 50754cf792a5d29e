"""Record -> fit -> scenario: the daemon's open-loop [schedule], fit reading the daemon's run log by
chamber name, the fitted values put into a scenario, and fit's input checks (units, replay length)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from cli_checks import one_line_error
from typer.testing import CliRunner

from checkout import ROOT
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.daemon.config import load_config
from hbma_ctrl.app.daemon.schedule import Schedule, ScheduleStep, ScheduleSystem
from hbma_ctrl.app.scenario import load_scenario, parse_scenario
from hbma_ctrl.app.tuning import fit_dynamic as D
from hbma_ctrl.app.tuning.fit import FitReport
from hbma_ctrl.app.tuning.fit_output import write_scenario
from hbma_ctrl.app.tuning.run_data import parse_run
from hbma_ctrl.core import units as U

runner = CliRunner()
RECORD = ROOT / "scenarios" / "record_chamber.toml"


def _schedule(*steps, **kw) -> Schedule:
    return Schedule(steps=tuple(ScheduleStep(**s) for s in steps), **kw).validate()


# --- the schedule ------------------------------------------------------------------------------
def test_schedule_writes_each_steps_command_then_vents():
    sys_ = ScheduleSystem(_schedule({"action": "pump", "duration": 0.02, "speed": 0.6},
                                    {"action": "hold", "duration": 0.01},
                                    {"action": "vent", "duration": 0.01, "outlet": 0.5}, repeat=2))
    got = [sys_.tick(0.01 * k, np.zeros(1))[:, 0].tolist() for k in range(10)]
    pump, hold, vent, safe = [0.6, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, 1.0]
    assert got == [pump, pump, hold, vent, pump, pump, hold, vent, safe, safe]
    events = [c for k, c in sys_.take_events() if k == "schedule"]
    assert len(events) == 7 and events[0].startswith("step 1 of 6: pump") and "ended" in events[-1]
    assert sys_.stats()["steps_run"] == 6 and sys_.stats()["schedule_s"] == pytest.approx(0.08)


def test_a_pumped_chamber_holds_at_pump_stop_for_the_rest_of_the_step():
    sys_ = ScheduleSystem(_schedule({"action": "pump", "duration": 0.05}, {"action": "pump", "duration": 0.02},
                                    pump_stop=20e3))
    u = [sys_.tick(0.01 * k, np.array([p]))[:, 0].tolist() for k, p in enumerate((0, 19e3, 20e3, 10e3, 10e3, 10e3))]
    assert u[1] == [1.0, 1.0, 0.0] and u[2] == u[3] == u[4] == [0.0, 0.0, 0.0]
    assert u[5] == [1.0, 1.0, 0.0]  # the next step pumps again
    assert sys_.pump_stops == 1


def test_schedule_refuses_setpoints_and_unknown_chambers():
    sys_ = ScheduleSystem(_schedule({"action": "vent", "duration": 1.0}))
    with pytest.raises(ValueError, match="takes no setpoints"):
        sys_.check_setpoint({"heights": {0: 0.005}})
    with pytest.raises(ValueError, match="'A1': no such chamber; the chambers are C1"):
        ScheduleSystem(_schedule({"action": "vent", "duration": 1.0, "chamber": "A1"}))


@pytest.mark.parametrize("body,needles", [
    ("[[schedule.step]]\naction = 'pumpp'\n", ["[schedule]", "action", "pump"]),
    ("[[schedule.step]]\naction = 'hold'\nspeed_pct = 50.0\n", ["[schedule]", "step[0]", "speed_pct"]),
    ("[[schedule.step]]\naction = 'pump'\nduration_s = 0.0\n", ["[schedule]", "duration_s"]),
    ("[[schedule.step]]\naction = 'pump'\nspeed_pct = 150.0\n", ["[schedule]", "speed_pct", "100"]),
    ("pump_stop_kpa = 40.0\n[[schedule.step]]\naction = 'pump'\n", ["pump_stop_kpa = 40", "p_max_kpa = 35"]),
    ("repeat = 2\n", ["[schedule]", "no steps"]),
    ("[[schedule.step]]\naction = 'vent'\n[controller]\nkind = 'pid'\ntargets_mm = [[0.0, 2.0]]\n",
     ["[schedule]", "drop [controller]"]),
])
def test_bad_schedule_is_one_line_naming_the_key(body, needles):
    with pytest.raises(ValueError) as exc:
        parse_scenario(tomllib.loads("[schedule]\n" + body))
    msg = str(exc.value)
    assert "\n" not in msg
    for n in needles:
        assert n in msg, msg


def test_the_shipped_recording_is_a_daemon_schedule_that_run_refuses(tmp_path):
    cfg = load_config(RECORD, {"--rig": "sim"})
    sched = cfg.scenario.role("schedule")
    assert cfg.kind == "schedule" and cfg.duration == pytest.approx(sched.length) and sched.p_max < 35e3
    assert load_config(RECORD, {"--duration-s": 2.0}).duration == 2.0
    res = runner.invoke(app, ["run", str(RECORD), "--out", str(tmp_path / "o")])
    one_line_error(res, "[schedule]", "hbma-ctrl daemon")
    assert list(tmp_path.iterdir()) == []  # refused before --out


@pytest.mark.subprocess  # the daemon's API runs in a process of its own
def test_the_shipped_recording_runs_on_the_daemon_until_its_schedule_ends(tmp_path):
    # the whole schedule through the daemon's command (sim rig, fast), ending by itself in the safe state
    res = runner.invoke(app, ["daemon", str(RECORD), "--rig", "sim", "--speed", "1000", "--api", "127.0.0.1:0",
                              "--out", str(tmp_path / "rec")])
    assert res.exit_code == 0, res.output
    events = (tmp_path / "rec" / "events.csv").read_text()
    length = load_config(RECORD, {"--rig": "sim"}).scenario.role("schedule").length
    assert events.count(",schedule,") >= 7 and "safe_exit" in events
    rows = (tmp_path / "rec" / "run_0001.csv").read_text().splitlines()
    assert float(rows[-1].split(",")[0]) == pytest.approx(length, abs=0.05)


# --- fit reads the daemon's run log ------------------------------------------------------------
def _daemon_log(names=("C1",), n=40) -> str:
    """A daemon run log (hbma_ctrl.app.daemon.runlog's columns): a pump then a vent, with a period the
    rig's clock did not move in and the stop's row at the last time."""
    from hbma_ctrl.app.daemon.runlog import chamber_columns

    lines = [",".join(chamber_columns(names))]
    for k in range(n):
        t = 0.01 * k
        pump = k < n // 2
        cells = [f"{t:.4f}", "running"]
        for _ in names:
            cells += [f"{0.5 * k if pump else 0.5 * (n - k):.3f}", "", "9.9", "", "", "1" if pump else "0",
                      "1" if pump else "0", "0" if pump else "1"]
        lines.append(",".join(cells + ["1.0", ""]))
        if k in (5, n - 1):  # the same time again: a period with no new sample, the stop
            lines.append(",".join(cells[:1] + ["stopped"] + cells[2:-3] + ["0", "0", "1", "", ""]))
    return "\n".join(lines) + "\n"


def test_daemon_log_read_by_chamber_name_one_row_per_time():
    run = parse_run(_daemon_log(("A1", "A2")).encode(), chamber="A2")
    assert run.columns == {"t": "t_s", "p": "p_A2_kpa", "speed": "speed_A2_1", "inlet": "inlet_A2_1",
                           "outlet": "outlet_A2_1"}
    assert run.t.size == 40 and np.all(np.diff(run.t) > 0)
    assert run.h is None  # the log's height is the filter's estimate: never fitted to
    # the last row of a repeated time is the command that held from it
    assert run.u[5].tolist() == [0.0, 0.0, 1.0] and run.u[-1].tolist() == [0.0, 0.0, 1.0]


@pytest.mark.parametrize("chamber,needles", [
    ("B7", ["--chamber B7", "no such chamber", "the chambers are A1, A2"]),
    (None, ["--chamber", "2 chambers (A1, A2)"]),
])
def test_chamber_absent_is_one_error_listing_the_names(tmp_path, chamber, needles):
    path = tmp_path / "run_0001.csv"
    path.write_text(_daemon_log(("A1", "A2")))
    args = ["fit", str(path), "--out", str(tmp_path / "o")] + (["--chamber", chamber] if chamber else [])
    one_line_error(runner.invoke(app, args), *needles)


def test_a_run_directory_reads_every_part_of_its_log(tmp_path):
    lines = _daemon_log(("A1", "A2")).splitlines()
    (tmp_path / "run_0001.csv").write_text("\n".join(lines[:20]) + "\n")
    (tmp_path / "run_0002.csv").write_text("\n".join(lines[:1] + lines[20:]) + "\n")
    from hbma_ctrl.app.cli.fit import _read_data

    raw, name = _read_data(tmp_path)
    assert parse_run(raw, chamber="A1").t.size == 40 and name == tmp_path / "run_0001.csv"
    one_line_error(runner.invoke(app, ["fit", str(tmp_path), "--chamber", "B7", "--out", str(tmp_path / "o")]),
                   "the chambers are A1, A2")
    one_line_error(runner.invoke(app, ["fit", str(tmp_path / "o2"), "--out", str(tmp_path / "o")]), "not found")


def test_chamber_on_a_plain_run_file_is_refused(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("t_s,p_kpa,speed,inlet,outlet\n0,0,1,1,0\n0.01,1,1,1,0\n")
    one_line_error(runner.invoke(app, ["fit", str(path), "--chamber", "C1", "--out", str(tmp_path / "o")]),
                   "--chamber C1", "no per-chamber columns")


# --- fit's input checks ------------------------------------------------------------------------
@pytest.mark.parametrize("text,needles", [
    # a 10 ms rig logged in ms
    ("t_s,p_kpa,speed,inlet,outlet\n" + "".join(f"{10 * i},{0.5 * i},1,1,0\n" for i in range(20)),
     ["column 't_s'", "10 s apart", "look like milliseconds"]),
    # heights in metres
    ("t_s,p_kpa,speed,inlet,outlet,h_mm\n" + "".join(f"{0.01 * i:.2f},{0.5 * i},1,1,0,{0.0004 * i:.4f}\n"
                                                      for i in range(20)),
     ["column 'h_mm'", "look like metres"]),
    # static points with heights in metres
    ("h_mm,p_kpa\n0.002,5\n0.004,9\n0.006,12\n", ["column 'h_mm'", "look like metres"]),
])
def test_input_units_that_look_wrong_are_named(tmp_path, text, needles):
    path = tmp_path / "d.csv"
    path.write_text(text)
    one_line_error(runner.invoke(app, ["fit", str(path), "--out", str(tmp_path / "o")]), *needles)


def test_replay_cap_names_the_flag(tmp_path):
    path = tmp_path / "long.csv"
    path.write_text("t_s,p_kpa,speed,inlet,outlet\n" + "".join(f"{0.1 * i:.1f},{min(0.05 * i, 20):g},1,1,0\n"
                                                                for i in range(4000)))
    one_line_error(runner.invoke(app, ["fit", str(path), "--out", str(tmp_path / "o")]),
                   "399.9 s long", "--max-replay-s 300", "raise it")
    short = parse_run(b"t_s,p_kpa,speed,inlet,outlet\n0,0,1,1,0\n0.0000001,0,1,1,0\n0.5,1,1,1,0\n")
    with pytest.raises(ValueError, match=r"rows 1e-07 s apart .*--max-replay-s 1 at"):
        D.check_replay(short, 5_000_000, 1e-7, 0.005, 1.0)


# --- the fitted values in a scenario ------------------------------------------------------------
def _result(E: float = 150e3, V0: float = 3.5e-6, flow: float = 0.95, C_out: float = 1.9e-10) -> FitReport:
    params = {"modulus_scale": E / 130.6e3, "V0": V0, "flow_scale": flow, "C_out": C_out, "E": E}
    return FitReport(material="nh", params=params, ci95={k: [v, v] for k, v in params.items()}, nrmsd=0.01,
                     n_points=100, unidentifiable=[], correlation={}, r1=U.mm(12.5), t0=U.mm(3.0))


def test_written_scenario_carries_every_fitted_parameter_and_keeps_the_simulated_rig(tmp_path):
    path = tmp_path / "fitted.toml"
    path.write_text((ROOT / "scenarios" / "daemon_chamber.toml").read_text())
    before = load_scenario(path)
    write_scenario(path, _result(), "exact")
    write_scenario(path, _result(E=152e3), "exact")  # again: each key replaced, never declared twice
    scn = load_scenario(path)
    assert scn.actuator.material.E == 152e3 and scn.actuator.V0 == pytest.approx(3.5e-6)
    assert scn.pneumatics.flow_scale == 0.95 and scn.pneumatics.outlet.C == 1.9e-10
    assert scn.role("controller") is not None and load_config(path).kind == "chamber"
    # the simulated rig stays the rig it was: its truth is the nominal chamber times its factors
    r0, r1 = before.role("rig"), scn.role("rig")
    assert before.actuator.material.E * r0.modulus_scale == pytest.approx(152e3 * r1.modulus_scale)
    assert before.actuator.V0 * r0.V0_scale == pytest.approx(3.5e-6 * r1.V0_scale)
    assert r0.flow_scale == pytest.approx(0.95 * r1.flow_scale)
    assert before.pneumatics.outlet.C * r0.C_out_scale == pytest.approx(1.9e-10 * r1.C_out_scale)


def test_written_scenario_alone_is_the_fitted_tables(tmp_path):
    path = tmp_path / "new.toml"
    notes = write_scenario(path, _result(), "cap")
    data = tomllib.loads(path.read_text())
    assert set(data) == {"actuator", "pneumatics"} and data["pneumatics"]["C_out"] == 1.9e-10
    assert data["actuator"]["r1_mm"] == 12.5 and any("scenarios copy" in n for n in notes)
    assert "spherical cap" in path.read_text().splitlines()[0]
