"""Record -> fit -> scenario -> daemon on the simulated rig, by the commands a user types: the shipped
recording through the daemon, ``fit`` of its run log by chamber name into a copy of the closed-loop
scenario, and the daemon's closed loop on that scenario (its loop in process on a virtual clock, so the
rig's true height can be read)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from checkout import ROOT
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.daemon.build import build_runner, make_monitor, make_rig
from hbma_ctrl.app.daemon.config import load_config
from hbma_ctrl.app.daemon.loop import DaemonLoop
from hbma_ctrl.app.daemon.state import DaemonState
from hbma_ctrl.app.scenario import load_scenario

cli = CliRunner()
RECORD = ROOT / "scenarios" / "record_chamber.toml"
#: the closed loop's file: the shipped chamber daemon with a 5 mm step (2 -> 7 mm at 3 s) and no API
CLOSED = (ROOT / "scenarios" / "daemon_chamber.toml").read_text().replace(
    "targets_mm = [[0.0, 2.0], [3.0, 6.0]]", "targets_mm = [[0.0, 2.0], [3.0, 7.0]]").replace(
    'api = "127.0.0.1:8765"\n', "")


class _VirtualClock:
    now = 0.0

    def clock(self) -> float:
        return self.now

    def sleep(self, dt: float) -> None:
        self.now += dt


def _closed_loop_heights(path, duration_s: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """The daemon's loop on ``path`` (sim rig, virtual clock): the true height after each period (m), the
    loop time of each (s, 0 at the loop's closing after the calibration) and the stats."""
    cfg = load_config(path, {"--duration-s": duration_s})
    runner = build_runner(cfg)
    rig = make_rig(cfg, runner)
    heights, times = [], []
    write = rig.write

    def recorded(u):
        write(u)
        if runner.t_closed is not None:
            heights.append(rig.rig.truth()["h"])
            times.append(rig.t - runner.t_closed)
    rig.write = recorded
    vc = _VirtualClock()
    loop = DaemonLoop(runner, rig, DaemonState(), cfg.period, speed=cfg.speed, duration=cfg.duration,
                      monitor=make_monitor(cfg, runner), clock=vc.clock, sleep=vc.sleep)
    stats = loop.run()
    return np.array(times), np.array(heights), stats


@pytest.mark.slow
def test_record_fit_scenario_daemon_recovers_the_modulus_and_settles_a_5mm_step(tmp_path):
    # 1. the recording, through the daemon's command on the simulated rig
    res = cli.invoke(app, ["daemon", str(RECORD), "--rig", "sim", "--speed", "1000", "--out", str(tmp_path / "rec")])
    assert res.exit_code == 0, res.output
    events = (tmp_path / "rec" / "events.csv").read_text()
    assert events.count(",schedule,") >= 7 and "safe_exit" in events
    # 2. the fit of its run log, by chamber name, into a copy of the closed-loop scenario
    fitted = tmp_path / "fitted.toml"
    fitted.write_text(CLOSED)
    res = cli.invoke(app, ["fit", str(tmp_path / "rec" / "run_0001.csv"), "--chamber", "C1", "--write-scenario",
                           str(fitted), "--out", str(tmp_path / "fit")])
    assert res.exit_code == 0, res.output
    # the rig's true modulus: the recording's nominal material times its [rig] modulus_scale
    rec = load_scenario(RECORD)
    true_E = rec.actuator.material.E * rec.role("rig").modulus_scale
    fit = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert fit["params"]["E"] == pytest.approx(true_E, rel=0.02), fit["params"]
    scn = load_scenario(fitted)
    assert scn.actuator.material.E == pytest.approx(fit["params"]["E"])
    assert scn.pneumatics.outlet.C == pytest.approx(fit["params"]["C_out"])
    # the simulated rig is the one recorded: its truth unchanged by the fitted nominal
    assert scn.actuator.material.E * scn.role("rig").modulus_scale == pytest.approx(true_E, rel=1e-9)
    # 3. the daemon's closed loop on the fitted scenario: 5 mm up at 3 s, settled within 0.6 mm
    t, h, stats = _closed_loop_heights(fitted, 8.0)
    assert stats["faults"] == {} and stats["safe_exit"]
    after = t > 5.0
    assert after.sum() > 50 and np.all(np.abs(h[after] - 7e-3) <= 0.6e-3), (h[after].min(), h[after].max())


def _cpu_s(pid: int) -> float:
    """User and system CPU time of a running process, s (/proc)."""
    import os

    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.slow
@pytest.mark.subprocess
def test_ctrl_c_during_a_fit_exits_130_without_a_traceback(tmp_path):
    data = tmp_path / "run.csv"
    # a run long enough that the fit is still replaying when the signal comes
    rows = ["t_s,p_kpa,speed,inlet,outlet"] + [f"{0.01 * i:.2f},{min(0.02 * i, 20):g},1,1,0" for i in range(6000)]
    data.write_text("\n".join(rows) + "\n")
    proc = subprocess.Popen([sys.executable, "-m", "hbma_ctrl", "fit", str(data), "--out", str(tmp_path / "o")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # by the process's own CPU time, not the wall clock: the imports take about 3 s of it, the fit minutes
    while _cpu_s(proc.pid) < 8.0 and proc.poll() is None:
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err and "interrupted" in err
    assert not (tmp_path / "o").exists()
