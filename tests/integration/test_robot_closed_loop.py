"""Closed-loop robot control: EKF bank, structured NMPC, pressure-PID baseline, mismatched rig."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.app.scenes.robot_loop import run_closed_loop
from hbma_ctrl.app.scenes.robot_closed import closed_loop_metrics
from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Pneumatics
from hbma_ctrl.models.bank import commands_from_inputs
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.rig import RobotRig, RobotRigSettings
from hbma_ctrl.robot.statics import load_sharing

D1 = RobotDesign(n_layers=1)

def parse_section(raw: dict):
    """The [robot] table (edge units) -> its SI settings, through the scenario schema."""
    return parse_role("robot", raw)



@pytest.fixture(scope="module")
def model(robot_bank):
    return robot_bank  # make_model(D1, Pneumatics(), "per_chamber")


@pytest.fixture(scope="module")
def shared_model(shared_robot_bank):
    return shared_robot_bank  # make_model(D1, Pneumatics(), "shared")


def _settings(limit_kpa: float = 45.0, topology: str = "per_chamber") -> RobotSettings:
    return RobotSettings(design=D1, pneumatics=RobotPneumatics(topology=topology, pressure_limit=limit_kpa * 1e3))


@pytest.mark.slow
def test_ekf_bank_tracks_heights_open_loop(model):
    """Inflate the three chambers differently (open loop) on the mismatched rig; the bank follows."""
    rig = RobotRig(D1, Pneumatics(), 50e3, "per_chamber", RobotRigSettings(seed=3))
    bank = ChamberEKFBank(model, 3, ChamberEKFSettings())
    a = np.array([1.0, 0.8, 0.6])
    w = np.zeros((2, 3))
    W = load_sharing(D1, np.zeros((1, 3))).forces.ravel()
    errs = []
    for j in range(170):
        est = bank.step(rig.measure(), w, np.maximum(W, 1e-3))
        W = load_sharing(D1, est["h"].reshape(1, 3)).forces.ravel()
        ak = a if j < 75 else np.zeros(3)
        U = commands_from_inputs(ak, np.zeros(3), "per_chamber")
        w = U[1:].copy()
        rig.apply(U)
        if j > 70:
            errs.append(est["h"] - np.maximum(rig.truth()["h"], 0))
    h = rig.truth()["h"]
    assert h.min() > 2e-3 and np.ptp(h) > 0.5e-3  # inflated, and differently
    assert np.sqrt(np.mean(np.square(errs))) < 0.5e-3
    assert np.all(bank.last["h_std"] < 1e-3)
    # the soft chamber (modulus -15 %) went past its limit point (~5 mm): there the pressure curve
    # tells its modulus and dead-volume (x1.2) factors apart
    assert h[1] > 6e-3
    assert abs(bank.last["k"][1] - rig.modulus_scales[1]) < 0.05
    assert abs(bank.last["c"][1] - 1.2) < 0.1


@pytest.mark.slow
def test_mpc_holds_chambers_past_the_limit_point(model):
    """Every chamber held at 7 mm (beyond the 5.7 mm limit point) on the mismatched rig, p <= 45 kPa."""
    tg = {0: ((0.0, U.mm(7.0), 0.0, 0.0),)}
    run = run_closed_loop(_settings(), tg, 3.0, "mpc", model=model)
    h_end = run.h[-50:].mean(0)
    assert np.all(np.abs(h_end - 7e-3) < 0.5e-3)
    peak_h = np.array([model.peak(w)[0] for w in run.loads[-1]])
    assert np.all(h_end > peak_h)  # on the far branch
    assert run.p.max() <= 45e3
    assert run.fallbacks == 0
    m = closed_loop_metrics(D1, run, 45e3, settle_time=2.0, model=model)
    assert m["chamber_height_rmse_mm"] < 0.5 and not m["pressure_limit_exceeded"]
    assert set(m["far_branch_chambers"]) == {"A1", "A2", "A3"}


@pytest.mark.slow
def test_pressure_limit_is_never_exceeded_with_a_tight_limit(model):
    """With a 38 kPa limit the stiff chambers (true peak ~42 kPa) cannot pass the limit point: the
    NMPC holds them below the limit instead of pushing through."""
    tg = {0: ((0.0, U.mm(7.0), 0.0, 0.0),)}
    run = run_closed_loop(_settings(limit_kpa=38.0), tg, 2.5, "mpc", model=model)
    assert run.p.max() <= 38e3
    assert run.h[-1].max() > 3e-3  # it did inflate


@pytest.mark.slow
def test_pressure_pid_runs_through_the_same_api_and_cannot_hold_the_far_branch(model):
    tg = {0: ((0.0, U.mm(7.0), 0.0, 0.0),)}
    run = run_closed_loop(_settings(), tg, 3.0, "pressure_pid", model=model)
    m = closed_loop_metrics(D1, run, 45e3, settle_time=2.0, model=model)
    assert m["controller"] == "pressure_pid" and m["step_ms_median"] > 0
    # a far-branch target pressure is met on the near branch (stiff chambers stay low) or never met
    # (soft chambers run away): no chamber settles at 7 mm
    assert np.all(np.abs(run.h[-1] - 7e-3) > 0.5e-3)


@pytest.mark.slow
def test_shared_compressor_respects_the_duty_budget(shared_model):
    tg = {0: ((0.0, U.mm(7.0), 0.0, 0.0),)}
    run = run_closed_loop(_settings(topology="shared"), tg, 3.5, "mpc", model=shared_model)
    assert np.all(run.a.sum(1) <= 1.0 + 1e-6)
    assert run.a.sum(1).max() > 0.9  # the budget was used
    assert np.all(np.abs(run.h[-1] - 7e-3) < 0.5e-3)


def test_closed_loop_section_validation():
    ok = parse_section({"mode": "closed_loop", "layers": 1, "controller": "pressure_pid",
                        "targets": {"all": [[0, 6, 0, 0], [2, 7, -15, 90]]}, "tip_load_n": [[1.0, 0, 0, -0.1]]})
    assert ok.controller == "pressure_pid" and ok.targets[0][1][3] == pytest.approx(-np.pi / 2)
    with pytest.raises(ValueError, match=r"\[robot\] controller = 'mcp' is not allowed; did you mean 'mpc'"):
        parse_section({"mode": "closed_loop", "layers": 1, "controller": "mcp", "targets": {"all": [[0, 6, 0, 0]]}})
    with pytest.raises(ValueError, match="chamber heights"):
        parse_section({"mode": "closed_loop", "layers": 1, "targets": {"all": [[0, 2, 20, 0]]}})
    with pytest.raises(ValueError, match=r"\[robot.targets\] D: no such layer"):
        parse_section({"mode": "closed_loop", "layers": 1, "targets": {"D": [[0, 6, 0, 0]]}})
    with pytest.raises(ValueError, match=r"needs \[robot.targets\]"):
        parse_section({"mode": "closed_loop", "layers": 1})


@pytest.mark.slow
def test_bench_robot_cli(tmp_path):
    import json

    from typer.testing import CliRunner

    from hbma_ctrl.app.cli.main import app

    r = CliRunner().invoke(app, ["bench", "robot", "--layers", "1", "--duration", "0.6", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    rows = json.loads((tmp_path / "bench_robot.json").read_text())["rows"]
    assert [row["layers"] for row in rows] == [1] and rows[0]["chambers"] == 3
    assert rows[0]["step_ms_p99"] >= rows[0]["step_ms_median"] > 0
    bad = CliRunner().invoke(app, ["bench", "robot", "--layers", "7", "--out", str(tmp_path)])
    assert bad.exit_code == 2 and "--layers" in bad.output


@pytest.mark.slow
def test_closed_loop_scene_tracks_the_bend_and_writes_metrics_and_plots(tmp_path):
    """A short 1-layer closed-loop scenario through the runner: after settling, the TRUE pose (from
    the logged rig heights, through the forward kinematics) holds the 10 deg bend about 90 deg within
    the 2 deg tolerance and every chamber within 0.5 mm; robot metrics, the baseline beside, the
    shape plot and the signals are written."""
    from hbma_ctrl.app.scenes.runner import run_scenario
    from hbma_ctrl.app.scenario import load_scenario

    p = tmp_path / "s.toml"
    p.write_text('[scenario]\nname = "cl"\nduration_s = 2.5\n[inputs]\nschedule = [[0.0, 0.0, 0.0, 0.0]]\n[rig]\nseed = 4\n[robot]\nmode = "closed_loop"\n'
                 'layers = 1\ncompare_baseline = true\nsettle_s = 1.0\n'
                 '[robot.targets]\nall = [[0.0, 4.0, 0.0, 0.0], [0.8, 5.0, 10.0, 90.0]]\n')
    out = run_scenario(load_scenario(p), tmp_path / "out")
    rob = out["robot"]
    for key in ("chamber_height_rmse_mm", "bend_angle_rmse_deg", "tip_position_rmse_mm", "step_ms_median",
                "step_ms_p99"):
        assert rob[key] is not None and rob[key] >= 0
    assert rob["controller"] == "mpc" and rob["baseline"]["controller"] == "pressure_pid"
    assert not rob["pressure_limit_exceeded"]
    for f in ("robot_shape.png", "robot_series.png", "robot_mpc_log.csv", "metrics.json"):
        assert (tmp_path / "out" / f).exists()
    # the bend step (0.8 s on) is tracked: checked from the log, independently of the metrics code
    import csv

    from hbma_ctrl.robot.kinematics import forward_kinematics

    with open(tmp_path / "out" / "robot_mpc_log.csv") as fh:
        rows = list(csv.DictReader(fh))
    last = [r for r in rows if float(r["t_s"]) >= 2.0]
    assert last
    for r in last:
        h = np.array([[float(r[f"h_A{i}_mm"]) for i in (1, 2, 3)]]) * 1e-3
        ref = np.array([[float(r[f"h_ref_A{i}_mm"]) for i in (1, 2, 3)]]) * 1e-3
        assert np.all(np.abs(h - ref) < 0.5e-3), (r["t_s"], h, ref)
        pose = forward_kinematics(D1, h)
        assert np.degrees(pose.bend[0]) == pytest.approx(10.0, abs=2.0)
        assert np.degrees(pose.direction[0]) == pytest.approx(90.0, abs=10.0)
    seg = rob["segments"][-1]
    assert seg["settled"] and seg["final_bend_err_deg"] < 2.0 and seg["final_height_err_mm"] < 0.5
