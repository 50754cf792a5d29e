"""log.mcap of real runs: a short daemon run on the simulated rig holds every period beside its CSV run
log, a daemon killed with SIGKILL leaves a log readable up to its last whole chunk, and
``hbma-ctrl report`` draws a scene's and a daemon's figures with labelled axes in the one unit style."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from checkout import ROOT, SCENARIOS
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.daemon.runlog import read_run_log
from hbma_ctrl.app.figstyle import LABELS
from hbma_ctrl.app.logs.reader import columns, read_mcap
from hbma_ctrl.app.report.figures import make_figures
from hbma_ctrl.app.report.load import load_run

cli = CliRunner()

PERIOD_TOPICS = ("/readings", "/estimates", "/targets", "/commands", "/truth", "/loop")


def _config(tmp: Path, base: Path, **replace) -> Path:
    """``base`` without its fixed API port and with the loop watchdog off (a loaded test machine must not
    decide these tests), and ``replace``'s texts replaced."""
    text = base.read_text().replace('api = "127.0.0.1:8765"\n', "")
    text = text.replace("log_flush_s = 0.5", "log_flush_s = 0.5\nmiss_limit = 100000")
    for a, b in replace.items():
        text = text.replace(a, b)
    p = tmp / base.name
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def daemon_run(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("daemon")
    out = tmp / "run"
    res = cli.invoke(app, ["daemon", str(_config(tmp, SCENARIOS / "daemon_chamber.toml")), "--rig", "sim",
                           "--speed", "5", "--duration-s", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


@pytest.mark.slow
def test_daemon_log_mcap_holds_every_period_of_the_csv_log_with_its_metadata(daemon_run):
    c = read_mcap(daemon_run / "log.mcap")
    header, rows = read_run_log(daemon_run)
    assert not c.truncated and c.metadata["log"]["dropped"] == "0"
    for topic in PERIOD_TOPICS:
        assert c.count(topic) == len(rows), topic
    est = columns(c.messages["/estimates"])
    csv_h = np.array([float(r[header.index("h_est_C1_mm")] or "nan") for r in rows])
    assert np.allclose(est["h_mm.C1"], csv_h, atol=1e-4, equal_nan=True)
    assert np.allclose(est["t_s"], [float(r[0]) for r in rows], atol=1e-4)
    events = [m["kind"] for m in c.messages["/events"]]
    assert events[0] == "start" and "safe_exit" in events
    assert set(c.metadata) >= {"run", "daemon", "calibration", "stats", "log"}
    assert c.metadata["run"]["version"] and c.metadata["daemon"]["chambers"] == "C1"
    assert b"[daemon]" in c.attachments["config.toml"][1]
    assert all(c.schemas[t]["title"] for t in c.messages)


def _log_in(out: Path) -> Path | None:
    tmps = list(out.parent.glob(f".{out.name}.tmp-*/log.mcap"))
    return tmps[0] if tmps else None


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_daemon_killed_with_sigkill_leaves_its_log_whole_up_to_the_last_chunk(tmp_path):
    out = tmp_path / "run"
    cfg = _config(tmp_path, SCENARIOS / "daemon_chamber.toml")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "hbma_ctrl", "daemon", str(cfg), "--rig", "sim", "--duration-s",
                             "600", "--out", str(out)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        seen = 0
        deadline = time.monotonic() + 180
        while seen < 150:  # a second and a half of periods in whole chunks on disk
            assert time.monotonic() < deadline and proc.poll() is None, "the daemon did not log"
            time.sleep(0.5)
            log = _log_in(out)
            if log is not None:
                seen = read_mcap(log).count("/readings")
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    c = read_mcap(_log_in(out))
    assert c.truncated and c.metadata["daemon"]["chambers"] == "C1" and "config.toml" in c.attachments
    t = columns(c.messages["/readings"])["t_s"]
    assert c.count("/readings") >= seen  # what was on disk before the kill is still there
    assert np.allclose(t, 0.01 * np.arange(t.size), atol=1e-6)  # every period from the start, no gap
    for topic in ("/estimates", "/commands", "/loop"):
        assert abs(c.count(topic) - t.size) <= 1, topic  # a period's messages share its chunk but the last


_LABEL = re.compile(r"^[a-z][\w ,]* \([^()]+\)$")


def _check_figures(figs: dict) -> None:
    """Every drawn axis: a y label in the "quantity (unit)" style (the events' rows excepted), the time
    axis labelled "t (s)" on each column's lowest panel, a legend where more than one line is labelled,
    no panel without data, and each kind of line the title names in its brackets in a legend."""
    assert figs
    for name, fig in figs.items():
        axes = [ax for ax in fig.axes if ax.get_visible()]
        assert fig._suptitle is not None and fig._suptitle.get_text(), name
        keys = {t.get_text() for ax in axes if ax.get_legend() for t in ax.get_legend().get_texts()}
        named = re.search(r"\(([^()]*)\)$", fig._suptitle.get_text())
        if named and name != "estimator_errors":  # its brackets say what an error is, not a line
            for word in re.split(r", | and ", named.group(1)):
                assert any(word in k for k in keys), (name, word, sorted(keys))
        for ax in axes:
            drawn = [ln for ln in ax.get_lines() if np.isfinite(np.asarray(ln.get_ydata(), float)).any()]
            assert drawn or ax.collections, (name, ax.get_title(), "an empty panel")
            y = ax.get_ylabel()
            assert _LABEL.match(y) or (name == "events" and y == "event"), (name, y)
            assert ax.get_xlabel() in ("", LABELS["t"]), (name, ax.get_xlabel())
            labelled = [ln for ln in ax.get_lines() if not ln.get_label().startswith("_")]
            if len(labelled) > 1:
                assert ax.get_legend() is not None, (name, y)
        assert LABELS["t"] in [ax.get_xlabel() for ax in axes], name


@pytest.mark.slow
def test_report_of_a_daemon_run_writes_png_and_pdf_of_labelled_figures(daemon_run, tmp_path):
    res = cli.invoke(app, ["report", str(daemon_run), "--out", str(tmp_path / "fig")])
    assert res.exit_code == 0, res.output
    figs = make_figures(load_run(daemon_run))
    assert set(figs) == {"tracking", "pressures", "commands", "estimator_errors", "events"}
    for name in figs:
        assert (tmp_path / "fig" / f"{name}.png").stat().st_size > 10_000
        assert (tmp_path / "fig" / f"{name}.pdf").stat().st_size > 1_000
    _check_figures(figs)


@pytest.mark.slow
def test_report_of_a_daemon_run_without_log_mcap_reads_its_csvs(daemon_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(daemon_run, run)
    (run / "log.mcap").unlink()
    sig = load_run(run)
    assert sig.source == "run_*.csv" and sig.names == ["C1"]
    figs = make_figures(sig)
    assert {"tracking", "pressures", "commands", "events"} <= set(figs)
    _check_figures(figs)


@pytest.mark.slow
def test_report_of_a_robot_scene_draws_its_layers_pose_and_labelled_figures(tmp_path):
    text = (SCENARIOS / "robot_bending.toml").read_text()
    text = re.sub(r"(?m)^duration_s = .*$", "duration_s = 1.0", text, count=1)
    text = re.sub(r"(?m)^compare_baseline = .*$", "compare_baseline = false", text)
    scn = tmp_path / "robot_bending.toml"
    scn.write_text(text)
    out = tmp_path / "run"
    res = cli.invoke(app, ["run", str(scn), "--out", str(out)])
    assert res.exit_code == 0, res.output
    c = read_mcap(out / "log.mcap")
    assert c.metadata["scene"]["kind"] == "robot closed loop" and c.count("/robot/pose") == c.count("/readings") > 0
    res = cli.invoke(app, ["report", str(out), "--out", str(tmp_path / "fig")])
    assert res.exit_code == 0, res.output
    figs = make_figures(load_run(out))
    assert set(figs) >= {"tracking", "pressures", "commands", "estimator_errors", "robot_pose"}
    assert all((tmp_path / "fig" / f"{n}.png").is_file() and (tmp_path / "fig" / f"{n}.pdf").is_file() for n in figs)
    _check_figures(figs)
