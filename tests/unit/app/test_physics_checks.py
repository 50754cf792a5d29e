"""A finished run whose numbers are not physics is marked failed with its reason, never 'ok'."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.metrics import MASS_BALANCE_TOL, physics_problems
from hbma_ctrl.core.materials import LAM_CHECK, Gent, NeoHookean
from hbma_ctrl.sim.trial import Log


def _log(mass_error: float = 0.0, lam_peak: float = 1.5) -> Log:
    t = np.linspace(0.0, 1.0, 11)
    mass_in = 1e-6 * t
    m = 3e-6 + mass_in + mass_error * (3e-6 + 1e-6) * t  # the error grows to mass_error of the largest mass
    return Log("x", "free", {"t": t, "m": m, "mass_in": mass_in, "lam": 1.0 + (lam_peak - 1.0) * t})


def test_a_consistent_run_has_no_problem():
    assert physics_problems(_log(1e-9), NeoHookean()) == []


@pytest.mark.parametrize("err", [2 * MASS_BALANCE_TOL, 0.5])
def test_gas_made_by_the_integrator_beyond_the_tolerance_is_named_with_its_size(err):
    (why,) = physics_problems(_log(err), NeoHookean())
    assert "mass balance is off by" in why and f"{err / (1 + err):.3g}" in why and "dt_ms" in why  # of max |m|


def test_a_stretch_past_a_gent_materials_locking_stretch_is_a_problem():
    mat = Gent(Jm=3.0)
    (why,) = physics_problems(_log(lam_peak=mat.lam_max() + 0.05), mat)
    assert "locking stretch" in why


def test_a_stretch_past_the_checked_range_of_the_laws_is_a_problem():
    (why,) = physics_problems(_log(lam_peak=LAM_CHECK + 0.5), NeoHookean())
    assert "beyond 4" in why and "checked over" in why


def test_a_run_too_coarse_for_its_integrator_exits_1_with_the_reason_and_is_kept_as_failed(tmp_path):
    scn = tmp_path / "coarse.toml"
    scn.write_text("[scenario]\nname = 'coarse'\nduration_s = 6\n[sim]\nintegrator = 'euler'\ndt_ms = 100\n")
    res = CliRunner().invoke(app, ["run", str(scn), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("error: the run failed the physics checks") and "mass balance" in line
    (kept,) = tmp_path.glob("o.failed-*")
    assert not (tmp_path / "o").exists() and (kept / "metrics.json").exists()


def test_a_diverged_run_keeps_its_own_status_and_gets_no_second_reason():
    log = _log(0.5)
    log.status = "diverged"
    assert physics_problems(log, NeoHookean()) == []


def test_the_protocol_command_keeps_a_run_with_a_failed_trial_as_failed_and_exits_1(tmp_path, monkeypatch):
    import hbma_ctrl.app.cli.sim as cli_sim

    def rows(material, out_dir, *a, **k):
        (out_dir / "summary.csv").write_text("status\nok\nfailed\n")
        return [{"status": "ok", "max_height_mm": 1.0, "max_pressure_kpa": 1.0},
                {"status": "failed", "max_height_mm": 1.0, "max_pressure_kpa": 1.0,
                 "failed_because": ["t3_r7.5_m0_s20: the gas mass balance is off by 0.05"]}]

    monkeypatch.setattr(cli_sim, "run_protocol", rows)
    res = CliRunner().invoke(app, ["protocol", "--no-plots", "--out", str(tmp_path / "p")])
    assert res.exit_code == 1, res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("error: 1 of 2 trials failed the physics checks (summary.csv status); t3_r7.5_m0_s20")
    (kept,) = tmp_path.glob("p.failed-*")
    assert not (tmp_path / "p").exists() and (kept / "summary.csv").exists()


def _pressure_log(p_peak_kpa: float) -> Log:
    log = _log()
    log.data["p"] = np.linspace(0.0, p_peak_kpa * 1e3, log["t"].size)
    return log


def _map(path, p_end_kpa: float, flow_at_end: float):
    rows = ["speed,pressure_pa,mass_flow_kgs"]
    for s in (0.0, 1.0):
        rows += [f"{s},0,{s * 6e-6:.3e}", f"{s},{p_end_kpa * 1e3:g},{s * flow_at_end:.3e}"]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_the_shipped_pumps_reach_is_its_full_speed_stall_pressure():
    from hbma_ctrl.core.params import Pneumatics
    from hbma_ctrl.core.physics import pump_reach

    # the default map: p_stall(s) = 50 kPa (0.3 + 0.7 s), flow linear in the back pressure
    reach, stalls = pump_reach(Pneumatics().csv_path)
    assert reach == pytest.approx(50e3) and stalls


@pytest.mark.parametrize("excess", [0.0, 0.5])
def test_a_pressure_up_to_the_tolerance_above_the_pumps_stall_is_no_problem(tmp_path, excess):
    from hbma_ctrl.app.metrics import PUMP_REACH_TOL

    pump = _map(tmp_path / "pump.csv", 40.0, 0.0)  # stalls at 40 kPa
    assert physics_problems(_pressure_log(40.0 * (1 + excess * PUMP_REACH_TOL)), NeoHookean(), pump) == []


def test_a_pressure_above_what_the_pump_reaches_names_both_pressures(tmp_path):
    pump = _map(tmp_path / "pump.csv", 40.0, 0.0)
    (why,) = physics_problems(_pressure_log(107.5), NeoHookean(), pump)
    assert "reached 107.5 kPa, above the 40 kPa the pump stalls at" in why


def test_a_pressure_past_the_end_of_a_map_that_still_delivers_flow_asks_for_a_longer_map(tmp_path):
    pump = _map(tmp_path / "pump.csv", 35.0, 3e-6)  # measured to 35 kPa only, like the paper's Fig. 5
    (why,) = physics_problems(_pressure_log(50.0), NeoHookean(), pump)
    assert "above the 35 kPa where its compressor map ends" in why and "compressor_csv" in why
