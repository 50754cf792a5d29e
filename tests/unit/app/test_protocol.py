"""README Model §7 protocol: the 150-trial grid, and a small subset run end to end (serial and in workers)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from hbma_ctrl.app.scenes.protocol import SUMMARY_COLUMNS, run_protocol
from hbma_ctrl.sim.batch import protocol_trials, simulate_trials
from hbma_ctrl.sim.trial import SimSettings


def test_protocol_trials_is_the_150_trial_grid():
    trials = protocol_trials("nh")
    assert len(trials) == 150
    assert len({t.name for t in trials}) == 150
    keys = {(round(t.actuator.t0 * 1e3, 6), round(t.actuator.r1 * 1e3, 6), round(t.platform.load * 1e3, 6),
             round(t.schedule.rows[0][1] * 100, 6)) for t in trials}
    assert len(keys) == 150
    assert {k[0] for k in keys} == {2.0, 3.0}
    assert {k[1] for k in keys} == {7.5, 10.0, 12.5}
    assert {k[2] for k in keys} == {0.0, 200.0, 400.0, 600.0, 800.0}
    assert {k[3] for k in keys} == {20.0, 40.0, 60.0, 80.0, 100.0}
    assert sum(t.default_fidelity() == "free" for t in trials) == 30
    for t in trials:
        (t_a, s, i_a, o_a), (t_b, s_b, i_b, o_b) = t.schedule.rows
        assert (t_a, i_a, o_a) == (0.0, 1.0, 0.0) and s > 0  # pump with the inlet open
        assert (t_b, s_b, i_b, o_b) == (3.0, 0.0, 0.0, 1.0)  # then vent
        assert t.duration == 6.0


def test_protocol_trials_validates_grid():
    with pytest.raises(ValueError, match=r"protocol\.speeds_pct"):
        protocol_trials("nh", speeds_pct=[0.0])
    with pytest.raises(ValueError, match=r"protocol\.t_inflate_s"):
        protocol_trials("nh", t_inflate_s=7.0)
    with pytest.raises(ValueError, match="material"):
        protocol_trials("neo")


def _subset():
    return protocol_trials("nh", loads_g=[0.0, 200.0], speeds_pct=[60.0, 100.0], t0_mm=[3.0], r1_mm=[12.5],
                           t_inflate_s=1.0, duration_s=2.0)


def test_subset_run_writes_summary_and_series(tmp_path):
    trials = _subset()
    rows = run_protocol("nh", tmp_path, trials=trials, plots=False)
    with open(tmp_path / "summary.csv") as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames) == SUMMARY_COLUMNS
        got = list(reader)
    assert len(got) == len(rows) == 4
    assert [r["status"] for r in got] == ["ok"] * 4
    assert [float(r["load_g"]) for r in got] == [0.0, 0.0, 200.0, 200.0]
    assert [float(r["speed_pct"]) for r in got] == [60.0, 100.0, 60.0, 100.0]
    for r in got:
        assert float(r["thickness_mm"]) == 3.0 and float(r["radius_mm"]) == 12.5
        assert float(r["max_height_mm"]) > 0 and float(r["wall_s"]) >= 0
    # faster pump: higher; loaded: lift-off needs at least W / (pi r1^2)
    assert float(got[1]["max_height_mm"]) > float(got[0]["max_height_mm"])
    p_lift = 0.2 * 9.80665 / (math.pi * 12.5e-3**2) * 1e-3
    assert float(got[3]["max_pressure_kpa"]) >= p_lift
    for t in trials:
        with open(tmp_path / "trials" / f"{t.name}.csv") as fh:
            series = list(csv.DictReader(fh))
        assert float(series[-1]["t_s"]) == pytest.approx(2.0)
        peak = max(float(s["h_mm"]) for s in series)
        row = next(r for r in got if float(r["load_g"]) * 1e-3 == pytest.approx(t.platform.load)
                   and float(r["speed_pct"]) == pytest.approx(t.schedule.rows[0][1] * 100))
        assert peak == pytest.approx(float(row["max_height_mm"]), rel=1e-5)


@pytest.mark.subprocess
def test_workers_give_the_same_logs_as_serial():
    trials = _subset()
    s = SimSettings()
    serial = simulate_trials(trials, s, "auto", workers=1)
    parallel = simulate_trials(trials, s, "auto", workers=2)
    assert [log.name for log in parallel] == [t.name for t in trials]
    for a, b in zip(serial, parallel):
        assert a.fidelity == b.fidelity
        np.testing.assert_allclose(a["h"], b["h"], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a["p"], b["p"], rtol=1e-9, atol=1e-9)


def test_platform_fidelity_keeps_free_for_unloaded_trials():
    trials = _subset()
    logs = simulate_trials(trials, SimSettings(), "platform")
    assert [log.fidelity for log in logs] == ["free", "free", "platform", "platform"]
    with pytest.raises(ValueError, match="'free' ignores the load"):
        simulate_trials(trials, SimSettings(), "free")


def test_nrmsd_is_spec_eq16():
    from hbma_ctrl.app.metrics import nrmsd

    y = np.sin(np.linspace(0, 3, 301))  # reference
    span = y.max() - y.min()
    assert nrmsd(y + 0.01 * span, y) == pytest.approx(0.01, rel=1e-12)
    noise = np.where(np.arange(301) % 2 == 0, 1.0, -1.0) * 0.02 * span
    assert nrmsd(y + noise, y) == pytest.approx(0.02, rel=1e-12)
    assert math.isnan(nrmsd(np.zeros(5), np.zeros(5)))  # constant reference: undefined
    with pytest.raises(ValueError, match="same non-zero length"):
        nrmsd(np.zeros(3), np.zeros(4))


@pytest.mark.slow
def test_bench_sim_rows_reference_cache_and_outputs(tmp_path, monkeypatch):
    import json

    import hbma_ctrl.app.bench.sim as bench

    short = protocol_trials("nh", loads_g=[0.0, 200.0], speeds_pct=[100.0], t0_mm=[3.0], r1_mm=[12.5],
                            t_inflate_s=0.4, duration_s=0.8)
    monkeypatch.setattr(bench, "bench_trials", lambda material, quick: short)
    grid = {"quasi_static": {"euler": (2.0,), "rk4": (5.0, 10.0)}}
    rows = bench.run_bench(tmp_path, grid=grid, progress=False)
    # the explicit rk4 5 ms row equals the default (5 ms free and loaded) and is folded into it
    assert [(r.integrator, r.dt_ms) for r in rows] == [("rk4", None), ("euler", 2.0), ("rk4", 10.0)]
    assert [r.default for r in rows] == [True, False, False]
    by = {(r.integrator, r.dt_ms): r for r in rows}
    assert all(r.n_trials == 2 and r.n_diverged == 0 for r in rows)
    # rk4 beats euler on accuracy; every error is small but not exactly zero (a real comparison)
    assert 0 < by[("rk4", None)].pressure_nrmsd_max < by[("euler", 2.0)].pressure_nrmsd_max < 0.05
    data = json.loads((tmp_path / "bench.json").read_text())
    assert len(data["rows"]) == 3 and data["meta"]["reference"]["integrator"] == "radau"
    assert (tmp_path / "bench.csv").read_text().splitlines()[0].startswith("integrator,fidelity,dt_ms")
    # the cached reference is reused: no radau run the second time
    calls = []
    real = bench.simulate_trials

    def spy(trials, settings=None, *a, **k):
        calls.append(settings.integrator if settings else None)
        return real(trials, settings, *a, **k)

    monkeypatch.setattr(bench, "simulate_trials", spy)
    again = bench.reference(short, "quasi_static", tmp_path)
    assert calls == [] and set(again) == {t.name for t in short}
