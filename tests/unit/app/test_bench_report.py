"""The benches' results pages (``hbma-ctrl bench <sub> --report DIR``): the writer's sections from a small
fake result, the index, a real bench writing its page and figure, and an unusable ``--report``."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.bench.report import Page, Pareto, Report, Table, docstring_paragraph
from hbma_ctrl.app.cli.main import app
from checkout import ROOT
from cli_checks import one_line_error

runner = CliRunner()


def _fake_page() -> Page:
    pts = [("a", ("fast", ""), 1.0, 0.3), ("b", ("slow", ""), 3.0, 0.1), ("c", ("slow", ""), 4.0, 0.2)]
    return Page("Fake bench", "It measures nothing against a made-up truth.",
                [Table("two variants", ["variant", "h (mm)", "step (ms)", "step / a"],
                       [["a", "0.3", "1", "1x"], ["b", "0.1", "3", "3x"]])],
                [Pareto("fake_pareto", "fake: step vs error", "step (ms)", [("height error (mm)", pts)])],
                ["a note"])


def test_page_from_a_fake_result_has_every_section_and_its_figure(tmp_path):
    page = Report(tmp_path, "sim", ["bench", "sim", "--quick", "--report", "docs/results"]).write(_fake_page())
    text = page.read_text()
    for heading in ("# Fake bench", "## What is measured", "## Command", "## Machine", "## Results"):
        assert re.search(rf"^{re.escape(heading)}$", text, re.M), heading
    assert "It measures nothing against a made-up truth." in text
    assert "hbma-ctrl bench sim --quick --report docs/results" in text
    for key in ("CPU", "cores", "Python", "casadi", "osqp", "load average at start"):
        assert f"| {key}" in text, key
    assert "| variant | h (mm) | step (ms) | step / a |" in text
    assert re.search(r"^Measured on \d{4}-\d{2}-\d{2} \(UTC\)", text, re.M)
    for name in ("fake_pareto.png", "fake_pareto.svg"):
        assert (tmp_path / name).stat().st_size > 0
        assert f"]({name})" in text
    assert "step (ms)" in (tmp_path / "fake_pareto.svg").read_text()  # the axis label, kept as text


def test_the_command_block_is_marked_not_run_for_the_docs_test(tmp_path):
    text = Report(tmp_path, "sim", ["bench", "sim"]).write(_fake_page()).read_text()
    assert "<!-- docs: not run: " in text.split("```bash")[0].splitlines()[-1]


def test_index_lists_every_page_present_with_its_date_in_bench_order(tmp_path):
    for sub in ("mpc", "sim"):
        Report(tmp_path, sub, ["bench", sub]).write(_fake_page())
    rows = [ln for ln in (tmp_path / "index.md").read_text().splitlines() if ln.startswith("| [")]
    assert [re.search(r"\]\((\w+)\.md\)", r).group(1) for r in rows] == ["sim", "mpc"]
    assert all(re.search(r"\| \d{4}-\d{2}-\d{2} \|$", r) for r in rows)


def test_docstring_paragraph_turns_rest_roles_and_literals_into_code():
    doc = "Title.\n\nUses :func:`hbma_ctrl.x.f`, :class:`~hbma_ctrl.y.C` and ``z``\n  over two lines.\n"
    assert docstring_paragraph(doc, 1) == "Uses `hbma_ctrl.x.f`, `C` and `z` over two lines."


@pytest.mark.parametrize("where", ["file", "file/below"])
def test_report_into_an_unwritable_place_is_one_error_naming_report(tmp_path, where):
    (tmp_path / "file").write_text("not a folder")
    res = runner.invoke(app, ["bench", "robot", "--layers", "1", "--duration", "0.5", "--out", str(tmp_path / "o"),
                              "--report", str(tmp_path / where)])
    one_line_error(res, "--report", str(tmp_path / where))
    assert not (tmp_path / "o").exists()  # refused before any work


@pytest.mark.slow
def test_bench_mpc_at_tiny_size_writes_its_page_and_pareto_figure(tmp_path):
    rep = tmp_path / "results"
    res = runner.invoke(app, ["bench", "mpc", "--variants", "rti_osqp", "--horizons", "5,10", "--no-baselines",
                              "--no-dompc", "--duration", "0.5", "--out", str(tmp_path / "o"), "--report", str(rep)])
    assert res.exit_code == 0, res.output
    text = (rep / "mpc.md").read_text()
    assert "--horizons 5,10" in text and "| rti_osqp N=10 |" in text
    assert (rep / "mpc_pareto.png").stat().st_size > 0 and (rep / "mpc_pareto.svg").stat().st_size > 0
    assert "](mpc.md)" in (rep / "index.md").read_text()
    assert (tmp_path / "o" / "bench_mpc.json").is_file()


def _fake_api_result(config: str) -> dict:
    lat = {"n": 20, "unanswered": 0, "median_ms": 1.5, "p99_ms": 4.0, "max_ms": 4.5, "within_period": 20}
    daemon = {"steps": 6000, "deadline_misses": 2, "overruns": 1, "step_ms_p99": 3.25, "faults": []}
    run = lambda n: {"clients": n, "daemon": daemon, "requests_per_s": 850.0 if n else 0.0,  # noqa: E731
                     "stop_latency": lat, "final_stop": {"status": 200}, "period_ms": 10.0}
    return {"config": config, "duration_s": 60.0, "clients": 100, "probe_every_s": 0.05,
            "runs": {"quiet": run(0), "loaded": run(100)},
            "verdicts": {"no_deadline_miss_added": True, "stop_within_a_period": True, "no_fault": True}}


def test_bench_api_writes_its_page_with_both_runs_and_the_verdicts(tmp_path, monkeypatch):
    import hbma_ctrl.app.bench.api as api

    config = str(ROOT / "scenarios" / "daemon_chamber.toml")
    monkeypatch.setattr(api, "run_api_bench", lambda *a, **k: _fake_api_result(config))
    rep = tmp_path / "results"
    res = runner.invoke(app, ["bench", "api", config, "--duration-s", "60", "--out", str(tmp_path / "o"),
                              "--report", str(rep)])
    assert res.exit_code == 0, res.output
    text = (rep / "api.md").read_text()
    assert f"--out {tmp_path / 'o'} --report {rep}" in text
    assert "| no_deadline_miss_added | yes |" in text
    assert "| quiet | 0 | 0 | 6000 | 2 | 1 | 3.25 | 20/20 | 1.5 | 4 | 4.5 | none |" in text
    assert "| loaded | 100 | 850 |" in text
    assert "](api.md)" in (rep / "index.md").read_text()


def test_the_ekf_page_states_the_mhe_summary_and_do_mpcs_ratio_or_why_it_is_missing():
    from hbma_ctrl.app.bench.pages import _ekf_summary

    sm = {"mhe_step_us_median": 63.4, "mhe_step_us_p99": 149.0, "dompc_mhe_step_us_median": 1.72e6,
          "dompc_compare_mhe_step_us_median": 65.6, "dompc_mhe_over_mhe_speed": 26210.0, "dompc_steps": 150,
          "dompc_vs_mhe_pressure_rms_pa": 376.0}
    lines = _ekf_summary({"summary": sm})
    assert "median 63.4 us, p99 149 us" in lines[0]
    assert "1720 ms per step against 65.6 us, 26,210x" in lines[1] and "376 Pa RMS" in lines[1]
    missing = _ekf_summary({"summary": {"mhe_step_us_median": 1.0, "mhe_step_us_p99": 2.0,
                                        "dompc": "do-mpc is not installed"}})
    assert missing[1] == "do-mpc's MHE: not measured (do-mpc is not installed)."
    assert _ekf_summary({"summary": {}}) == []
