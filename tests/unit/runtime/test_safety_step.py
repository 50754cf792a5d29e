"""The runtime's safety blocks as casadi Functions against numpy oracles, step by step over long random
runs: the supervisor (hbma_ctrl.runtime.safety.Supervisor, which runs
hbma_ctrl.runtime.safety_step.supervisor_function) against the rule-by-rule numpy policy
(tests/oracles/safety.py), for the robot's supervisor (two columns, plans by time, the stretch
interlock, lost estimates, bursts) and a chamber-style one (three columns, the outlet opened at the
limit, plans by rows, missing pressures at the limit); the burst test (hbma_ctrl.runtime.burst.BurstTest,
which runs hbma_ctrl.runtime.burst.burst_function) against its numpy oracle (tests/oracles/burst.py)."""

from __future__ import annotations

import numpy as np
import pytest
from oracles.safety import SupervisorOracle, oracle_state

from hbma_ctrl.runtime.robot import robot_supervisor
from hbma_ctrl.runtime.safety import Supervisor, SupervisorSettings
from hbma_ctrl.runtime.safety_step import EVENTS, state_size, supervisor_function

P_MAX = 45e3


def _robot(n: int) -> SupervisorSettings:
    s = robot_supervisor(P_MAX, n, plan_period=0.02, fallback_plan_steps=4).settings
    s.stretch_max = 3.5
    s.vent_height = 5e-5
    return s


def _chamber_style() -> SupervisorSettings:
    return SupervisorSettings(p_max=P_MAX, guard_margin=1e3, vent_margin=0.5e3, fallback_plan_steps=3, stretch_max=3.0,
                              event_log_size=50)


def _run(settings: SupervisorSettings, n: int, c: int, H: int, steps: int, seed: int) -> dict:
    """The Supervisor and the oracle side by side on the same random inputs: the same commands,
    releases, latches, state, counts and event log at every step; what each kind of event was seen
    (so the test can check the run reached it)."""
    sup, oracle = Supervisor(settings, n), SupervisorOracle(settings, n)
    assert supervisor_function(settings, n, c, H).nnz_in("state") == state_size(n, c, H)
    rng = np.random.default_rng(seed)
    seen = {k: 0 for k in EVENTS} | {"released": 0, "failed": 0}
    fail_run = 0
    for k in range(steps):
        t = 0.01 * k
        cmd = rng.uniform(-0.1, 1.1, (n, c))  # out of [0, 1] too: clipped
        if fail_run == 0 and rng.uniform() < 0.08:
            fail_run = int(rng.integers(1, 8))  # a run of failures longer than the plan may last
        if fail_run:
            fail_run -= 1
            ok = rng.uniform(size=n) < 0.3 if rng.uniform() < 0.3 else np.zeros(n, dtype=bool)
        else:
            ok = np.ones(n, dtype=bool)
        plan = rng.uniform(0.0, 1.0, (H, n, c)) if rng.uniform() < (0.9 if ok.all() else 0.3) else None
        p = rng.uniform(0.0, P_MAX + 2e3, n)
        p[rng.uniform(size=n) < 0.1] = np.nan
        p[rng.uniform(size=n) < 0.1] = 500.0  # down: a lost chamber's release
        target = rng.uniform(0.0, 10e-3, n)
        target[rng.uniform(size=n) < 0.1] = 0.0
        stretch = rng.uniform(1.0, 4.0, n)
        stretch[rng.uniform(size=n) < 0.1] = np.nan
        lost = rng.uniform(size=n) < 0.03
        burst = rng.uniform(size=n) < (0.01 if k > steps // 2 else 0.0)
        cause = f"cause {k % 3}"
        counts0, failed0 = dict(oracle.counts), oracle.failed_steps
        args = dict(ok=ok if not ok.all() else True, plan=plan, target=target, stretch=stretch, lost=lost, burst=burst,
                    cause=cause)
        want = oracle.apply(t, cmd, p, **args)
        got = sup.apply(t, cmd, p, **args)
        np.testing.assert_array_equal(got, want, err_msg=f"command at step {k}")
        for key in ("released", "lost", "burst"):
            np.testing.assert_array_equal(getattr(sup, key), getattr(oracle, key), err_msg=f"{key}, step {k}")
        np.testing.assert_array_equal(sup.state(c, H), oracle_state(oracle, c, H), err_msg=f"state, step {k}")
        assert (sup.counts, sup.failure_causes, sup.failed_steps) == (oracle.counts, oracle.failure_causes,
                                                                       oracle.failed_steps), k
        assert list(sup.events) == list(oracle.events) and sup.logged == oracle.logged, k
        for key in EVENTS:
            seen[key] += oracle.counts[key] - counts0[key]
        seen["failed"] += oracle.failed_steps - failed0
        seen["released"] += int(oracle.released.sum())
        if k == steps - 50:
            sup.reset()
            oracle.reset()
    return seen


@pytest.mark.parametrize("seed", [0, 1])
def test_the_robots_supervisor_as_one_function_follows_apply(seed):
    """Four chambers, two columns, a 15-row plan replayed by time (20 ms rows, 10 ms steps), a reset
    near the end: the same commands, releases, state, counts and log at every step of 400, every rule
    reached."""
    seen = _run(_robot(4), 4, 2, 15, 400, seed)
    assert all(v > 0 for v in seen.values()), seen


def test_a_chamber_style_supervisor_as_one_function_follows_apply():
    """Three columns, the outlet opened within the vent margin, missing pressures at the limit, the
    plan replayed row by row, no vent rule, a log shorter than the run: the same at every step of 400,
    every other rule reached."""
    seen = _run(_chamber_style(), 3, 3, 10, 400, 2)
    assert seen.pop("vent") == 0 and all(v > 0 for v in seen.values()), seen


@pytest.mark.parametrize("relapses", [2, 3, 5])
def test_the_burst_test_as_one_function_follows_the_numpy_test(relapses):
    """500 periods of 5 chambers: innovations with NaN (unused readings), -inf and +inf, exactly at the
    allowance and at the cap, runs of falls that flag by the sum, lost estimates in bursts that flag
    by relapses within the window (times a whole window apart among them: the window is open) and
    spread out ones that do not, restarts (the supervisor's releases) and resets of some chambers
    and of all: the same flags, reasons, sums, peaks and kept lost times at every period, both ways
    of flagging reached."""
    from oracles.burst import BurstTestOracle, oracle_state

    from hbma_ctrl.runtime.burst import BurstTest, BurstTestSettings, burst_function, burst_state

    n = 5
    settings = BurstTestSettings(relapses=relapses, relapse_window=20 / 64)  # t and the window exact in binary
    bt, oracle = BurstTest(n, settings), BurstTestOracle(n, settings)
    assert burst_function(settings, n).nnz_in("state") == burst_state(bt).size
    rng = np.random.default_rng(relapses)
    restarted = np.zeros(n, dtype=bool)
    by_sum = by_lost = 0
    for k in range(500):
        t = k / 64
        r = rng.normal(0.0, 2.0, n)
        if k % 97 < 6:
            r[(k // 97) % 3] = -rng.uniform(10.0, 60.0)  # a run of falls on one of chambers 0-2
        r[rng.uniform(size=n) < 0.05] = np.nan
        r[rng.uniform(size=n) < 0.01] = -np.inf
        r[rng.uniform(size=n) < 0.01] = np.inf
        r[rng.uniform(size=n) < 0.03] = -settings.allowance
        r[rng.uniform(size=n) < 0.03] = -settings.allowance - settings.step_cap
        lost = rng.uniform(size=n) < (0.3 if k % 150 < 10 else 0.01)
        lost[:3] &= rng.uniform(size=3) < 0.1  # chambers 0-2 lose their estimates seldom
        if k % 20 == 0:
            lost[4] = True  # a whole window apart: never within one window
        if k % 200 == 199:
            mask = None if k == 199 else rng.uniform(size=n) < 0.5  # a person cleared the flags
            bt.reset(mask)
            oracle.reset(mask)
        bt.restart(restarted)
        oracle.restart(restarted)
        new_u = oracle.update(r)
        new_l = oracle.lost(t, lost)
        np.testing.assert_array_equal(bt.step(t, r, lost), new_u | new_l, err_msg=f"period {k}")
        np.testing.assert_array_equal(bt.flagged, oracle.flagged, err_msg=f"period {k}")
        np.testing.assert_array_equal(burst_state(bt), oracle_state(oracle), err_msg=f"period {k}")
        assert bt.why == oracle.why, k
        by_sum += int(new_u.sum())
        by_lost += int(new_l.sum())
        restarted = rng.uniform(size=n) < 0.05
    assert by_sum > 0 and by_lost > 0, (by_sum, by_lost)
