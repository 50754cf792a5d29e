"""The simulated rig: mismatch, sensor (noise, saturation, dropouts), load steps, determinism."""

import math

import numpy as np
import pytest

from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.materials import make_material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.sim.rig import (
    CAP_RIG,
    Rig,
    RigSettings,
    mismatched,
    simulate_rig,
)
from hbma_ctrl.sim.trial import InputSchedule, Trial

PUMP = Command(1.0, 1.0, 0.0)


def test_settings_validation_names_field():
    with pytest.raises(ValueError, match="rig.noise_std"):
        RigSettings(noise_std=-1.0).validate()
    with pytest.raises(ValueError, match="rig.fidelity"):
        RigSettings(fidelity="free").validate()
    with pytest.raises(ValueError, match="did you mean noise_std_kpa"):
        parse_role("rig", {"noise_std_kp": 0.2})


def test_section_converts_edge_units():
    s = parse_role("rig", {"noise_std_kpa": 0.5, "sensor_range_kpa": 30, "sample_period_ms": 5, "modulus_scale": 0.85})
    assert s.noise_std == pytest.approx(500.0)
    assert s.sensor_range == pytest.approx(30e3)
    assert s.sample_period == pytest.approx(5e-3)
    assert s.modulus_scale == 0.85


def test_mismatch_scales_moduli_not_shape_parameters():
    act = Actuator(material=make_material("gent", mu=40e3, Jm=50.0))
    a, p = mismatched(act, Pneumatics(), RigSettings(modulus_scale=1.15, V0_scale=1.2, flow_scale=0.9))
    assert a.material.mu == pytest.approx(46e3)
    assert a.material.Jm == 50.0
    assert a.V0 == pytest.approx(1.2 * act.V0)
    assert p.flow_scale == pytest.approx(0.9)


def test_sensor_noise_saturation_and_dropouts():
    rig = Rig(Actuator(), Pneumatics(), Platform(load=0.8, own_mass=0.02),
              RigSettings(sensor_range=10e3, noise_std=300.0, dropout_prob=0.2, seed=3))
    z0 = np.array([rig.measure() for _ in range(2000)])  # at rest, p = 0
    ok = z0[np.isfinite(z0)]
    assert 0.15 < np.mean(~np.isfinite(z0)) < 0.25
    assert np.std(ok) == pytest.approx(300.0, rel=0.1)
    for _ in range(60):  # 0.6 s at full speed: the flat chamber passes 10 kPa
        rig.apply(PUMP)
    assert rig.truth()["p"] > 10e3
    z = np.array([rig.measure() for _ in range(200)])
    assert np.nanmax(z) <= 10e3  # never above the range
    assert np.all(z[np.isfinite(z)] == 10e3)  # p is 20+ kPa above the range: always saturated


def test_deterministic_for_a_seed():
    def run(seed):
        rig = Rig(Actuator(), Pneumatics(), Platform(load=0.2), RigSettings(seed=seed))
        out = []
        for _ in range(30):
            rig.apply(PUMP)
            out.append(rig.measure())
        return np.array(out), rig.truth()["h"]

    a, ha = run(1)
    b, hb = run(1)
    c, _ = run(2)
    assert np.array_equal(a, b) and ha == hb
    assert not np.array_equal(a, c)


def test_load_steps_keep_the_gas_and_switch_models():
    rig = Rig(Actuator(), Pneumatics(), Platform(), RigSettings(noise_std=0.0))
    assert rig.fidelity == "free"
    for _ in range(100):
        rig.apply(PUMP)
    before = rig.truth()
    rig.set_load(0.4)  # put on the apex
    assert rig.fidelity == "platform"
    after = rig.truth()
    assert after["m"] == pytest.approx(before["m"], rel=1e-9)
    for _ in range(100):
        rig.apply(Command(0.0, 0.0, 0.0))
    loaded = rig.truth()
    assert loaded["F"] == pytest.approx(0.4 * 9.80665, rel=0.05)  # settled on the membrane
    assert loaded["h"] < before["h"]
    rig.set_load(0.0)
    assert rig.fidelity == "free"
    assert rig.truth()["m"] == pytest.approx(loaded["m"], rel=1e-9)
    assert rig.truth()["h"] > loaded["h"]
    assert any("load_set" in name for _, name in rig.events)
    with pytest.raises(ValueError, match="mass_kg"):
        rig.set_load(-1.0)


@pytest.mark.slow
def test_batched_rig_matches_the_stepped_rig():
    """On the cap rig without noise the readings are the true pressure clipped at the range (the
    default rig's structure, applied alike by both, is checked in tests/test_rig_exact.py)."""
    tr = Trial(Actuator(), Pneumatics(), Platform(load=0.4, own_mass=0.02),
               InputSchedule.inflate_deflate(0.8, 1.0), 1.5, "x")
    (rec,) = simulate_rig([tr], RigSettings(noise_std=0.0, **CAP_RIG))
    rig = Rig(tr.actuator, tr.pneumatics, tr.platform, RigSettings(noise_std=0.0, **CAP_RIG))
    hs = [rig.truth()["h"]]
    for k in range(len(rec.t) - 1):
        rig.apply(Command(*rec.u[k]))
        hs.append(rig.truth()["h"])
    assert np.allclose(hs, rec.truth["h"], atol=1e-6)
    assert np.allclose(rec.meas, np.minimum(rec.truth["p"], 35e3))
    assert any(name == "lift_off" for _, name in rec.events)
    assert math.isfinite(rec.truth["h"].max()) and rec.truth["h"].max() > 1e-3


def test_batch_noise_follows_the_stream_id_not_the_batch():
    """A trial's readings depend on its stream id, not on which batch it ran in (the protocol
    splits its trials across worker processes)."""
    a = Trial(Actuator(), Pneumatics(), Platform(), InputSchedule.inflate_deflate(0.2, 0.2), 0.5, "a")
    b = Trial(Actuator(), Pneumatics(), Platform(load=0.2), InputSchedule.inflate_deflate(0.2, 0.2), 0.5, "b")
    rs = RigSettings(seed=4)
    both = simulate_rig([a, b], rs)
    alone = simulate_rig([b], rs, stream_ids=[1])
    np.testing.assert_array_equal(both[1].meas, alone[0].meas)
    assert not np.array_equal(simulate_rig([b], rs)[0].meas, alone[0].meas)
    with pytest.raises(ValueError, match="stream_ids"):
        simulate_rig([a, b], rs, stream_ids=[0])
