"""``hbma-ctrl bench protocol``: the package's main job, ``hbma-ctrl protocol`` on its defaults, timed
as a user runs it.

Each timed run is a fresh interpreter (``python -m hbma_ctrl protocol --out DIR``): start-up, imports,
the 150 trials' simulation, their CSVs, summary.csv and the three figures, as a user waits for them.
The same with ``--no-plots``, and the start-up alone (``import hbma_ctrl.app.cli.main``) in a fresh
interpreter, say where the time goes; the simulation alone is timed in this process (warm: its
compiled model loaded once before). Like the compiled model, Fig. 6 (which shows no input of a run)
is drawn by a machine's first run and copied from the cache after, so the timed runs copy it. Medians
of ``repeat`` runs, written to ``bench.json`` with every run's time. Wall times depend on what else
the machine runs: compare rows of one run.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path

__all__ = ["run_bench_protocol", "TARGET_WALL_S"]

#: the protocol's target wall time, s
TARGET_WALL_S = 2.0


def _timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])} failed (exit {res.returncode}): {res.stderr.strip()[-300:]}")
    return wall


def _summary(xs: list[float]) -> dict:
    return {"median_s": statistics.median(xs), "min_s": min(xs), "max_s": max(xs), "runs_s": xs}


def run_bench_protocol(out: Path, repeat: int = 3, on_row=None) -> dict:
    """Time the protocol command (module doc) ``repeat`` times per row; write and return bench.json's
    dict {row: {median_s, min_s, max_s, runs_s}} plus ``target_wall_s`` and ``meets_target``."""
    from hbma_ctrl.sim.batch import protocol_trials, simulate_trials
    from hbma_ctrl.sim.trial import SimSettings

    py = sys.executable
    rows = {}
    with tempfile.TemporaryDirectory(prefix="bench_protocol_") as scratch:
        def protocol(extra: list[str]):
            def one(i: int) -> float:
                return _timed([py, "-m", "hbma_ctrl", "protocol", "--out", str(Path(scratch) / f"run{len(rows)}_{i}"), *extra])
            return one

        cases = {
            "protocol": protocol([]),
            "protocol --no-plots": protocol(["--no-plots"]),
            "start-up (import hbma_ctrl.app.cli.main)": lambda i: _timed([py, "-c", "import hbma_ctrl.app.cli.main"]),
        }
        for name, fn in cases.items():
            fn(-1)  # a first run fills the compiled-model and figure caches; not timed
            rows[name] = _summary([fn(i) for i in range(repeat)])
            if on_row:
                on_row(name, rows[name])
    trials, settings = protocol_trials("nh"), SimSettings().validate()
    simulate_trials(trials, settings)
    # one call per timing, the garbage collector on as in a user's run
    sims = timeit.repeat(lambda: simulate_trials(trials, settings), "gc.enable()", number=1, repeat=repeat)
    name = "simulation of the 150 trials (in process)"
    rows[name] = _summary(sims)
    if on_row:
        on_row(name, rows[name])
    res = {"rows": rows, "repeat": repeat, "target_wall_s": TARGET_WALL_S,
           "meets_target": rows["protocol"]["median_s"] <= TARGET_WALL_S}
    Path(out, "bench.json").write_text(json.dumps(res, indent=1))
    return res
