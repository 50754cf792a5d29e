"""Results directories: --out checked before any work, locked, replaced whole, partial work kept aside."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import signal
import subprocess
from pathlib import Path

import pytest
from typer.testing import CliRunner

import hbma_ctrl.app.cli.sim as cli_mod
from checkout import ROOT
import hbma_ctrl.app.endsignals as endsignals
import hbma_ctrl.app.outputs as outputs
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.outputs import MANIFEST_KEYS, RunInterrupted, check_out, default_out, run_dir
from hbma_ctrl.app.scenario import load_scenario

FIG7 = ROOT / "scenarios" / "open_loop_fig7.toml"
runner = CliRunner()


def _one_line(res, code: int) -> str:
    assert res.exit_code == code, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    return lines[0]


def _fake_run(calls: list, raise_exc: BaseException | None = None):
    """A stand-in for run_scenario: records the call, writes one file, optionally raises."""

    def fake(scn, out_dir):
        calls.append(Path(out_dir))
        (Path(out_dir) / "log.csv").write_text("t_s\n0\n")
        if raise_exc is not None:
            raise raise_exc
        (Path(out_dir) / "metrics.json").write_text("{}\n")
        return {"scenario": {"name": scn.name}}

    return fake


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


@pytest.mark.slow
def test_second_run_refused_then_overwrite_replaces_and_manifest_is_complete(tmp_path):
    out = tmp_path / "fig7"
    argv = ["run", str(FIG7), "--out", str(out)]
    first = runner.invoke(app, argv)
    assert first.exit_code == 0, first.output
    metrics = (out / "metrics.json").read_bytes()
    man = json.loads((out / "manifest.json").read_text())
    assert set(MANIFEST_KEYS) <= set(man)
    assert man["status"] == "complete" and man["command"] == "run" and man["argv"] == argv
    assert man["scenario_sha256"] == hashlib.sha256(FIG7.read_bytes()).hexdigest()
    assert man["version"] == "0.1.0" and man["error"] is None
    assert man["git_commit"] is None or len(man["git_commit"]) == 40
    t0 = dt.datetime.fromisoformat(man["started_utc"].replace("Z", "+00:00"))
    t1 = dt.datetime.fromisoformat(man["finished_utc"].replace("Z", "+00:00"))
    assert t0.utcoffset() == dt.timedelta(0) and t0 <= t1

    (out / "stale.csv").write_text("from an older run\n")
    man["files"].append("stale.csv")  # an older run's own file: its manifest lists it
    (out / "manifest.json").write_text(json.dumps(man))
    line = _one_line(runner.invoke(app, argv), 2)
    assert "--out" in line and str(out) in line and "--overwrite" in line
    assert (out / "metrics.json").read_bytes() == metrics  # the first run is intact

    again = runner.invoke(app, [*argv, "--overwrite"])
    assert again.exit_code == 0, again.output
    assert not (out / "stale.csv").exists()  # replaced whole: nothing of the old run is left
    assert {p.name for p in out.iterdir()} == {"metrics.json", "log.csv", "log.mcap", "run.png", "run.pdf",
                                               "manifest.json"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig7"]  # no temp, old or lock files beside it


def test_a_shipped_scenario_given_by_name_is_hashed_in_the_manifest(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no file called open_loop_fig7 here: the name is the shipped one
    monkeypatch.setattr(cli_mod, "run_scenario", _fake_run([]))
    res = runner.invoke(app, ["run", "open_loop_fig7", "--out", "o"])
    assert res.exit_code == 0, res.output
    man = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert man["scenario_path"] == "open_loop_fig7"
    assert man["scenario_sha256"] == hashlib.sha256(FIG7.read_bytes()).hexdigest()
    # tune, daemon, codegen and the benches write their manifests through the same function
    for given in ("track_height", "scenarios/track_height.toml"):
        sha = outputs.manifest("tune", [], given)["scenario_sha256"]
        assert sha == hashlib.sha256((ROOT / "scenarios" / "track_height.toml").read_bytes()).hexdigest()


def test_failure_midway_leaves_nothing_at_out_and_a_failed_dir(tmp_path, monkeypatch):
    calls: list = []
    monkeypatch.setattr(cli_mod, "run_scenario", _fake_run(calls, ValueError("solver gave up")))
    out = tmp_path / "o"
    line = _one_line(runner.invoke(app, ["run", str(FIG7), "--out", str(out)]), 2)
    assert "solver gave up" in line and "partial results in" in line
    assert not out.exists()
    (failed,) = tmp_path.glob("o.failed-*")
    man = json.loads((failed / "manifest.json").read_text())
    assert man["status"] == "failed" and "solver gave up" in man["error"] and man["finished_utc"]
    assert (failed / "log.csv").exists()
    assert not list(tmp_path.glob(".o.*"))  # lock and temp directory gone


def test_ctrl_c_exits_130_with_one_line_and_an_interrupted_dir(tmp_path, monkeypatch):
    calls: list = []
    monkeypatch.setattr(cli_mod, "run_scenario", _fake_run(calls, KeyboardInterrupt()))
    out = tmp_path / "o"
    line = _one_line(runner.invoke(app, ["run", str(FIG7), "--out", str(out)]), 130)
    (partial,) = tmp_path.glob("o.interrupted-*")
    assert line == f"interrupted: partial results in {partial}"
    assert not out.exists()
    assert json.loads((partial / "manifest.json").read_text())["status"] == "interrupted"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_end_a_run_as_ctrl_c_does_with_exit_128_plus_the_signal(tmp_path, monkeypatch, sig):
    calls: list = []

    def signalled(scn, out_dir):
        calls.append(out_dir)
        (Path(out_dir) / "log.csv").write_text("t_s\n0\n")
        os.kill(os.getpid(), sig)  # the handler raises in this thread at once
        raise AssertionError("the signal did not end the run")

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    monkeypatch.setattr(cli_mod, "run_scenario", signalled)
    out = tmp_path / "o"
    line = _one_line(runner.invoke(app, ["run", str(FIG7), "--out", str(out)]), 128 + sig)
    (partial,) = tmp_path.glob("o.interrupted-*")
    assert line == f"interrupted: partial results in {partial}" and (partial / "log.csv").exists()
    man = json.loads((partial / "manifest.json").read_text())
    assert man["status"] == "interrupted" and man["error"] == sig.name
    assert not out.exists() and not (tmp_path / ".o.lock").exists() and len(calls) == 1
    assert {s: signal.getsignal(s) for s in before} == before  # the caller's handlers are back


def test_protocol_rerun_with_fewer_trials_leaves_no_stale_trial_files(tmp_path, monkeypatch):
    def fake_protocol(names):
        def run(material, out, *a, **kw):
            (Path(out) / "trials").mkdir()
            for n in names:
                (Path(out) / "trials" / f"{n}.csv").write_text("t_s\n")
            (Path(out) / "summary.csv").write_text("status\n" + "ok\n" * len(names))
            return [{"status": "ok", "max_height_mm": 1.0, "max_pressure_kpa": 2.0} for _ in names]
        return run

    out = tmp_path / "protocol"
    monkeypatch.setattr(cli_mod, "run_protocol", fake_protocol(["a", "b", "c"]))
    assert runner.invoke(app, ["protocol", "--out", str(out), "--no-plots"]).exit_code == 0
    monkeypatch.setattr(cli_mod, "run_protocol", fake_protocol(["a"]))
    _one_line(runner.invoke(app, ["protocol", "--out", str(out), "--no-plots"]), 2)
    res = runner.invoke(app, ["protocol", "--out", str(out), "--no-plots", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (out / "trials").iterdir()) == ["a.csv"]
    assert json.loads((out / "manifest.json").read_text())["command"] == "protocol"


@pytest.mark.parametrize("kind", ["file", "device", "parent_file", "long_name", "long_parent", "no_files_here"])
def test_unusable_out_is_refused_before_any_work(tmp_path, monkeypatch, kind):
    calls: list = []
    monkeypatch.setattr(cli_mod, "run_scenario", _fake_run(calls))
    target = {"file": tmp_path / "a_file", "device": Path("/dev/null"), "parent_file": tmp_path / "a_file" / "sub",
              "long_name": tmp_path / ("a" * 230), "long_parent": tmp_path / ("b" * 300) / "run",
              "no_files_here": Path("/proc/hbma_ctrl_run")}[kind]
    (tmp_path / "a_file").write_text("not a directory\n")
    line = _one_line(runner.invoke(app, ["run", str(FIG7), "--out", str(target)]), 2)
    assert line.startswith("error: --out ") and str(target)[:40] in line
    assert calls == []  # no work was done
    why = {"device": "device", "long_name": "is 230 bytes long; a folder name may have at most 200",
           "long_parent": "is 300 bytes long; a folder name may have at most 255",
           "no_files_here": "no file can be created in /proc"}
    assert why.get(kind, "") in line


def test_a_scenario_name_too_long_for_a_folder_is_one_error_naming_the_key(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(f'[scenario]\nname = "{"n" * 20000}"\nduration_s = 6.0\n')
    line = _one_line(runner.invoke(app, ["run", str(p)]), 2)
    assert "[scenario] name" in line and "20000 characters long: at most 200" in line and len(line) < 300


def test_a_folder_given_as_the_scenario_file_is_named_a_folder(tmp_path):
    line = _one_line(runner.invoke(app, ["run", str(tmp_path)]), 2)
    assert str(tmp_path) in line and "is a folder" in line


def test_unwritable_parent_is_refused(tmp_path, monkeypatch):
    # as root every directory is writable: make os.access answer as for an ordinary user
    monkeypatch.setattr(outputs.os, "access", lambda path, mode: False)
    with pytest.raises(ValueError, match="--out .* is not writable"):
        check_out(tmp_path / "o")


def test_held_lock_is_refused_and_a_stale_lock_is_taken_over(tmp_path, monkeypatch):
    calls: list = []
    monkeypatch.setattr(cli_mod, "run_scenario", _fake_run(calls))
    out = tmp_path / "o"
    lock = tmp_path / ".o.lock"
    lock.write_text(f"{os.getpid()}\n")  # a live writer
    line = _one_line(runner.invoke(app, ["run", str(FIG7), "--out", str(out)]), 2)
    assert "--out" in line and "in use" in line and str(os.getpid()) in line
    assert calls == [] and not out.exists()

    lock.write_text(f"{_dead_pid()}\n")  # its writer is gone
    res = runner.invoke(app, ["run", str(FIG7), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert len(calls) == 1 and (out / "manifest.json").exists() and not lock.exists()


def test_scenario_name_must_be_a_plain_name(tmp_path, monkeypatch):
    for name in ("../x", "/abs", ".hidden", "a/b"):
        p = tmp_path / "s.toml"
        p.write_text(f'[scenario]\nname = "{name}"\n')
        line = _one_line(runner.invoke(app, ["run", str(p)]), 2)
        assert "[scenario] name" in line and "plain directory name" in line
    # a file stem that cannot be a directory name, used as the default name
    calls: list = []
    monkeypatch.setattr(cli_mod, "run_scenario", _fake_run(calls))
    p = tmp_path / "two words.toml"
    p.write_text("[scenario]\nduration_s = 6.0\n")
    line = _one_line(runner.invoke(app, ["run", str(p)]), 2)
    assert "[scenario] name" in line and "--out" in line and calls == []
    assert default_out("fig_7.v2") == Path("runs/fig_7.v2")
    assert load_scenario(FIG7).name == "open_loop_fig7"


def test_run_dir_directly_keeps_partial_work_and_carries_a_cache(tmp_path):
    out = tmp_path / "bench"
    with run_dir(out, command="bench sim", argv=[]) as tmp:
        (tmp / "ref_free.npz").write_bytes(b"cache")
        (tmp / "bench.json").write_text("{}")
    with run_dir(out, command="bench sim", argv=[], overwrite=True, carry=("ref_*.npz",)) as tmp:
        assert (tmp / "ref_free.npz").read_bytes() == b"cache" and not (tmp / "bench.json").exists()
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "ref_free.npz"]

    with pytest.raises(RunInterrupted) as info:
        with run_dir(tmp_path / "x", command="t", argv=[]) as tmp:
            (tmp / "part.csv").write_text("1\n")
            raise KeyboardInterrupt
    assert info.value.partial.name.startswith("x.interrupted-") and (info.value.partial / "part.csv").exists()
    with pytest.raises(RuntimeError) as err:
        with run_dir(tmp_path / "y", command="t", argv=[]):
            raise RuntimeError("boom")
    assert err.value.partial_results.name.startswith("y.failed-")
    empty = tmp_path / "empty"
    empty.mkdir()
    with run_dir(empty, command="t", argv=[]) as tmp:  # an empty directory is not a run: accepted
        (tmp / "a.txt").write_text("a")
    assert (empty / "a.txt").exists()


def test_log_csv_is_what_csv_writer_writes_quoting_included(tmp_path):
    """The bulk-formatted trial CSV is byte for byte what csv.writer wrote value by value (%.9g,
    CRLF rows, an event naming a comma quoted), NaN and negative zero included."""
    import csv

    import numpy as np

    from hbma_ctrl.app.metrics import edge_series, write_log_csv
    from hbma_ctrl.sim.trial import Log

    t = np.linspace(0.0, 0.05, 6)
    data = {"t": t, "h": np.array([0.0, 1e-3, np.nan, -0.0, 2.123456789e-3, 5e-3]), "p": 1e3 * np.arange(6.0)}
    log = Log("x", "free", data, events=[(0.01, "lift_off"), (0.01, "b,c"), (0.04, 'q"x')])
    path = tmp_path / "x.csv"
    write_log_csv(log, path)
    cols = edge_series(log)
    keys = list(cols)
    ev = {1: 'lift_off;b,c', 4: 'q"x'}
    ref = tmp_path / "ref.csv"
    with open(ref, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(keys + ["event"])
        for i in range(len(t)):
            w.writerow([f"{cols[k][i]:.9g}" for k in keys] + [ev.get(i, "")])
    assert path.read_bytes() == ref.read_bytes()


def _write_marker(path):
    Path(path).write_text(str(os.getpid()))


def _fail_in_child(path, parent_pid):
    if os.getpid() != parent_pid:
        raise RuntimeError("child fails")
    Path(path).write_text("parent")


@pytest.mark.subprocess
def test_forked_work_is_done_by_a_child_or_redone_here_when_the_child_fails(tmp_path):
    from hbma_ctrl.app.forked import Forked

    ok = tmp_path / "ok.txt"
    job = Forked(_write_marker, ok)
    job.join()
    assert ok.exists()
    import multiprocessing as mp

    if "fork" in mp.get_all_start_methods() and (os.cpu_count() or 1) > 1:
        assert ok.read_text() != str(os.getpid())  # written by the child
    failed = tmp_path / "failed.txt"
    Forked(_fail_in_child, failed, os.getpid()).join()
    assert failed.read_text() == "parent"  # the child's failure is redone in this process, not lost


def _write_what_arrives(recv, path, parent_pid, fail):
    got = []
    while (obj := recv()) is not None:
        got.append(obj)
    if fail and os.getpid() != parent_pid:
        raise RuntimeError("child fails")
    Path(path).write_text(f"{os.getpid()} {got}")


@pytest.mark.subprocess
@pytest.mark.parametrize("fail", [False, True])
def test_forked_work_with_an_inbox_gets_what_is_sent_in_order_even_when_redone_here(tmp_path, fail):
    from hbma_ctrl.app.forked import Forked

    out = tmp_path / "got.txt"
    job = Forked(_write_what_arrives, out, os.getpid(), fail, inbox=True)
    for obj in ([1, 2], "three", None):
        job.send(obj)
    job.join()
    pid, got = out.read_text().split(" ", 1)
    assert got == "[[1, 2], 'three']"
    import multiprocessing as mp

    if "fork" in mp.get_all_start_methods() and (os.cpu_count() or 1) > 1:
        assert (int(pid) == os.getpid()) == fail  # the child's work, or this process's redo of it


def test_overwrite_replaces_a_run_but_never_a_users_own_directory(tmp_path, monkeypatch):
    """--overwrite on a directory of a user's files, on the current directory or on one holding it, on
    the home directory: one error naming --out, every file still there; on a run: replaced."""
    from hbma_ctrl.app.outputs import check_out, is_run_dir

    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / "chapter1.tex").write_text("years of work")
    with pytest.raises(ValueError, match="--out.*no run of hbma-ctrl"):
        check_out(thesis, overwrite=True)
    monkeypatch.chdir(thesis)
    for out in (Path("."), thesis, tmp_path):
        with pytest.raises(ValueError, match="--out.*current directory"):
            check_out(out, overwrite=True)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / ".bashrc").write_text("x")
    with pytest.raises(ValueError, match="--out.*home directory"):
        check_out(tmp_path / "home", overwrite=True)
    assert (thesis / "chapter1.tex").read_text() == "years of work"

    run = tmp_path / "run"
    with run_dir(run, command="t", argv=[]) as tmp:
        (tmp / "a.csv").write_text("1\n")
    assert is_run_dir(run) and not is_run_dir(thesis)
    with run_dir(run, command="t", argv=[], overwrite=True) as tmp:
        (tmp / "b.csv").write_text("2\n")
    assert sorted(p.name for p in run.iterdir()) == ["b.csv", "manifest.json"]


@pytest.mark.parametrize("argv, kept", [
    (["daemon", "x.toml", "--token", "s3cret", "--api", "0.0.0.0:1"],
     ["daemon", "x.toml", "--token", "<redacted>", "--api", "0.0.0.0:1"]),
    (["daemon", "--token=s3cret"], ["daemon", "--token=<redacted>"]),
    (["daemon", "--out", "token"], ["daemon", "--out", "token"]),
])
def test_a_token_never_reaches_the_manifest(tmp_path, argv, kept):
    with run_dir(tmp_path / "r", command="daemon", argv=argv):
        pass
    text = (tmp_path / "r" / "manifest.json").read_text()
    assert json.loads(text)["argv"] == kept and "s3cret" not in text


def test_raise_if_signalled_raises_the_signal_a_solver_swallowed_and_nothing_without_one():
    """A signal whose exception was lost inside C code (casadi's solvers catch it and carry on) is
    raised again at the next check, as the signal it was; without a signal the check passes."""
    saved = dict(endsignals._signalled)
    try:
        endsignals._signalled.update(pid=os.getpid(), signum=None)
        endsignals.raise_if_signalled()  # nothing pending: returns
        endsignals._signalled["signum"] = int(signal.SIGTERM)
        with pytest.raises(endsignals.Terminated) as err:
            endsignals.raise_if_signalled()
        assert err.value.signum == signal.SIGTERM and isinstance(err.value, KeyboardInterrupt)
    finally:
        endsignals._signalled.clear()
        endsignals._signalled.update(saved)


def test_a_closed_loop_ends_at_its_next_period_when_a_signal_was_lost_inside_a_solver(tmp_path):
    """end_on_signals registers the check the lockstep driver makes each period: a signal whose exception
    casadi swallowed ends the run as the signal it was, not at the end of the run."""
    from hbma_ctrl.core import interrupt
    from hbma_ctrl.system.run import run_lockstep

    class Never:
        warming = False

        def tick(self, t, p, held):
            raise AssertionError("ticked after the signal")

    saved = dict(endsignals._signalled)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        endsignals.end_on_signals()
        endsignals._signalled["signum"] = int(signal.SIGHUP)  # as the handler leaves it when its raise is lost
        with pytest.raises(endsignals.Terminated) as err:
            run_lockstep(Never(), rig=type("R", (), {"sample_period": 0.01})(), duration=1.0)
        assert err.value.signum == signal.SIGHUP
    finally:
        interrupt.set_check(None)
        for s, h in handlers.items():
            signal.signal(s, h)
        endsignals._signalled.clear()
        endsignals._signalled.update(saved)
