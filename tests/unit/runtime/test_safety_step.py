"""The runtime's safety blocks as casadi Functions against their classes, step by step over long random
runs: the supervisor's policy (hbma_ctrl.runtime.safety_step) against Supervisor.apply, for the robot's
supervisor (two columns, plans by time, the stretch interlock, lost estimates, bursts) and a
chamber-style one (three columns, the outlet opened at the limit, plans by rows, missing pressures at
the limit); the burst test's period (hbma_ctrl.runtime.burst.burst_function) against BurstTest."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.runtime.robot import robot_supervisor
from hbma_ctrl.runtime.safety import Supervisor, SupervisorSettings
from hbma_ctrl.runtime.safety_step import EVENTS, state_size, supervisor_function, supervisor_state

P_MAX = 45e3


def _robot(n: int) -> Supervisor:
    sup = robot_supervisor(P_MAX, n, plan_period=0.02, fallback_plan_steps=4)
    sup.settings.stretch_max = 3.5
    sup.settings.vent_height = 5e-5
    return sup


def _chamber_style(n: int) -> Supervisor:
    return Supervisor(SupervisorSettings(p_max=P_MAX, guard_margin=1e3, vent_margin=0.5e3, fallback_plan_steps=3,
                                         stretch_max=3.0), n=n)


def _run(sup: Supervisor, c: int, H: int, steps: int, seed: int) -> dict:
    """Supervisor and Function side by side on the same random inputs; what each kind of event was
    seen (so the test can check the run reached it)."""
    n = sup.n
    f = supervisor_function(sup.settings, n, c, H)
    assert f.nnz_in("state") == state_size(n, c, H)
    state = supervisor_state(sup, c, H)
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
        counts0, failed0 = dict(sup.counts), sup.failed_steps
        want = sup.apply(t, cmd, p, ok=ok if not ok.all() else True, plan=plan, target=target, stretch=stretch,
                         lost=lost, burst=burst)
        out, state, released, events, failed = f(
            t, cmd.ravel(), p, ok.astype(float), np.zeros(H * n * c) if plan is None else plan.ravel(),
            0.0 if plan is None else 1.0, target, stretch, lost.astype(float), burst.astype(float), state)
        np.testing.assert_array_equal(np.asarray(out).reshape(n, c), want, err_msg=f"command at step {k}")
        np.testing.assert_array_equal(np.asarray(released).ravel() > 0.5, sup.released, err_msg=f"released, step {k}")
        np.testing.assert_array_equal(np.asarray(state).ravel(), supervisor_state(sup, c, H), err_msg=f"state, step {k}")
        ev = np.asarray(events).reshape(len(EVENTS), n)
        for j, key in enumerate(EVENTS):
            assert ev[j].sum() == sup.counts[key] - counts0[key], (key, k)
            seen[key] += int(ev[j].sum())
        assert float(failed) == sup.failed_steps - failed0
        seen["failed"] += int(float(failed))
        seen["released"] += int(sup.released.sum())
    return seen


@pytest.mark.parametrize("seed", [0, 1])
def test_the_robots_supervisor_as_one_function_follows_apply(seed):
    """Four chambers, two columns, a 15-row plan replayed by time (20 ms rows, 10 ms steps): the same
    commands, releases, state and counts at every step of 400, every rule reached."""
    seen = _run(_robot(4), 2, 15, 400, seed)
    assert all(v > 0 for v in seen.values()), seen


def test_a_chamber_style_supervisor_as_one_function_follows_apply():
    """Three columns, the outlet opened within the vent margin, missing pressures at the limit, the
    plan replayed row by row, no vent rule: the same at every step of 400, every other rule reached."""
    seen = _run(_chamber_style(3), 3, 10, 400, 2)
    assert seen.pop("vent") == 0 and all(v > 0 for v in seen.values()), seen


@pytest.mark.parametrize("relapses", [2, 3, 5])
def test_the_burst_test_as_one_function_follows_the_class(relapses):
    """500 periods of 5 chambers: innovations with NaN (unused readings), -inf and +inf, runs of
    falls that flag by the sum, lost estimates in bursts that flag by relapses within the window and
    spread out ones that do not, and restarts (the supervisor's releases): the same flags, sums, peaks
    and kept lost times at every period, both ways of flagging reached."""
    from hbma_ctrl.runtime.burst import BurstTest, BurstTestSettings, burst_function, burst_state

    n = 5
    settings = BurstTestSettings(relapses=relapses, relapse_window=0.3)
    bt = BurstTest(n, settings)
    f = burst_function(settings, n)
    state = burst_state(bt)
    rng = np.random.default_rng(relapses)
    restarted = np.zeros(n, dtype=bool)
    by_sum = by_lost = 0
    for k in range(500):
        t = 0.01 * k
        r = rng.normal(0.0, 2.0, n)
        if k % 97 < 6:
            r[(k // 97) % 3] = -rng.uniform(10.0, 60.0)  # a run of falls on one of chambers 0-2
        r[rng.uniform(size=n) < 0.05] = np.nan
        r[rng.uniform(size=n) < 0.01] = -np.inf
        r[rng.uniform(size=n) < 0.01] = np.inf
        lost = rng.uniform(size=n) < (0.3 if k % 150 < 10 else 0.01)
        lost[:3] &= rng.uniform(size=3) < 0.1  # chambers 0-2 lose their estimates seldom
        if k % 200 == 199:
            bt.reset()  # a person cleared the flags: the class and the Function start again
            state = burst_state(bt)
        bt.restart(restarted)
        new_u = bt.update(r)
        new_l = bt.lost(t, lost)
        now, flagged, state = (np.asarray(v).ravel() for v in f(t, r, lost.astype(float), restarted.astype(float), state))
        np.testing.assert_array_equal(now > 0.5, new_u | new_l, err_msg=f"period {k}")
        np.testing.assert_array_equal(flagged > 0.5, bt.flagged, err_msg=f"period {k}")
        np.testing.assert_array_equal(state, burst_state(bt), err_msg=f"period {k}")
        by_sum += int(new_u.sum())
        by_lost += int(new_l.sum())
        restarted = rng.uniform(size=n) < 0.05
    assert by_sum > 0 and by_lost > 0, (by_sum, by_lost)
