"""The reference page of scenario keys (app/schema/reference.py, ``hbma-ctrl scenario keys``): the committed
page is the generator's output, every key of every table is on it, a bad --table is one clear line."""

from __future__ import annotations

from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.schema.reference import PAGE, TABLES, markdown, table_markdown
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.core import units as U
from checkout import ROOT

runner = CliRunner()


def test_committed_page_is_the_generators_output():
    # regenerate with: python -c "from hbma_ctrl.app.schema.reference import *; open(PAGE, 'w').write(markdown())"
    assert (ROOT / PAGE).read_text() == markdown()


def test_every_key_of_every_table_is_on_its_section():
    for name, model in TABLES.items():
        section = table_markdown(name)
        assert section.startswith(f"## [{name}]\n")
        missing = [k for k in model.model_fields if f"\n| {k} |" not in section]
        assert not missing, (name, missing)
    assert set(TABLES) >= {"scenario", "actuator", "controller", "estimator", "rig", "robot", "sim", "daemon"}


def test_a_row_reads_the_settings_declaration():
    row = next(r for r in table_markdown("controller").splitlines() if r.startswith("| p_max_kpa |"))
    assert row == f"| p_max_kpa | number | kPa | (0, 1000] | {U.to_kpa(MPCSettings.p_max):g} | gauge pressure limit |"


def test_cli_prints_the_page_and_one_table():
    res = runner.invoke(app, ["scenario", "keys"])
    assert res.exit_code == 0, res.output
    assert res.stdout == markdown()
    res = runner.invoke(app, ["scenario", "keys", "--table", "daemon"])
    assert res.exit_code == 0, res.output
    assert res.stdout == table_markdown("daemon") and "## [controller]" not in res.stdout


def test_cli_bad_table_is_one_line_naming_the_tables():
    res = runner.invoke(app, ["scenario", "keys", "--table", "contrller"])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --table = 'contrller'")
    assert "did you mean 'controller'" in lines[0] and all(name in lines[0] for name in TABLES)
