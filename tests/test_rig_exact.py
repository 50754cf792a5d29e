"""The exact membrane at the edges: `equilibrium --fidelity exact`, the rig's exact free-inflation rung,
and the rig's structural mismatches (valve delay and minimum on-time, compressor-map shape, sensor lag)."""

from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.cli import app

runner = CliRunner()
E, R1, T0 = 130.6e3, 7.5e-3, 3e-3


def _eq(*args: str) -> dict:
    res = runner.invoke(app, ["equilibrium", "--json", "--fidelity", "exact", *args])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


def test_equilibrium_exact_small_deflection_matches_foppl_hencky():
    # Foppl-Hencky clamped membrane (Poisson 1/2): p = 4.75 E t0 h^3 / r1^4, independent of the shooter
    h = 0.2e-3
    out = _eq("--h1-mm", "0.2")
    assert out["pressure_kpa"] * 1e3 == pytest.approx(4.75 * E * T0 * h**3 / R1**4, rel=0.01)
    assert out["force_n"] == 0.0 and out["contact_radius_mm"] == 0.0


def test_equilibrium_exact_flat_plate_force_is_pressure_times_contact_area():
    out = _eq("--h1-mm", "5", "--h2-mm", "2", "--p-kpa", "24")
    assert out["h_mm"] == 3.0 and out["pressure_kpa"] == pytest.approx(24.0)
    a = out["contact_radius_mm"] * 1e-3
    assert 0 < a < R1
    assert out["force_n"] == pytest.approx(24e3 * math.pi * a**2, rel=1e-9)
    assert out["load_g"] == pytest.approx(out["force_n"] / 9.80665 * 1e3, rel=1e-9)


def test_equilibrium_exact_bonded_reports_the_disk_radius_as_contact_radius():
    out = _eq("--h1-mm", "3", "--contact", "bonded", "--disk-radius-mm", "2", "--p-kpa", "24")
    assert out["contact_radius_mm"] == pytest.approx(2.0)
    assert out["force_n"] > 0 and out["volume_cm3"] > 3.0


@pytest.mark.parametrize("args, needle", [
    (["--fidelity", "exact", "--contact", "bonded", "--disk-radius-mm", "9", "--p-kpa", "24"], "--disk-radius-mm = 9"),
    (["--fidelity", "exact", "--contact", "bonded"], "--p-kpa is required"),
    (["--fidelity", "exact", "--p-kpa", "10"], "--p-kpa"),
    (["--fidelity", "exakt"], "--fidelity = 'exakt'"),
    (["--contact", "bonded", "--p-kpa", "10"], "--fidelity exact"),
    (["--fidelity", "exact", "--contact", "glued", "--p-kpa", "10"], "--contact = 'glued'"),
])
def test_equilibrium_exact_bad_combination_is_one_line_exit_2(args, needle):
    res = runner.invoke(app, ["equilibrium", "--h1-mm", "3", *args])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], res.output


def test_equilibrium_exact_unreachable_height_names_the_flags():
    res = runner.invoke(app, ["equilibrium", "--h1-mm", "30", "--fidelity", "exact"])
    assert res.exit_code == 2
    assert res.output.startswith("error: --h1-mm/--h2-mm: h = 30 mm") and "mm" in res.output
