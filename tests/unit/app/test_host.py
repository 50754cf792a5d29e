"""The daemon's ask for a short scheduler slice (hbma_ctrl.app.daemon.host)."""

from __future__ import annotations

import os
import platform
import re
import sys
import threading

import pytest

from hbma_ctrl.app.daemon import host as latency
from hbma_ctrl.app.daemon.host import SLICE_S, ask_short_slice, thread_slice_s


def _kernel_takes_slices() -> bool:
    """Linux 6.12 or later on a machine the module knows: a fair task's slice is its own."""
    m = re.match(r"(\d+)\.(\d+)", platform.release())
    return (sys.platform.startswith("linux") and platform.machine() in latency._SYSCALLS and m is not None
            and (int(m.group(1)), int(m.group(2))) >= (6, 12))


def _in_thread(fn):
    out: dict = {}

    def run():
        out["tid"] = threading.get_native_id()
        out["value"] = fn()

    t = threading.Thread(target=run)
    t.start()
    t.join()
    return out


def test_the_slice_is_the_calling_threads_own_and_its_nice_value_is_kept():
    if not _kernel_takes_slices():
        pytest.skip(f"kernel {platform.release()} on {platform.machine()}: no per-task slice to ask for")
    main_before = thread_slice_s()

    def ask():
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + 2)  # raising needs no right
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        got = ask_short_slice()
        return got, thread_slice_s(), nice, os.getpriority(os.PRIO_PROCESS, tid), os.sched_getscheduler(tid)

    got, now, nice_before, nice_after, policy = _in_thread(ask)["value"]
    assert got == pytest.approx(SLICE_S) and now == pytest.approx(SLICE_S)
    assert nice_after == nice_before and policy == os.SCHED_OTHER
    assert thread_slice_s() == main_before  # the other threads keep theirs


def test_a_slice_asked_back_restores_the_one_the_thread_had():
    if not _kernel_takes_slices():
        pytest.skip(f"kernel {platform.release()}: no per-task slice to ask for")

    def ask_and_restore():
        before = thread_slice_s()
        ask_short_slice()
        return before, ask_short_slice(before), thread_slice_s()

    before, restored, now = _in_thread(ask_and_restore)["value"]
    assert before is not None and restored == pytest.approx(before) and now == pytest.approx(before)


def test_a_real_time_thread_is_left_in_its_class():
    def ask():
        tid = threading.get_native_id()
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(1))
        except PermissionError:
            return None
        return ask_short_slice(), os.sched_getscheduler(tid), thread_slice_s()

    if not sys.platform.startswith("linux"):
        pytest.skip("no SCHED_FIFO here")
    got = _in_thread(ask)["value"]
    if got is None:
        pytest.skip("setting a real-time class needs a privilege this test does not have")
    assert got == (None, os.SCHED_FIFO, None)


def test_elsewhere_the_ask_does_nothing_and_says_so(monkeypatch):
    monkeypatch.setattr(latency.sys, "platform", "darwin")
    assert ask_short_slice() is None and thread_slice_s() is None
    monkeypatch.setattr(latency.sys, "platform", "linux")
    monkeypatch.setattr(latency.platform, "machine", lambda: "sparc64")
    assert ask_short_slice() is None and thread_slice_s() is None
