"""Defects a hostile probe of the CLI found: each is one line 'error: ...' naming what was given, no
traceback, nothing written silently."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from checkout import ROOT
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.outputs import MAX_PATH_BYTES

FIG7 = ROOT / "scenarios" / "open_loop_fig7.toml"
runner = CliRunner()


def _one_line(res, code: int = 2) -> str:
    assert res.exit_code == code, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in res.output, res.output
    return lines[0]


def test_a_megabyte_scenario_name_is_refused_with_a_short_line_naming_the_key(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(f'[scenario]\nname = "{"x" * 1_000_000}"\nduration_s = 6.0\n')
    line = _one_line(runner.invoke(app, ["run", str(p), "--out", str(tmp_path / "o")]))
    assert "[scenario] name" in line and "1000000 characters long" in line and len(line) < 300


def test_an_out_path_longer_than_the_system_takes_is_one_error_naming_out(tmp_path):
    deep = tmp_path.joinpath(*(["d" * 200] * (MAX_PATH_BYTES // 200 + 2)))
    line = _one_line(runner.invoke(app, ["run", str(FIG7), "--out", str(deep)]))
    assert line.startswith("error: --out ") and "bytes long" in line and len(line) < 300


def test_copy_to_a_place_no_file_can_be_written_names_to(tmp_path):
    # a path under a regular file: no folder there, for root as for anyone
    (tmp_path / "f").write_text("x")
    line = _one_line(runner.invoke(app, ["scenarios", "copy", "open_loop_fig7", "--to", str(tmp_path / "f" / "x.toml")]))
    assert "--to" in line


def test_copy_write_error_is_one_line_naming_to(tmp_path, monkeypatch):
    import hbma_ctrl.app.shipped as shipped

    def refuse(src, dst):
        raise PermissionError(13, "Permission denied", str(dst))

    monkeypatch.setattr(shipped.shutil, "copyfile", refuse)
    line = _one_line(runner.invoke(app, ["scenarios", "copy", "open_loop_fig7", "--to", str(tmp_path)]))
    assert "--to" in line and "Permission denied" in line


def test_an_os_error_no_command_turned_into_a_message_is_one_line_without_traceback(tmp_path, monkeypatch):
    import hbma_ctrl.app.cli.scenario as scen

    def boom(*a, **k):
        raise IsADirectoryError(21, "Is a directory", str(tmp_path / ("y" * 300)))

    monkeypatch.setattr(scen, "copy", boom)
    monkeypatch.setattr("hbma_ctrl.app.shipped.copy_scenario", boom)
    line = _one_line(runner.invoke(app, ["scenarios", "copy", "open_loop_fig7", "--to", str(tmp_path)]))
    assert "Is a directory" in line and len(line) < 200


def test_export_of_a_log_holding_no_message_is_an_error_not_an_empty_success(tmp_path):
    run = tmp_path / "r"
    run.mkdir()
    (run / "log.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 64)
    line = _one_line(runner.invoke(app, ["export", str(run)]))
    assert "log.mcap" in line and "no message" in line


def test_overwrite_refuses_a_run_directory_holding_files_its_run_did_not_write(tmp_path):
    from hbma_ctrl.app.outputs import check_out, foreign_entries, run_dir

    run = tmp_path / "run"
    with run_dir(run, command="t", argv=[]) as tmp:
        (tmp / "a.csv").write_text("1\n")
        (tmp / "figs").mkdir()
        (tmp / "figs" / "f.png").write_bytes(b"x")
    assert foreign_entries(run) == []
    check_out(run, overwrite=True)  # the run alone: replaced
    (run / "mydata").mkdir()
    (run / "mydata" / "big.csv").write_text("years of work\n")
    with pytest.raises(ValueError, match="--out.*'mydata' and 1 more.*did not write"):
        check_out(run, overwrite=True)
    assert (run / "mydata" / "big.csv").read_text() == "years of work\n"


def test_write_scenario_where_no_file_can_be_written_names_the_flag(tmp_path):
    from types import SimpleNamespace

    from hbma_ctrl.app.tuning import fit_output

    (tmp_path / "f").write_text("x")
    target = tmp_path / "f" / "s.toml"  # under a regular file: no folder there
    res = SimpleNamespace(material="nh")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit_output, "scenario_tables", lambda result, law: {})
        mp.setattr(fit_output, "_keep_rig", lambda base, data: None)
        mp.setattr(fit_output, "parse_scenario", lambda data, path: None)
        with pytest.raises(ValueError, match=r"^--write-scenario .*s\.toml: cannot write it"):
            fit_output.write_scenario(target, res, "exact")


@pytest.mark.parametrize("argv, needle", [
    (["observability", "--r1-mm", "-1"], "--r1-mm = -1 is out of range (0.5, 100] mm"),
    (["observability", "--t0-mm", "nan"], "--t0-mm = nan is out of range (0.05, 20] mm"),
    (["robot", "table2", "--layers", "0"], "--layers = 0 is out of range [1, 26]"),
    (["robot", "workspace", "--layers", "-1"], "--layers = -1 is out of range [1, 26]"),
    (["robot", "workspace", "--max-stretch", "1"], "--max-stretch = 1 is out of range [1.05, 20]"),
    (["robot", "pose", "--heights-mm", "-5,5,5"], "--heights-mm: chamber heights must be >= 0 mm; A1 = -5 mm"),
    (["robot", "pose", "--centre-mm", "-5"], "--centre-mm = -5 is out of range (0, 200] mm"),
    (["robot", "pose", "--centre-mm", "5", "--direction-deg", "nan"], "--direction-deg = nan is out of range"),
    (["robot", "pose", "--heights-mm", "5,5,5", "--pressure-limit-kpa", "0"], "--pressure-limit-kpa = 0 is out of range"),
])
def test_a_flag_out_of_range_is_named_as_written_in_its_unit(tmp_path, argv, needle):
    line = _one_line(runner.invoke(app, [*argv, "--out", str(tmp_path / "o")]))
    assert needle in line
    assert not (tmp_path / "o").exists()


def test_a_seed_range_of_a_hundred_million_is_refused_before_it_is_built():
    from hbma_ctrl.app.tuning.tune import MAX_SEEDS, parse_seeds

    with pytest.raises(ValueError, match=r"^--train-seeds = '0-99999999': more than 1000 seeds"):
        parse_seeds("0-99999999", "--train-seeds")
    assert len(parse_seeds(f"0-{MAX_SEEDS - 1}", "--train-seeds")) == MAX_SEEDS
    with pytest.raises(ValueError, match="at most 1000"):
        parse_seeds(f"0-{MAX_SEEDS - 1},5000", "--train-seeds")


def test_a_data_column_given_twice_is_refused_naming_it():
    from hbma_ctrl.app.tuning.run_data import data_rows

    with pytest.raises(ValueError, match="^data: column 'h_mm' appears 2 times in the header"):
        data_rows(b"h_mm,h_mm,p_kpa\n2,2,0.5\n", "h_mm,p_kpa")


@pytest.mark.parametrize("col, value, needle", [
    ("load_g", "1e9", "column 'load_g', row 1: 1e+09 g is out of range [0, 50000] g"),
    ("F_n", "1e6", "column 'F_n', row 1: 1e+06 N is out of range [0, 490.332] N"),
])
def test_a_static_load_beyond_any_rig_is_refused_naming_its_column(col, value, needle):
    from hbma_ctrl.app.tuning.fit import parse_data

    with pytest.raises(ValueError) as err:
        parse_data(f"h_mm,p_kpa,{col}\n2,0.5,{value}\n4,3,1\n".encode())
    assert needle in str(err.value)


def test_report_and_export_never_replace_a_users_file_in_an_explicit_out_and_overwrite_still_replaces_the_run(
        tmp_path, monkeypatch):
    import hbma_ctrl.app.logs.export as export_mod
    import hbma_ctrl.app.report.figures as figures
    from hbma_ctrl.app.outputs import check_out, run_dir

    def fake_figures(run, out):
        (Path(out) / "tracking.png").write_bytes(b"figure")
        return [Path(out) / "tracking.png"]

    def fake_tables(log, out, fmt):
        (Path(out) / "readings.csv").write_text("t_s\n0\n")
        return [Path(out) / "readings.csv"]

    monkeypatch.setattr(figures, "report", fake_figures)
    monkeypatch.setattr(export_mod, "export_log", fake_tables)
    run = tmp_path / "run"
    with run_dir(run, command="t", argv=[]) as tmp:
        (tmp / "log.mcap").write_bytes(b"x")
    user = tmp_path / "user"
    user.mkdir()
    (user / "tracking.png").write_text("my own figure")
    (user / "readings.csv").write_text("my own table")
    for cmd, name in (("report", "tracking.png"), ("export", "readings.csv")):
        line = _one_line(runner.invoke(app, [cmd, str(run), "--out", str(user)]))
        assert f"--out {user}: holds '{name}', which {cmd} did not write" in line
    assert (user / "tracking.png").read_text() == "my own figure"
    assert (user / "readings.csv").read_text() == "my own table"
    for _ in range(2):  # the default folders, twice: their own files are replaced
        assert runner.invoke(app, ["report", str(run)]).exit_code == 0
        assert runner.invoke(app, ["export", str(run)]).exit_code == 0
    assert (run / "figures" / "tracking.png").read_bytes() == b"figure"
    check_out(run, overwrite=True)  # the figures and tables are the package's: the run is still replaceable
    (run / "figures" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="figures/notes.txt"):
        check_out(run, overwrite=True)
    assert not list(tmp_path.glob(".*tmp-*"))


def test_rig_emulate_link_never_replaces_a_users_file_or_folder(tmp_path):
    thesis = tmp_path / "thesis.tex"
    thesis.write_text("years of work")
    (tmp_path / "adir").mkdir()
    for target in (thesis, tmp_path / "adir"):
        line = _one_line(runner.invoke(app, ["rig", "emulate", "--link", str(target)]))
        assert f"--link {target}: exists and is not a symlink" in line
    line = _one_line(runner.invoke(app, ["rig", "emulate", "--link", str(tmp_path / "no" / "x")]))
    assert "--link" in line and "does not exist" in line
    assert thesis.read_text() == "years of work" and (tmp_path / "adir").is_dir()


def test_rig_emulate_truth_log_never_truncates_a_users_file(tmp_path):
    thesis = tmp_path / "thesis.csv"
    thesis.write_text("a,b\n1,2\n")
    cfg = ROOT / "scenarios" / "daemon_chamber.toml"
    line = _one_line(runner.invoke(app, ["rig", "emulate", "--config", str(cfg), "--truth-log", str(thesis)]))
    assert f"--truth-log {thesis}: exists and is not a truth log" in line
    assert thesis.read_text() == "a,b\n1,2\n"


@pytest.mark.parametrize("name", ["index.md", "sim.md"])
def test_bench_report_never_replaces_a_users_page_of_the_same_name(tmp_path, name):
    from hbma_ctrl.app.bench.report import open_report

    (tmp_path / name).write_text("# My own notes\n")
    with pytest.raises(ValueError, match=f"--report {tmp_path}: holds {name}, which no bench wrote"):
        open_report(tmp_path, "sim", ["bench", "sim"])
    assert (tmp_path / name).read_text() == "# My own notes\n"


def test_bench_report_rewrites_its_own_pages(tmp_path):
    from hbma_ctrl.app.bench.report import open_report, write_index

    (tmp_path / "sim.md").write_text("# Simulator\n\nMeasured on 2026-01-01 (UTC) by `hbma-ctrl bench sim`\n")
    write_index(tmp_path)
    assert open_report(tmp_path, "sim", ["bench", "sim"]) is not None


def test_a_journal_storage_that_is_a_users_text_file_is_refused_naming_storage_and_left_as_it_is(tmp_path):
    from hbma_ctrl.app.tuning.tune import make_storage

    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    for text in ("my notes\n", "my notes\nline two\n", '{"a": 1}\n'):
        notes.write_text(text)
        with pytest.raises(ValueError, match=rf"^--storage journal:{notes}: {notes} is not an optuna journal"):
            make_storage(f"journal:{notes}")
        assert notes.read_text() == text
    with pytest.raises(ValueError, match="is not an optuna journal"):
        make_storage(f"journal:{tmp_path}")
    make_storage(f"journal:{tmp_path / 'new.journal'}")  # a new file: fine


def test_overlapping_seed_ranges_count_their_common_seeds_once_against_the_cap():
    from hbma_ctrl.app.tuning.tune import MAX_SEEDS, parse_seeds

    assert parse_seeds(f"0-{MAX_SEEDS - 1},0-5,7", "--train-seeds") == list(range(MAX_SEEDS))
    with pytest.raises(ValueError, match="at most 1000"):
        parse_seeds(f"0-{MAX_SEEDS - 2},{MAX_SEEDS - 1}-{MAX_SEEDS}", "--train-seeds")
