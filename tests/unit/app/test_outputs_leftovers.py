"""What a dead run left hidden beside --out is made visible by the next run, and only that; a signal
while a finished run moves into place acts once it is in place."""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest

import hbma_ctrl.app.endsignals as endsignals
import hbma_ctrl.app.outputs as outputs
from hbma_ctrl.app.outputs import run_dir


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def _run(path, text: str) -> None:
    path.mkdir()
    (path / "a.txt").write_text(text)
    (path / "manifest.json").write_text(json.dumps(dict(outputs.manifest("t", []), status="complete")))


def test_only_a_dead_runs_own_temporary_is_moved_and_a_foreign_manifest_is_kept(tmp_path, capfd):
    dead = _dead_pid()
    ours = tmp_path / f".o.tmp-{dead}-abcd_123"
    ours.mkdir()
    (ours / "manifest.json").write_text('{"mine": 1}')  # not a manifest of this package: left as it is
    legacy = tmp_path / ".o.tmp-k2j4x9_q"  # an older version's name, without the pid
    legacy.mkdir()
    keep = [tmp_path / f".o.tmp-{os.getppid()}-abcdefgh",  # its process runs
            tmp_path / ".o.tmp-notours", tmp_path / f".o.tmp-{dead}-abc", tmp_path / f".oo.tmp-{dead}-abcdefgh"]
    for k in keep:
        k.mkdir()
    as_file = tmp_path / f".o.tmp-{dead}-zzzzzzzz"
    as_file.write_text("a file of that name")
    with run_dir(tmp_path / "o", command="t", argv=[]) as tmp:
        assert tmp.name.startswith(f".o.tmp-{os.getpid()}-")
    lines = capfd.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all(ln.startswith(f"note: --out {tmp_path / 'o'}: ") for ln in lines)
    assert any(f"a run of pid {dead} " in ln and ours.name in ln for ln in lines)
    assert any(": a run that ended without its clean-up" in ln and legacy.name in ln for ln in lines)
    parked = sorted(tmp_path.glob("o.interrupted-*"))
    assert len(parked) == 2 and not ours.exists() and not legacy.exists()
    assert {(p / "manifest.json").read_text() for p in parked if (p / "manifest.json").exists()} >= {'{"mine": 1}'}
    assert all(k.is_dir() for k in keep) and as_file.is_file()


def test_a_run_moved_aside_by_a_dead_replacement_is_put_back_or_kept_visible(tmp_path, capfd):
    out = tmp_path / "o"
    aside = tmp_path / f".o.old-20260101T000000Z-{_dead_pid()}"
    _run(aside, "old")  # the replacement died between its two renames: --out is empty
    with pytest.raises(ValueError, match="--out"):  # the run is back, so it is refused without --overwrite
        with run_dir(out, command="t", argv=[]):
            pass
    assert (out / "a.txt").read_text() == "old" and not aside.exists()
    assert "put back" in capfd.readouterr().err

    _run(aside, "older")  # --out holds a run too: which replaced which is unknown, so both are kept
    with run_dir(out, command="t", argv=[], overwrite=True) as tmp:
        (tmp / "a.txt").write_text("new")
    (kept,) = tmp_path.glob("o.replaced-*")
    assert (kept / "a.txt").read_text() == "older" and (out / "a.txt").read_text() == "new"
    assert f"kept as {kept}" in capfd.readouterr().err and not list(tmp_path.glob(".o.*"))


def test_a_signal_while_a_finished_run_moves_into_place_acts_once_it_is_in_place(tmp_path, monkeypatch):
    out = tmp_path / "o"
    _run(out, "old")
    real = outputs._install

    def signalled_install(tmp, path, run):
        os.kill(os.getpid(), signal.SIGTERM)  # between the complete manifest and the renames
        real(tmp, path, run)

    monkeypatch.setattr(outputs, "_install", signalled_install)
    saved = dict(endsignals._signalled)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        endsignals.end_on_signals()
        with pytest.raises(endsignals.Terminated) as err:
            with run_dir(out, command="t", argv=[], overwrite=True) as tmp:
                (tmp / "a.txt").write_text("new")
        assert err.value.signum == signal.SIGTERM
    finally:
        endsignals.interrupt.set_check(None)
        for s, h in handlers.items():
            signal.signal(s, h)
        endsignals._signalled.clear()
        endsignals._signalled.update(saved)
    assert (out / "a.txt").read_text() == "new"
    assert json.loads((out / "manifest.json").read_text())["status"] == "complete"
    assert not list(tmp_path.glob(".o.*")) and not list(tmp_path.glob("o.*"))
