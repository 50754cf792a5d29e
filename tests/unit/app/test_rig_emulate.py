"""``hbma-ctrl rig emulate``'s flag checks (the emulated boards themselves: tests/integration/test_firmware.py)."""

from __future__ import annotations

from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app


def test_rig_emulate_refuses_an_unknown_target_or_chamber_count():
    res = CliRunner().invoke(app, ["rig", "emulate", "--target", "arm"])
    assert res.exit_code == 2 and "--target = 'arm'" in res.output
    res = CliRunner().invoke(app, ["rig", "emulate", "--target", "avr", "--n", "5"])
    assert res.exit_code == 2 and "--n = 5" in res.output
