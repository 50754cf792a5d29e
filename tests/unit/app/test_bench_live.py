"""``hbma-ctrl bench live``'s parts that need no daemon and no browser: the page's readings against the
run log, the results page, and its flags checked before anything runs."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.bench.live import compare_with_log
from hbma_ctrl.app.cli.main import app
from checkout import ROOT
from cli_checks import one_line_error

runner = CliRunner()
COLUMNS = ["t_s", "mode", "p_C1_kpa", "p_est_C1_kpa", "h_est_C1_mm", "h_std_C1_mm", "target_C1_mm", "speed_C1_1",
           "inlet_C1_1", "outlet_C1_1", "step_ms", "faults"]
ROWS = [[f"{0.01 * k:.4f}", "running", f"{10 + 0.01 * k:.4f}", f"{9.9 + 0.01 * k:.4f}", f"{2 + 0.001 * k:.4f}",
         "0.1000", "6.0000", "0.8765", "1.0000", "0.0000", "3.0", ""] for k in range(1, 101)]


def shown(steps: int, **over) -> dict:
    """What the page shows at ``steps`` for ROWS, with the digits it shows."""
    row = ROWS[steps - 1]
    c = {"h_mm": f"{float(row[4]):.3f}", "p_kpa": f"{float(row[2]):.2f}", "p_est_kpa": f"{float(row[3]):.2f}",
         "speed_pct": f"{100 * float(row[7]):.1f}", "inlet_duty": "1.00", "outlet_duty": "0.00"}
    c.update(over)
    return {"mode": "running", "t_s": f"{float(row[0]):.2f}", "steps": str(steps), "chambers": [c],
            "names": ["C1"], "status_steps": steps + 7}


def test_a_page_showing_the_logged_row_of_its_step_matches_and_its_lag_is_counted_in_periods():
    (c,) = compare_with_log([shown(40)], COLUMNS, ROWS)
    assert c == {"steps": 40, "matches_log": True, "differs": [], "lag_periods": 7}


def test_a_value_shown_that_is_not_the_logs_is_named():
    (c,) = compare_with_log([shown(40, p_kpa="10.50")], COLUMNS, ROWS)
    assert not c["matches_log"] and c["differs"] == ["p_kpa[0] shown 10.50, logged 10.4"]


def test_a_page_a_step_behind_its_label_does_not_match():
    s = shown(40)
    s["steps"] = "41"  # values of step 40 under the step count 41
    (c,) = compare_with_log([s], COLUMNS, ROWS)
    assert not c["matches_log"]


def test_readings_before_the_loop_runs_are_not_compared():
    s = shown(40)
    s.update(steps="-", mode="starting")
    assert compare_with_log([s], COLUMNS, ROWS) == []


def _fake_result(config: str) -> dict:
    daemon = {"steps": 6000, "deadline_misses": 3, "overruns": 1, "step_ms_median": 2.5, "step_ms_p99": 7.25,
              "tick_ms_p99": 6.0, "jitter_ms_p99": 0.5, "faults": {}}
    run = lambda client: {"client": client, "daemon": daemon, "period_ms": 10.0, "daemon_cpu_s": 40.0,  # noqa: E731
                          "client_error": None}
    page = {**run("page"), "rate_hz": 5.0, "every_steps": 20, "samples": 60, "compared": 58, "matching_log": 58,
            "differences": [], "lag_periods_median": 12.0, "lag_periods_max": 21.0, "within_one_decimation_period": 58,
            "browser_cpu_s": 3.5, "browser_wall_s": 59.0}
    return {"config": config, "duration_s": 60.0, "rate_hz": 5.0, "sample_every_s": 1.0,
            "runs": {"without_page": run("none"), "stream_only": {**run("stream"), "events": 300}, "with_page": page},
            "verdicts": {"no_deadline_miss_added": True, "page_matches_log": True,
                         "page_within_one_decimation_period": True, "no_fault": True}}


def test_bench_live_writes_its_page_with_the_three_runs_and_the_verdicts(tmp_path, monkeypatch):
    import hbma_ctrl.app.bench.live as live

    config = str(ROOT / "scenarios" / "daemon_chamber.toml")
    monkeypatch.setattr(live, "run_live_bench", lambda *a, **k: _fake_result(config))
    rep = tmp_path / "results"
    res = runner.invoke(app, ["bench", "live", config, "--duration-s", "60", "--out", str(tmp_path / "o"),
                              "--report", str(rep)])
    assert res.exit_code == 0, res.output
    text = (rep / "live.md").read_text()
    assert "| page_matches_log | yes |" in text
    assert "| without page | 6000 | 3 | 1 | 2.5 | 7.25 | 6 | 0.5 | 40 | - | none |" in text
    assert "| with page | 6000 | 3 | 1 | 2.5 | 7.25 | 6 | 0.5 | 40 | 3.5 | none |" in text
    assert "| 5 | 20 | 60 | 58 | 58 | 12 | 21 | 58/58 |" in text
    assert "](live.md)" in (rep / "index.md").read_text()


@pytest.mark.parametrize("args,needle", [(["--rate-hz", "100"], "--rate-hz"), (["--duration-s", "0"], "--duration-s"),
                                         (["--sample-every-s", "-1"], "--sample-every-s"),
                                         (["--browser-nice", "20"], "--browser-nice")])
def test_bench_live_refuses_a_bad_flag_before_running(tmp_path, args, needle):
    res = runner.invoke(app, ["bench", "live", str(ROOT / "scenarios" / "daemon_chamber.toml"), *args,
                              "--out", str(tmp_path / "o")])
    one_line_error(res, needle)
    assert not (tmp_path / "o").exists()
