"""hbma-ctrl fit --contact bonded: lift points of a disk glued at the membrane's centre. The truth is the exact
solver itself at twice the fit table's discretisation, evaluated at the data points (not the table the fit
interpolates), with noise on height, force and pressure; the geometry is a lift rig's (35 mm clamp, 2 mm
membrane, 25.4 mm disk). The first use builds the fit's table for that geometry (about a minute, then
cached): those tests are slow. Bad options are refused in one line before any table is built."""

from __future__ import annotations

import numpy as np
import pytest
from cli_checks import one_line_error
from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.tuning import fit as F
from hbma_ctrl.app.tuning.fit_bonded import BondedLaw
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import make_material
from hbma_ctrl.core.params import Actuator
from hbma_ctrl.models.exact import ExactMembrane
from hbma_ctrl.robot.statics import bonded_table

runner = CliRunner()
R1, T0, C = U.mm(35.0), U.mm(2.0), U.mm(12.7)
E_TRUE = 95e3  # 27 % below the table's default modulus: the fit scales the table, it never sits on it


def lift_points(E: float = E_TRUE, n_steps: int = 320) -> np.ndarray:
    """Rows (h m, p Pa, F N) of the exact bonded solver at n_steps (the fit's table: 160) where the disk is
    pushed up (F >= 0): heights 1-20 mm, pressures 1-8 kPa."""
    m = ExactMembrane(make_material("nh", E=E), R1, T0, "bonded", C, n_steps=n_steps)
    rows = []
    for h in U.mm(np.linspace(1.0, 20.0, 6)):
        for p in U.kpa(np.linspace(1.0, 8.0, 6)):
            try:
                r = m.contact(h, p)
            except ValueError:  # beyond the solver's reach: a rig cannot hold it either
                continue
            if r["F"] >= 0:
                rows.append((h, p, r["F"]))
    return np.array(rows)


def noisy(pts: np.ndarray, seed: int) -> F.StaticData:
    """The points read by a rig: height +-0.1 mm, force 1 % + 0.02 N, pressure 0.05 kPa (one sigma)."""
    g = np.random.default_rng(seed)
    n = len(pts)
    h = np.abs(pts[:, 0] + U.mm(0.1) * g.standard_normal(n))
    force = np.abs(pts[:, 2] * (1 + 0.01 * g.standard_normal(n)) + 0.02 * g.standard_normal(n))
    p = np.abs(pts[:, 1] + U.kpa(0.05) * g.standard_normal(n))
    return F.StaticData(h, p, force, "F_n")


@pytest.fixture(scope="module")
def truth() -> np.ndarray:
    return lift_points()


def _csv(path, data: F.StaticData) -> None:
    rows = "".join(f"{U.to_mm(h):.4f},{f:.5f},{U.to_kpa(p):.5f}\n" for h, p, f in zip(data.h, data.p, data.F))
    path.write_text("# a lift rig: disk 25.4 mm glued at the centre\nh_mm,F_n,p_kpa\n" + rows)


def test_bonded_table_on_a_small_grid_is_built_once_then_read_from_the_cache(tmp_path):
    act = Actuator(r1=R1, t0=T0, material=make_material("nh"))
    h, p = U.mm(np.array([2.0, 4.0])), U.kpa(np.array([0.0, 3.0]))
    first = bonded_table(act, C, tmp_path, h=h, p=p)
    again = bonded_table(act, C, tmp_path, h=h, p=p)
    assert first["build_s"] > 0 and again["build_s"] == 0.0 and again["path"] == first["path"]
    np.testing.assert_array_equal(first["F"], again["F"])
    # another disk is another table
    assert bonded_table(act, U.mm(10.0), tmp_path, h=h, p=p)["path"] != first["path"]


@pytest.mark.slow
def test_bonded_fit_recovers_the_finer_solvers_modulus_within_2_percent_over_noise_seeds(truth):
    for seed in range(4):
        res = F.fit_static(noisy(truth, seed), "nh", R1, T0, "bonded", fidelity="exact", disk_radius=C)
        assert abs(res.params["E"] / E_TRUE - 1) < 0.02, (seed, res.params)
        assert res.nrmsd <= 0.035, (seed, res.nrmsd)
        assert res.contact == "bonded" and res.disk_radius == C


@pytest.mark.slow
def test_bonded_law_matches_the_finer_solver_at_its_own_points(truth):
    law = BondedLaw(R1, T0, C, truth[:, 0], truth[:, 2])
    p = law.pressure(np.array([E_TRUE]))
    assert np.all(np.abs(p - truth[:, 1]) < 1e-3 * truth[:, 1].max())
    assert BondedLaw(R1, T0, C, truth[:, 0], truth[:, 2]).build_s == 0.0  # the second use reads the cache


@pytest.mark.slow
def test_a_point_beyond_the_solvers_reach_is_refused_by_its_row_not_fitted_around(truth):
    # 20 N at 2 mm needs a pressure past what the annulus holds: the fit must not move E to reach it
    d = np.vstack([truth, [U.mm(2.0), U.kpa(10.0), 20.0]])
    with pytest.raises(ValueError, match=rf"row {len(d)}: h 2 mm with a force of 20 N is beyond"):
        F.fit_static(F.StaticData(d[:, 0], d[:, 1], d[:, 2], "F_n"), "nh", R1, T0, "bonded", fidelity="exact",
                     disk_radius=C)


@pytest.mark.slow
def test_cli_fits_load_g_lift_data_and_writes_the_disk_into_params_toml(tmp_path, truth):
    d = noisy(truth, 7)
    rows = "".join(f"{U.to_mm(h):.4f},{U.to_grams(f / U.G_STD):.3f},{U.to_kpa(p):.5f}\n"
                   for h, p, f in zip(d.h, d.p, d.F))
    path = tmp_path / "lift.csv"
    path.write_text("h_mm,load_g,p_kpa\n" + rows)
    out = tmp_path / "fit"
    res = runner.invoke(app, ["fit", str(path), "--contact", "bonded", "--disk-radius-mm", "12.7", "--r1-mm", "35",
                              "--t0-mm", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "bonded contact (disk 12.7 mm)" in " ".join(res.output.split())
    import json
    import tomllib

    fit = json.loads((out / "fit.json").read_text())
    lo, hi = fit["ci95"]["E"]
    assert lo < fit["params"]["E"] < hi and abs(fit["params"]["E"] / E_TRUE - 1) < 0.02
    text = (out / "params.toml").read_text()
    assert "disk_radius_mm = 12.7" in text and tomllib.loads(text)["actuator"]["material"] == "nh"


def test_bonded_fit_python_api_refuses_a_disk_outside_the_clamp():
    d = F.StaticData(U.mm(np.array([1.0, 2.0])), U.kpa(np.array([2.0, 3.0])), np.array([1.0, 1.0]), "F_n")
    with pytest.raises(ValueError, match=r"--disk-radius-mm 40 is out of range \(0, 35\) mm"):
        F.fit_static(d, "nh", R1, T0, "bonded", fidelity="exact", disk_radius=U.mm(40.0))


LIFT = "h_mm,F_n,p_kpa\n2,3.0,3.0\n4,2.0,3.5\n6,1.0,4.0\n"
GEOM = ["--r1-mm", "35", "--t0-mm", "2"]


@pytest.mark.parametrize("args,needles", [
    (["--contact", "bonded", "--disk-radius-mm", "0"], ["--disk-radius-mm 0 is out of range (0, 35) mm"]),
    (["--contact", "bonded", "--disk-radius-mm", "35"], ["--disk-radius-mm 35 is out of range (0, 35) mm"]),
    (["--contact", "bonded", "--disk-radius-mm", "-3"], ["--disk-radius-mm -3 is out of range"]),
    (["--contact", "bonded", "--disk-radius-mm", "nan"], ["--disk-radius-mm nan is out of range"]),
    (["--contact", "bonded"], ["--contact bonded needs --disk-radius-mm", "(0, 35)"]),
    (["--contact", "flat", "--disk-radius-mm", "12.7"], ["--disk-radius-mm: only with --contact bonded"]),
    (["--contact", "bonded", "--disk-radius-mm", "12.7", "--fidelity", "cap"],
     ["--contact bonded", "exact membrane's law only", "drop --fidelity cap"]),
    (["--contact", "bonded", "--disk-radius-mm", "12.7", "--material", "mr"],
     ["--contact bonded", "--material nh or gent only", "C1, C2"]),
    (["--contact", "bonded", "--disk-radius-mm", "12.7", "--material", "gent", "--fix", "Jm=5"],
     ["--fix Jm=5", "outside the physical range [10, 1e+06]"]),
    (["--contact", "bonded", "--disk-radius-mm", "12.7", "--write-scenario", "s.toml"],
     ["--write-scenario", "no glued disk", "params.toml"]),
    (["--contact", "bondet", "--disk-radius-mm", "12.7"], ["--contact bondet", "did you mean 'bonded'"]),
    (["--contact", "flat", "--keep-beyond-reach"], ["--keep-beyond-reach: only with --contact bonded"]),
])
def test_bad_bonded_options_are_one_error_line(tmp_path, args, needles):
    path = tmp_path / "lift.csv"
    path.write_text(LIFT)
    one_line_error(runner.invoke(app, ["fit", str(path), "--out", str(tmp_path / "o"), *GEOM, *args]), *needles)
    assert not (tmp_path / "o").exists() and not (tmp_path / "s.toml").exists()


if __name__ == "__main__":
    # the measurement behind docs/how-to/fit-bonded.md: PYTHONPATH=.:tests python tests/unit/app/test_fit_bonded.py
    pts = lift_points()
    for seed in range(10):
        d = noisy(pts, seed) if seed else F.StaticData(pts[:, 0], pts[:, 1], pts[:, 2], "F_n")
        res = F.fit_static(d, "nh", R1, T0, "bonded", fidelity="exact", disk_radius=C)
        lo, hi = res.ci95["E"]
        print(f"{'noise seed ' + str(seed) if seed else 'noiseless':>13}: {len(pts)} points, E {res.params['E']:.0f} Pa "
              f"(error {res.params['E'] / E_TRUE - 1:+.4f}, 95 % [{lo:.0f}, {hi:.0f}]), pressure NRMSD {res.nrmsd:.4f}")
