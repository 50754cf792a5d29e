"""The exact flat-plate contact in the loaded fidelities, the rig and the simulator's 'exact' rung
(README Model §9): the table against the solver, the cap's chart at lift-off, and the rung's force balance
checked by the exact solver itself."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from checkout import ROOT
from hbma_ctrl.core.materials import make_material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.exact import ExactMembrane
from hbma_ctrl.models.exact_tables import RATIO_S, RATIO_U, contact_ratio_table
from hbma_ctrl.models.fidelity import OUTPUTS
from hbma_ctrl.models.fidelity_exact import make_exact_free, make_exact_loaded
from hbma_ctrl.sim.rig import Rig, RigSettings, mismatched
from hbma_ctrl.sim.simulate import simulate
from hbma_ctrl.sim.trial import InputSchedule, SimSettings, Trial

R1, T0 = 7.5e-3, 3e-3
ACT = Actuator(r1=R1, t0=T0)
CSV = str(Pneumatics().csv_path)
PLAIN = dict(noise_std=0.0, valve_delay=0.0, valve_min_on=0.0, compressor_tilt=0.0, sensor_tau=0.0)


def _law(fid, h1: float, h2: float, act: Actuator = ACT) -> dict:
    """The fidelity's membrane law at chart (h1, h2), numeric: p (Pa), V (m^3), F (N)."""
    theta, P = fid.space.symbols()
    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    p, V, _, a2 = fid.contact_law(a, b, P)
    f = ca.Function("law", [a, b, theta], [p, V, ca.pi * a2 * p])
    out = f(h1, h2, fid.space.values(act))
    return {"p": float(out[0]), "V": float(out[1]), "F": float(out[2])}


@pytest.fixture(scope="module")
def qs():
    return make_exact_loaded("quasi_static", make_material("nh"), CSV)


# mid-nodes (u = h1/r1 and sqrt(s) halfway between nodes) where the plate's pressure is below the free
# limit point, where the solver's contact at (h, p) is unique
@pytest.mark.parametrize("i, j", [(3, 20), (6, 16), (9, 10), (12, 4), (15, 1)])
def test_contact_table_matches_the_solver_at_mid_nodes_within_1_percent(qs, i, j):
    u = 0.5 * (RATIO_U[i] + RATIO_U[i + 1])
    s = (0.5 * (np.sqrt(RATIO_S[j]) + np.sqrt(RATIO_S[j + 1]))) ** 2
    h1, h2 = u * R1, s * u * R1
    got = _law(qs, h1, h2)
    ref = ExactMembrane(make_material("nh"), R1, T0).contact(h1 - h2, got["p"])
    assert got["F"] == pytest.approx(ref["F"], rel=0.01)
    assert got["V"] == pytest.approx(ref["V"] + ACT.V0, rel=0.01)


def test_contact_law_meets_the_exact_free_inflation_as_the_plate_leaves(qs):
    free = make_exact_free(make_material("nh"), CSV)
    theta = free.space.values(ACT)
    for h1 in (2e-3, 5e-3, 8e-3):
        y = np.asarray(free.out([h1], [0, 0, 0], theta, 1.0)).ravel()
        touching = _law(qs, h1, 1e-9 * h1)
        assert touching["F"] == pytest.approx(0.0, abs=1e-6)  # a^2 ~ h2: 1e-9 h1 presses with micronewtons
        assert touching["p"] == pytest.approx(y[OUTPUTS.index("p")], rel=2e-3)
        assert touching["V"] == pytest.approx(y[OUTPUTS.index("V")], rel=2e-3)
        # the force grows continuously from 0 as the plate presses
        assert 0 < _law(qs, h1, 0.01 * h1)["F"] < _law(qs, h1, 0.05 * h1)["F"]


@pytest.mark.slow
def test_contact_table_is_the_same_for_any_geometry_and_modulus_scale(tmp_path):
    # the ratios are dimensionless: one table serves every r1, t0 and modulus scale of a material
    u, s = RATIO_U[:6], RATIO_S[:5]
    a = contact_ratio_table(ExactMembrane(make_material("nh"), R1, T0), u, s, cache=tmp_path)
    b = contact_ratio_table(ExactMembrane(make_material("nh").scaled(1.3), 12.5e-3, 2e-3), u, s, cache=tmp_path)
    assert a["build_s"] > 0 and np.allclose(a["Rp"], b["Rp"], rtol=1e-6) and np.allclose(a["Rv"], b["Rv"], rtol=1e-6)
    assert contact_ratio_table(ExactMembrane(make_material("nh"), R1, T0), u, s, cache=tmp_path)["build_s"] == 0.0


@pytest.mark.slow
def test_exact_quasi_static_rig_carries_the_load_by_the_solvers_contact_force():
    s = RigSettings(**{**PLAIN, "membrane": "exact", "fidelity": "quasi_static"})
    plat = Platform(load=0.2)
    rig = Rig(ACT, Pneumatics(), plat, s)
    for _ in range(60):
        rig.apply([0.6, 1.0, 0.0])
    tr = rig.truth()
    act, _ = mismatched(ACT, Pneumatics(), s)
    assert tr["h"] > 1e-3
    # the solver itself, at the rig's height and pressure, with the rig's mismatched modulus
    ref = ExactMembrane(act.material, act.r1, act.t0).contact(tr["h"], tr["p"])
    assert ref["F"] == pytest.approx(plat.weight, rel=0.01)
    cap = Rig(ACT, Pneumatics(), plat, RigSettings(**{**PLAIN, "membrane": "cap", "fidelity": "quasi_static"}))
    for _ in range(60):
        cap.apply([0.6, 1.0, 0.0])
    assert abs(cap.truth()["h"] - tr["h"]) > 0.1e-3  # the membrane law now reaches a loaded chamber


@pytest.mark.slow
def test_simulator_exact_rung_runs_loaded_and_free_trials_and_says_exact():
    sched = InputSchedule(((0.0, 0.8, 1.0, 0.0), (0.8, 0.0, 0.0, 1.0)))
    trials = [Trial(ACT, Pneumatics(), Platform(load=load), sched, 1.5, name=f"m{load}") for load in (0.0, 0.2)]
    logs = simulate(trials, SimSettings(), fidelity="exact")
    assert [log.fidelity for log in logs] == ["exact", "exact"] and all(log.status == "ok" for log in logs)
    loaded = logs[1]
    names = [n for _, n in loaded.events]
    assert "lift_off" in names and "touch_down" in names
    # while the platform moves the force on it is the exact law's at its height (platform: F = p pi a^2)
    k = int(np.argmax(loaded["h"]))
    ref = ExactMembrane(make_material("nh"), R1, T0).contact(loaded["h"][k], loaded["p"][k])
    assert loaded["F"][k] == pytest.approx(ref["F"], rel=0.01)


def test_exact_loaded_rung_refuses_a_free_name():
    with pytest.raises(ValueError, match="allowed: quasi_static, platform"):
        make_exact_loaded("free", make_material("nh"), CSV)


@pytest.mark.slow
def test_bench_sim_fidelity_axis_scores_every_rung_against_the_exact_membrane(tmp_path, monkeypatch):
    import json

    import hbma_ctrl.app.bench.sim as bench
    from hbma_ctrl.sim.batch import protocol_trials

    short = protocol_trials("nh", loads_g=[0.0, 200.0], speeds_pct=[100.0], t0_mm=[3.0], r1_mm=[12.5],
                            t_inflate_s=0.4, duration_s=0.8)
    monkeypatch.setattr(bench, "bench_trials", lambda material, quick: short)
    rows = bench.run_bench(tmp_path, grid={"quasi_static": {"rk4": (10.0,)}}, progress=False, fidelity_axis=True,
                           fidelity_grid={"free": {"rk4": (10.0,)}, "exact": {"rk4": (2.0,)}})
    by = {(r.fidelity, r.integrator, r.dt_ms): r for r in rows}
    # the old rows first, unchanged in kind; then the free rung (its 0 g trial only) and the exact rung
    assert list(by)[:2] == [("quasi_static", "rk4", None), ("quasi_static", "rk4", 10.0)]
    assert by[("free", "rk4", None)].n_trials == 1 and by[("exact", "rk4", None)].n_trials == 2
    qs, ex = by[("quasi_static", "rk4", None)], by[("exact", "rk4", 2.0)]
    # the cap's membrane law is a model error far above the exact rung's own step error
    assert ex.height_nrmsd_vs_exact_mean < 1e-3 < qs.height_nrmsd_vs_exact_mean
    assert 0 < ex.pressure_nrmsd_vs_exact_mean < qs.pressure_nrmsd_vs_exact_mean
    data = json.loads((tmp_path / "bench.json").read_text())
    assert {"height_nrmsd_mean", "height_nrmsd_vs_exact_mean"} <= set(data["rows"][0])
    assert data["meta"]["fidelity_axis"]["reference"] == "exact"
    assert (tmp_path / "pareto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_role_pareto_plots_read_bench_json_and_mark_the_front(tmp_path):
    import json

    from hbma_ctrl.app.bench.plots import controller_pareto_png, controller_points, pareto_front

    # (cost, error): the two cheapest-for-their-accuracy points are the front, the dominated one is not
    assert pareto_front([1.0, 2.0, 3.0], [0.3, 0.1, 0.2]).tolist() == [0, 1]
    rows = [{"controller": "rti_osqp N=10", "solve_ms_median": 0.8, "height_rmse_mm": 1.3},
            {"controller": "ipopt N=20", "solve_ms_median": 30.0, "height_rmse_mm": 1.15}]
    (tmp_path / "bench_mpc.json").write_text(json.dumps({"rows": rows}))
    pts, _ = controller_points(tmp_path / "bench_mpc.json")
    assert [(p[0], p[1][0], p[2], p[3]) for p in pts] == [("N=10", "rti_osqp", 0.8, 1.3), ("N=20", "ipopt", 30.0, 1.15)]
    png = controller_pareto_png(tmp_path / "bench_mpc.json", tmp_path / "c.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_bench_sim_bad_role_json_is_one_error_line_exit_2(tmp_path):
    from typer.testing import CliRunner

    from hbma_ctrl.app.cli.main import app

    (tmp_path / "x.json").write_text("{}")
    for flag, path, needle in (("--ekf-json", tmp_path / "none.json", "--ekf-json: no file"),
                               ("--mpc-json", tmp_path / "x.json", "--mpc-json: ")):
        res = CliRunner().invoke(app, ["bench", "sim", "--quick", "--out", str(tmp_path / "o"), flag, str(path)])
        lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
        assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: " + needle), res.output
    # --roles runs the role benches itself: a JSON beside it is refused before any work
    res = CliRunner().invoke(app, ["bench", "sim", "--quick", "--roles", "--out", str(tmp_path / "o"), "--ekf-json",
                                   str(tmp_path / "x.json")])
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: --roles runs"), res.output
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_run_open_loop_scene_with_fidelity_exact_logs_the_exact_rung(tmp_path):
    pass

    from hbma_ctrl.app.scenes.runner import run_scenario
    from hbma_ctrl.app.scenario import load_scenario

    root = ROOT
    text = (root / "scenarios" / "open_loop_loaded.toml").read_text()
    text = text.replace('fidelity = "platform"', 'fidelity = "exact"').replace("duration_s = 6.0", "duration_s = 1.0")
    text = text.replace("[3.0, 0.0,   0.0, 1.0]", "[0.6, 0.0,   0.0, 1.0]")
    (tmp_path / "s.toml").write_text(text)
    scn = load_scenario(tmp_path / "s.toml")
    assert scn.fidelity == "exact"
    metrics = run_scenario(scn, tmp_path / "out")
    flat = {k: v for sec in metrics.values() if isinstance(sec, dict) for k, v in sec.items()}
    assert flat["fidelity"] == "exact" and flat["status"] == "ok" and flat["max_force_n"] > 0
