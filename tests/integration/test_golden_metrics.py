"""Every shipped scenario's metrics, pinned: a change that moves a non-timing metric is a change in
behaviour, never a side effect of restructuring.

``tests/data/golden/<scenario>.json`` holds each scenario's pinned metrics.json (rewrite one only for a
change of behaviour that is meant, and say so in the commit). Every number except the wall and solve
times must be met to 1e-6 relative. The cheap scenarios run in CI; all of them run with
``pytest -m sweep tests/integration/test_golden_metrics.py`` (about 25 min on 2 cores).
"""

from __future__ import annotations

import json
import math
import re

import pytest

from checkout import SCENARIOS, TEST_DATA
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.app.scenes.runner import run_scenario

GOLDEN = TEST_DATA / "golden"
#: wall-clock measurements, which depend on the machine and its load
TIMING = re.compile(r"^((solve_cpu|solve|step|controller|ekf|est_step|tick)_(ms|us)_(median|p99|max|mean)|wall_s)$")
#: the scenarios CI runs (each well under a minute); the rest run with -m sweep
CHEAP = ("open_loop_fig7", "track_height", "mpc_load_step", "robot_sequential", "ekf_load_steps")
ALL = sorted(p.stem for p in GOLDEN.glob("*.json"))


def differences(golden, new, path: str = "", rtol: float = 1e-6) -> list[str]:
    """Where ``new`` departs from ``golden``: numbers beyond ``rtol`` (NaN equals NaN), other values
    unequal, keys or list lengths that differ; timing keys are skipped."""
    key = path.rsplit(".", 1)[-1]
    if TIMING.match(key) or path == ".scenario.path":
        return []
    if isinstance(golden, dict) and isinstance(new, dict):
        out = [f"{path}.{k}: only in {'the run' if k in new else 'the golden file'}"
               for k in sorted(set(golden) ^ set(new)) if not TIMING.match(k) and f"{path}.{k}" != ".scenario.path"]
        for k in sorted(set(golden) & set(new)):
            out += differences(golden[k], new[k], f"{path}.{k}", rtol)
        return out
    if isinstance(golden, list) and isinstance(new, list):
        if len(golden) != len(new):
            return [f"{path}: {len(golden)} entries in the golden file, {len(new)} in the run"]
        return [d for i, (g, n) in enumerate(zip(golden, new)) for d in differences(g, n, f"{path}[{i}]", rtol)]
    numbers = (int, float)
    if isinstance(golden, numbers) and isinstance(new, numbers) and not isinstance(golden, bool):
        if math.isnan(golden) and math.isnan(new) or math.isclose(golden, new, rel_tol=rtol, abs_tol=1e-12):
            return []
        return [f"{path}: golden {golden!r}, run {new!r}"]
    return [] if golden == new else [f"{path}: golden {golden!r}, run {new!r}"]


def test_differences_finds_a_moved_metric_and_skips_the_timings():
    golden = {"controller": {"height_rmse_mm": 0.25, "solve_ms_median": 1.0, "steps": [1, 2]}}
    assert differences(golden, {"controller": {"height_rmse_mm": 0.25, "solve_ms_median": 9.0, "steps": [1, 2]}}) == []
    assert differences(golden, {"controller": {"height_rmse_mm": 0.2500003, "solve_ms_median": 1.0,
                                               "steps": [1, 2]}})
    assert differences(golden, {"controller": {"height_rmse_mm": 0.25, "steps": [1, 3]}}) == [
        ".controller.steps[1]: golden 2, run 3"]


def _check(name: str, tmp_path) -> None:
    golden = json.loads((GOLDEN / f"{name}.json").read_text())
    new = json.loads(json.dumps(run_scenario(load_scenario(SCENARIOS / f"{name}.toml"), tmp_path)))
    found = differences(golden, new)
    assert not found, f"{name}: " + "; ".join(found[:20])


@pytest.mark.slow
@pytest.mark.parametrize("name", CHEAP)
def test_cheap_scenarios_keep_their_metrics(name, tmp_path):
    _check(name, tmp_path)


@pytest.mark.sweep
@pytest.mark.parametrize("name", [n for n in ALL if n not in CHEAP])
def test_every_other_scenario_keeps_its_metrics(name, tmp_path):
    _check(name, tmp_path)
