"""The exact membrane at the edges: `equilibrium --fidelity exact`, the rig's exact free-inflation rung,
and the rig's structural mismatches (valve delay and minimum on-time, compressor-map shape, sensor lag)."""

from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app

runner = CliRunner()
E, R1, T0 = 130.6e3, 7.5e-3, 3e-3


def _eq(*args: str) -> dict:
    res = runner.invoke(app, ["equilibrium", "--json", "--fidelity", "exact", "--r1-mm", str(R1 * 1e3), *args])
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
    (["--fidelity", "exact", "--contact", "bonded", "--disk-radius-mm", "13", "--p-kpa", "24"], "--disk-radius-mm = 13"),
    (["--fidelity", "exact", "--contact", "bonded"], "--p-kpa is required"),
    (["--fidelity", "exact", "--p-kpa", "10"], "--p-kpa"),
    (["--fidelity", "exakt"], "--fidelity = 'exakt'"),
    (["--contact", "bonded", "--p-kpa", "10", "--fidelity", "cap"], "--fidelity exact"),
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


# --- the rig's exact free-inflation rung ---------------------------------------------------------
import numpy as np  # noqa: E402

from hbma_ctrl.core.interfaces import Command  # noqa: E402
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics  # noqa: E402
from hbma_ctrl.core.physics import load_compressor_table  # noqa: E402
from hbma_ctrl.models.exact import ExactMembrane  # noqa: E402
from hbma_ctrl.sim.rig import Rig, RigSettings, mismatched, simulate_rig, tilted_map  # noqa: E402
from hbma_ctrl.sim.trial import InputSchedule, Trial  # noqa: E402

PUMP = Command(1.0, 1.0, 0.0)
# only the membrane law differs between these rigs: no structural mismatch, no noise
PLAIN = dict(noise_std=0.0, valve_delay=0.0, valve_min_on=0.0, compressor_tilt=0.0, sensor_tau=0.0)


def _free_run(n: int, **kw) -> Rig:
    rig = Rig(Actuator(), Pneumatics(), Platform(), RigSettings(**{**PLAIN, **kw}))
    for _ in range(n):
        rig.apply(PUMP)
    return rig


def test_exact_rig_free_pressure_is_the_exact_membranes_at_its_height():
    rig = _free_run(40, membrane="exact")
    tr = rig.truth()
    act, _ = mismatched(Actuator(), Pneumatics(), rig.settings)
    # the solver itself (not the rig's table) at the rig's true height, with the rig's mismatched modulus
    ref = ExactMembrane(act.material, act.r1, act.t0).free(tr["h"])
    assert tr["p"] == pytest.approx(ref["p"], rel=2e-3)
    assert tr["h"] > 0.3 * act.r1


def test_exact_rig_differs_from_the_cap_rig_by_the_caps_pressure_error():
    exact, cap = _free_run(40, membrane="exact").truth(), _free_run(40, membrane="cap").truth()
    # the cap needs a larger height for the same gas: its pressure is low and its volume small
    assert exact["h"] < cap["h"]
    assert abs(exact["p"] / cap["p"] - 1) < 0.2 and exact["p"] != pytest.approx(cap["p"], rel=1e-3)


def test_exact_rig_batched_matches_stepped_and_load_removal_keeps_the_gas():
    s = RigSettings(**{**PLAIN, "membrane": "exact"})
    tr = Trial(Actuator(), Pneumatics(), Platform(), InputSchedule(((0.0, 1.0, 1.0, 0.0),)), 0.3, name="x")
    rec = simulate_rig([tr], s)[0]
    rig = _free_run(30, membrane="exact")
    assert rig.truth()["h"] == pytest.approx(rec.truth["h"][-1], rel=1e-9)
    m = rig.truth()["m"]
    rig.set_load(0.2)
    rig.set_load(0.0)  # the load leaves at once: the exact free membrane holds the same gas
    assert rig.truth()["m"] == pytest.approx(m, rel=1e-9)


# --- structural mismatches ----------------------------------------------------------------------
def _pump_trace(n: int = 12, **kw) -> np.ndarray:
    s = RigSettings(**{**PLAIN, **kw})
    tr = Trial(Actuator(), Pneumatics(), Platform(load=0.2, own_mass=0.02),
               InputSchedule(((0.0, 1.0, 1.0, 0.0),)), n * s.sample_period, name="x")
    rec = simulate_rig([tr], s)[0]
    return rec


def test_valve_delay_shifts_the_response_by_the_delay():
    ref, late = _pump_trace(), _pump_trace(valve_delay=0.02)
    assert np.all(late.truth["p"][:3] == late.truth["p"][0])  # nothing flows for 20 ms
    assert late.truth["p"][2:] == pytest.approx(ref.truth["p"][:-2], rel=1e-9, abs=1e-6)


def test_valve_minimum_on_time_drops_short_openings_and_lengthens_others():
    s = RigSettings(valve_min_on=0.002, sample_period=0.01)
    u = s.shape_command(np.array([[1.0, 1.0, 1.0], [0.05, 0.15, 0.5], [0.0, 0.12, 1.0]]))
    assert u[1].tolist() == [0.0, 0.2, 0.5] and u[2].tolist() == [0.0, 0.2, 1.0]
    assert u[0].tolist() == [1.0, 1.0, 1.0]  # the pump speed is not a valve
    # a 0.5 ms opening (5 % duty) never happens on the rig: the chamber stays at rest
    dribble = dict(membrane="cap")
    rig = Rig(Actuator(), Pneumatics(), Platform(), RigSettings(**{**PLAIN, **dribble, "valve_min_on": 0.002}))
    free = Rig(Actuator(), Pneumatics(), Platform(), RigSettings(**{**PLAIN, **dribble}))
    for _ in range(10):
        rig.apply(Command(1.0, 0.05, 0.0))
        free.apply(Command(1.0, 0.05, 0.0))
    assert rig.truth()["m"] == pytest.approx(Rig(Actuator(), Pneumatics(), Platform()).truth()["m"], rel=1e-12)
    assert free.truth()["h"] > 5e-5 and free.truth()["p"] > 0.0


def test_compressor_tilt_changes_the_maps_shape_not_its_mean():
    src = Pneumatics().csv_path
    s, p, q = load_compressor_table(src)
    s2, p2, q2 = load_compressor_table(tilted_map(src, 0.2))
    assert np.array_equal(s, s2) and np.array_equal(p, p2)
    full = q[-1] > 0
    ratio = q2[-1][full] / q[-1][full]
    assert ratio[0] == pytest.approx(1.1) and ratio[-1] == pytest.approx(1.1 - 0.2 * p[full][-1] / p.max())
    assert np.mean(1.0 - 0.2 * (p / p.max() - 0.5)) == pytest.approx(1.0)
    _, pn = mismatched(Actuator(), Pneumatics(), RigSettings(compressor_tilt=0.2))
    assert pn.csv_path != src and load_compressor_table(pn.csv_path)[2] == pytest.approx(q2)


def test_sensor_lag_reads_a_ramp_tau_late():
    rec = _pump_trace(40, sensor_tau=0.01, membrane="cap")
    p, z, t = rec.truth["p"], rec.meas, rec.t
    rate = np.gradient(p, t)
    k = slice(20, 38)  # past the start transient of the lag (a few tau)
    # a first-order lag follows a ramp tau behind: p(t) - y(t) ~ tau p'(t)
    assert np.median((p[k] - z[k]) / rate[k]) == pytest.approx(0.01, rel=0.15)
    assert np.all(z[1:] < p[1:])


def test_exact_rung_continues_past_its_table_without_a_jump():
    from hbma_ctrl.models.fidelity import OUTPUTS
    from hbma_ctrl.models.fidelity_exact import make_exact_free

    act = Actuator(r1=7.5e-3, t0=2e-3)
    fid = make_exact_free(act.material, str(Pneumatics().csv_path))
    th = fid.space.values(act, Pneumatics(), Platform())
    hm = fid.x_max * act.r1

    def y(h):
        return np.asarray(fid.out([h], [0, 0, 0], th, 1.0)).ravel()

    below, above = y(hm * (1 - 1e-9)), y(hm * (1 + 1e-9))
    for k in ("p", "V", "lam"):
        assert above[OUTPUTS.index(k)] == pytest.approx(below[OUTPUTS.index(k)], rel=1e-6)
    far = y(2.8 * act.r1)  # well past the limit point: finite, positive, and the gas still grows
    assert np.all(np.isfinite(far)) and far[OUTPUTS.index("p")] > 0
    assert far[OUTPUTS.index("m")] > above[OUTPUTS.index("m")]


def test_exact_free_rig_vents_from_flat_without_diverging_and_its_law_is_odd_in_height():
    """A 0 g exact rig starts flat and is vented (the start-up calibration's first command): the plant
    stays alive at h ~ 0 (dG/dh1 at the flat membrane is p_env dV/dh1 > 0), and below the clamp the
    law mirrors the one above (p and the added volume odd in h1)."""
    from hbma_ctrl.models.fidelity import OUTPUTS

    act = Actuator(r1=12.5e-3, t0=3e-3, V0=3e-6)
    rig = Rig(act, Pneumatics(), Platform(load=0.0), RigSettings(seed=1, membrane="exact"))
    for _ in range(20):
        rig.apply(Command(0.0, 0.0, 1.0))
    assert abs(rig.truth()["h"]) < 1e-9
    fid = rig._plant.fid
    theta = rig._theta(fid, Platform(load=0.0))
    out = fid.out
    ip, iV, il = (OUTPUTS.index(k) for k in ("p", "V", "lam"))
    V0 = rig.actuator.V0
    for hh in (1e-4, 2e-3, 6e-3):
        up = np.asarray(out([hh], np.zeros(3), theta, 1.0)).ravel()
        dn = np.asarray(out([-hh], np.zeros(3), theta, 1.0)).ravel()
        assert dn[ip] == pytest.approx(-up[ip]) and up[ip] > 0
        assert dn[iV] - V0 == pytest.approx(-(up[iV] - V0)) and dn[il] == pytest.approx(up[il])
