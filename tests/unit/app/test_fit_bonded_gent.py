"""hbma-ctrl fit --contact bonded --material gent: a stiffening membrane glued to a disk, its mu and Jm fitted
through tables on a grid in 1 / Jm; and the rule for rows at h = 0 (the disk resting on its stop).

The truth of the law's test is the exact solver itself at a Jm between the tables' nodes. The data set is
public lift data (tests/data/spa_design, MIT: Campbell et al., SPA_Design): a 2 mm Ecoflex 00-30 membrane
in a 70 mm clamp lifting 1.5, 2.5 and 4 kg with a 25.4 mm disk. Its first use builds the geometry's tables
(one nh table, about a minute, and seven Gent ones, about two minutes each; then cached): a quarter of an
hour on a clean machine, so these tests are in the by-hand set (``pytest -m sweep``), not the CI run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hbma_ctrl.app.metrics import nrmsd
from hbma_ctrl.app.tuning import fit as F
from hbma_ctrl.app.tuning.fit_bonded import GENT_U, BondedLaw
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import make_material
from hbma_ctrl.models.exact import ExactMembrane

DATA = Path(__file__).resolve().parents[2] / "data" / "spa_design" / "ringless_lift.csv"
R1, T0, C = U.mm(70.0), U.mm(2.0), U.mm(25.4)
#: the pressure NRMSD the Gent fit reaches on the shipped data (measured 0.1567: see the __main__ block);
#: the data's floor is 0.080 (:func:`floor_nrmsd`), so the 0.035 asked of this data set is out of reach
NRMSD_REACHED = 0.158


def spa_data() -> F.StaticData:
    return F.parse_data(DATA.read_bytes())


def floor_nrmsd(d: F.StaticData) -> float:
    """The pressure NRMSD of the best single-valued p(h, F) through the data: each load's mean pressure at
    each of its heights (the heights are whole millimetres), a resting row (h = 0) missing by nothing."""
    best = d.p.copy()
    lifted = d.h > 0
    for key in set(zip(d.F[lifted].tolist(), d.h[lifted].tolist())):
        k = lifted & (d.F == key[0]) & (d.h == key[1])
        best[k] = d.p[k].mean()
    return nrmsd(best, d.p)


@pytest.mark.slow
@pytest.mark.sweep
def test_gent_law_between_its_tables_matches_the_exact_solver():
    mu, Jm = 30e3, 35.0  # 1 / Jm between two nodes of the grid, mu 31 % below the tables' modulus
    assert not np.any(np.isclose(GENT_U, 1 / Jm))
    m = ExactMembrane(make_material("gent", mu=mu, Jm=Jm), R1, T0, "bonded", C)
    rows = []
    for h in U.mm(np.array([5.0, 20.0, 40.0, 60.0])):
        for p in U.kpa(np.array([2.0, 3.0, 4.0])):
            r = m.contact(h, p)
            if r["F"] > 0:
                rows.append((h, p, r["F"]))
    pts = np.array(rows)
    assert len(pts) >= 8
    law = BondedLaw(R1, T0, C, pts[:, 0], pts[:, 2], material="gent")
    p = law.pressure(np.array([mu, Jm]))
    assert not law.beyond(np.array([mu, Jm])).any()
    # measured: 3e-4 of the pressure at most (1e-3 at Jm 28, next to the reach)
    assert np.all(np.abs(p - pts[:, 1]) < 3e-3 * pts[:, 1]), np.abs(p - pts[:, 1]) / pts[:, 1]


@pytest.mark.slow
@pytest.mark.sweep
def test_a_resting_row_misses_only_by_its_pressure_above_lift_off():
    h, F_n = np.zeros(2), np.array([14.715, 14.715])
    lift = BondedLaw(R1, T0, C, h, F_n).pressure(np.array([90e3]))[0]  # no data pressures: the lift-off one
    assert U.kpa(0.5) < lift < U.kpa(5.0)
    p = np.array([0.5 * lift, 1.5 * lift])
    law = BondedLaw(R1, T0, C, h, F_n, p=p)
    np.testing.assert_allclose(law.pressure(np.array([90e3])), [0.5 * lift, lift])
    assert not law.beyond(np.array([90e3])).any()


@pytest.mark.slow
@pytest.mark.sweep
def test_nh_cannot_hold_the_spa_lift_at_70_mm_so_the_fit_refuses_that_row():
    with pytest.raises(ValueError, match=r"row 1: h 70 mm with a force of 14.71 N is beyond .* fitted E = "):
        F.fit_static(spa_data(), "nh", R1, T0, "bonded", fidelity="exact", disk_radius=C)


@pytest.mark.slow
@pytest.mark.sweep
def test_gent_fit_of_the_spa_lift_data_reaches_its_measured_nrmsd_above_the_data_floor():
    d = spa_data()
    # the fitted membrane cannot hold every row (its solver's stretch limit): refused unless kept
    with pytest.raises(ValueError, match=r"row 1: h 70 mm .* beyond .* fitted mu = .* Jm = .*--keep-beyond-reach"):
        F.fit_static(d, "gent", R1, T0, "bonded", fidelity="exact", disk_radius=C)
    res = F.fit_static(d, "gent", R1, T0, "bonded", fidelity="exact", disk_radius=C, keep_beyond=True)
    assert res.nrmsd <= NRMSD_REACHED, res.nrmsd
    assert len(res.notes) == 1 and "rows lie beyond" in res.notes[0]
    # no static model beats the best single-valued curve through the data (its hysteresis)
    assert floor_nrmsd(d) < res.nrmsd
    for k in ("mu", "Jm"):
        lo, hi = res.ci95[k]
        assert lo < res.params[k] < hi, (k, res.ci95)


def measure(d: F.StaticData, res) -> str:
    """The fit's numbers as the how-to quotes them: parameters, NRMSD over all points and per load (each
    relative to the whole data's pressure span, so that they combine), and the data's floor."""
    span = float(d.p.max() - d.p.min())
    lines = [f"{res.n_points} points: " + ", ".join(f"{k} {v:.4g} [{res.ci95[k][0]:.4g}, {res.ci95[k][1]:.4g}]"
                                                    for k, v in res.params.items()),
             f"pressure NRMSD {res.nrmsd:.4f} (floor {floor_nrmsd(d):.4f}); lifted rows only "
             f"{nrmsd(res.p_model[d.h > 0], d.p[d.h > 0]):.4f}"]
    for f in np.unique(d.F):
        k = d.F == f
        miss = np.sqrt(np.mean((res.p_model[k] - d.p[k]) ** 2))
        sub = F.StaticData(d.h[k], d.p[k], d.F[k], "F_n")
        fl = floor_nrmsd(sub) * float(sub.p.max() - sub.p.min()) / span
        lines.append(f"  {f / U.G_STD:.2f} kg ({k.sum()} rows): RMS miss {U.to_kpa(miss):.3f} kPa, "
                     f"{miss / span:.4f} of the span (floor {fl:.4f})")
    return "\n".join(lines)


if __name__ == "__main__":
    # the measurement behind docs/how-to/fit-bonded.md: PYTHONPATH=.:tests python tests/unit/app/test_fit_bonded_gent.py
    # [a CSV of the full data set instead of the shipped one]
    import sys

    d = F.parse_data(Path(sys.argv[1]).read_bytes()) if len(sys.argv) > 1 else spa_data()
    res = F.fit_static(d, "gent", R1, T0, "bonded", fidelity="exact", disk_radius=C, keep_beyond=True)
    print(measure(d, res))
    print("\n".join(res.notes))
