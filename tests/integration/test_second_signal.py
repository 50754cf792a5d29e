"""A second ending signal ends a run at once and still leaves nothing hidden or locked; what a process
killed outright left hidden is made visible by the next run on the same --out."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from checkout import ROOT
from hbma_ctrl.app.outputs import run_dir

# A run whose clean-up hangs after the first signal (as a rig that never answers its safe command
# would): only a second signal can end it. It says on stdout when its work has begun and when its
# clean-up has, so the test signals at those points, not after a guessed delay.
CHILD = """
import signal, sys
from pathlib import Path
from hbma_ctrl.app.endsignals import end_on_signals
from hbma_ctrl.app.outputs import run_dir

end_on_signals()
with run_dir(Path(sys.argv[1]), command="test", argv=sys.argv[1:]) as tmp:
    (tmp / "part.csv").write_text("t_s\\n0\\n")
    try:
        print("working", flush=True)
        while True:
            signal.pause()
    except KeyboardInterrupt:
        print("cleaning up", flush=True)
        while True:
            signal.pause()
"""


def _child(out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, "-c", CHILD, str(out)], cwd=out.parent, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_line(proc: subprocess.Popen, line: str, limit_s: float = 120.0) -> None:
    """Block until the child prints ``line``; the limit only turns a hung child into a failure."""
    deadline = time.monotonic() + limit_s
    while True:
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
        assert ready, f"no {line!r} from the child within {limit_s} s"
        got = proc.stdout.readline()
        assert got, f"the child ended before {line!r}: {proc.communicate()}"
        if got.strip() == line:
            return


@pytest.mark.subprocess
@pytest.mark.parametrize("first, second", [(signal.SIGTERM, signal.SIGINT), (signal.SIGINT, signal.SIGHUP),
                                           (signal.SIGHUP, signal.SIGTERM)])
def test_a_second_signal_ends_at_once_with_no_hidden_temporary_and_no_lock(tmp_path, first, second):
    out = tmp_path / "o"
    proc = _child(out)
    try:
        _wait_for_line(proc, "working")
        proc.send_signal(first)
        _wait_for_line(proc, "cleaning up")
        proc.send_signal(second)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + second, err
    assert not list(tmp_path.glob(".o.*")), "a hidden temporary or a lock was left"
    (partial,) = tmp_path.glob("o.interrupted-*")
    assert (partial / "part.csv").read_text() == "t_s\n0\n" and not out.exists()
    man = json.loads((partial / "manifest.json").read_text())
    first_name = "KeyboardInterrupt" if first == signal.SIGINT else first.name
    assert man["status"] == "interrupted" and man["command"] == "test"
    assert man["error"].startswith(f"{first_name}, then {second.name}") and "cut short" in man["error"]
    assert err.strip().splitlines()[-1] == f"interrupted: partial results in {partial} (cut short by a second signal)"


@pytest.mark.subprocess
def test_the_next_run_makes_visible_what_a_killed_run_left_hidden(tmp_path, capfd):
    out = tmp_path / "o"
    proc = _child(out)
    try:
        _wait_for_line(proc, "working")
        proc.kill()  # SIGKILL: no handler runs, the temporary and the lock stay
        proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    (hidden,) = tmp_path.glob(".o.tmp-*")
    assert hidden.name.startswith(f".o.tmp-{proc.pid}-") and (tmp_path / ".o.lock").exists()

    capfd.readouterr()
    with run_dir(out, command="again", argv=[]) as tmp:
        (tmp / "a.txt").write_text("a")
    err = capfd.readouterr().err
    (partial,) = tmp_path.glob("o.interrupted-*")
    assert err.strip().splitlines() == [
        f"note: --out {out}: a run of pid {proc.pid} that ended without its clean-up had left its work hidden "
        f"in {hidden.name}; kept as {partial}"]
    assert (partial / "part.csv").exists() and (out / "a.txt").exists()
    man = json.loads((partial / "manifest.json").read_text())
    assert man["status"] == "interrupted" and man["command"] == "test" and "cut short" in man["error"]
    assert json.loads((out / "manifest.json").read_text())["status"] == "complete"
    assert not list(tmp_path.glob(".o.*"))
