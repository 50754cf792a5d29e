"""The moving-horizon estimator: indexing, constraints, arrival cost, fallback, and tracking on the rig.

The rig (:mod:`hbma_ctrl.sim.rig`) differs from the estimator's model in structure (platform dynamics,
pump map of another shape, valve and sensor timing) and parameters (modulus x1.15, flow x0.9, dead
volume x1.2): the truth is never the model under test.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hbma_ctrl.app.scenes.evaluate import contact_events, run_filter, score
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.estimators.common import FACTOR_RANGE, FilterSettings
from hbma_ctrl.estimators.ekf_step import KIND_NONE, KIND_OK, observer_model
from hbma_ctrl.estimators.mhe import (
    MHE,
    MHESettings,
    constraint_violations,
    lean_model,
    linearise_function,
    mhe_step_function,
)
from hbma_ctrl.estimators.steady import steady_gain
from hbma_ctrl.models.actuation import CommandTiming
from hbma_ctrl.models.chamber import NX
from hbma_ctrl.models.reduced import EPS_K
from hbma_ctrl.sim.batch import protocol_trials
from hbma_ctrl.sim.rig import RigSettings, simulate_rig

SMALL = MHESettings(horizon=3, compile=False)


def test_constraint_violations_counts_each_broken_rule():
    h1 = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3])
    h2 = np.array([0.0, -1e-6, 2e-3, 0.0, 0.0, 0.0])
    h = np.array([1e-3, 1e-3, 1e-3, -1e-6, 1e-3, 1e-3])
    F = np.array([0.0, 0.0, 0.0, 0.0, -0.1, 0.0])
    W = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -0.2])
    assert constraint_violations(h1[:1], h2[:1], h[:1], F[:1], W[:1]) == 0
    assert constraint_violations(h1, h2, h, F, W) == 5


def test_contact_events_finds_lift_off_and_touch_down():
    h = np.r_[np.zeros(10), np.linspace(0.0, 5e-3, 20), np.full(10, 5e-3), np.linspace(5e-3, 0.0, 20), np.zeros(5)]
    lift, down = contact_events(h)
    assert h[lift] > 0.2e-3 >= h[lift - 1]
    assert h[down] <= 0.2e-3 < h[down - 1]
    assert contact_events(np.zeros(20)) == (None, None)


def test_steady_gain_is_the_scalar_riccati_solution():
    """The correction's gain for x+ = a x + w, z = c x + v against the closed-form steady-state
    prior variance P (K = P c / (c^2 P + r))."""
    a, c, q, r = 0.98, 2.0, 0.1, 1.0
    # P = a^2 P r / (c^2 P + r) + q: the positive root of c^2 P^2 + (r - a^2 r - q c^2) P - q r = 0
    B = r - a * a * r - q * c * c
    P = (-B + np.sqrt(B * B + 4 * c * c * q * r)) / (2 * c * c)
    assert steady_gain(a, c, q, r) == pytest.approx(P * c / (c * c * P + r), rel=1e-9)


def test_settings_name_the_key_and_range():
    with pytest.raises(ValueError, match=r"estimator\.horizon = 1 must be an integer in \[2, 200\]"):
        MHESettings(horizon=1).validate()
    with pytest.raises(ValueError, match="estimator.solver"):
        MHESettings(solver="sqp").validate()


def test_scenario_kind_mhe_and_its_keys(tmp_path):
    from hbma_ctrl.app.scenario import load_scenario

    base = '[scenario]\nname = "x"\nkind = "protocol"\nduration_s = 6.0\n[estimator]\n'
    p = tmp_path / "a.toml"
    p.write_text(base + 'kind = "mhe"\nhorizon = 10\nsolver = "ipopt"\n')
    sec = load_scenario(p).role("estimator")
    assert sec.filter == "mhe" and sec.tuning["horizon"] == 10 and sec.tuning["solver"] == "ipopt"
    p.write_text(base + 'kind = "mhe"\nhorizon = 500\n')
    with pytest.raises(ValueError, match=r"\[estimator\] horizon = 500 is out of range \[2, 200\] samples"):
        load_scenario(p)
    p.write_text(base + 'kind = "ekf"\nhorizon = 10\n')
    with pytest.raises(ValueError, match='horizon is a key of the moving-horizon estimator: it needs kind = "mhe"'):
        load_scenario(p)
    p.write_text(base + 'kind = "mhe"\nfilter = "ekf"\n')
    with pytest.raises(ValueError, match="name the estimator twice"):
        load_scenario(p)


# --- the step Function (casadi's virtual machine, a short window) ---------------------------------

@pytest.fixture(scope="module")
def small_step():
    om = observer_model(Actuator(), Pneumatics(), SMALL)
    step, lin = mhe_step_function(om, SMALL), linearise_function(om, SMALL.horizon)

    def fn(M, th, S, U, *rest):
        return step(M, th, S, U, *rest, *lin(M, th, S, U, om.theta))

    return om, fn


def _window(om, N, m_rel, W, factors, shape_h1, pump):
    m = om.m_env * np.asarray(m_rel)
    S = np.vstack([np.full(N + 1, shape_h1), np.zeros(N + 1)])
    U = np.tile(np.array([pump, pump, 0.0])[:, None], (1, N))
    return m, np.array([W, *factors]), S, U


@pytest.mark.slow
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(m_rel=st.lists(st.floats(0.95, 1.5), min_size=4, max_size=4),
       W=st.floats(-0.5, 10.0), b=st.floats(0.4, 2.2), k=st.floats(0.4, 2.2), c=st.floats(0.4, 2.2),
       z_kpa=st.lists(st.floats(-5.0, 45.0), min_size=3, max_size=3), h1_mm=st.floats(0.0, 10.0),
       pump=st.sampled_from([0.0, 1.0]))
def test_step_keeps_the_hard_constraints(small_step, m_rel, W, b, k, c, z_kpa, h1_mm, pump):
    """Any window (states off their bounds too, readings past the range): after the step the load is
    >= 0 and the factors within FACTOR_RANGE (to the QP's tolerance, which the estimator then clips),
    and the estimate has h >= 0, 0 <= h2 <= h1 and F >= 0 (to the contact condition's regularising
    stiffness, micronewtons)."""
    om, fn = small_step
    N = SMALL.horizon
    M, th, S, U = _window(om, N, m_rel, W, (b, k, c), h1_mm * 1e-3, pump)
    Z = np.array(z_kpa) * 1e3
    kinds = np.where(Z >= SMALL.sensor_range, 2.0, 0.0)
    out = fn(M, th, S, U, Z, kinds, np.r_[M[0], th], np.diag(SMALL.prior_var()), om.theta, 1.0)
    if int(out[8]) != 0:
        return  # a failed step is not used (the EKF takes over; test_fallback_is_counted)
    thn = np.asarray(out[1]).ravel()
    h1, h2, h, F, _ = np.asarray(out[5]).ravel()
    tol = 1e-6
    # a start off its bounds is brought back by at most the trust region per step
    if W >= 0 and all(FACTOR_RANGE[0] <= v <= FACTOR_RANGE[1] for v in (b, k, c)):
        assert thn[0] >= -tol
        assert np.all(thn[1:] >= FACTOR_RANGE[0] - tol) and np.all(thn[1:] <= FACTOR_RANGE[1] + tol)
    assert h >= -tol and h2 >= -tol and h2 <= h1 + tol and F >= -EPS_K * max(h2, 0.0) - tol
    assert np.all(np.asarray(out[0]).ravel() > 0)


@pytest.mark.slow
def test_arrival_cost_is_the_ekf_predict_without_a_reading(small_step):
    """With no reading at node 1 the next arrival covariance is the EKF's predict from node 0
    (A P0 A^T + Q at the window's start), not a fixed weight; with one, it shrinks along H."""
    om, fn = small_step
    N = SMALL.horizon
    M, th, S, U = _window(om, N, [1.1, 1.12, 1.14, 1.16], 2.0, (1.0, 1.0, 1.0), 4e-3, 1.0)
    P0 = np.diag(SMALL.prior_var())
    none = np.full(N, float(KIND_NONE))
    out = fn(M, th, S, U, np.zeros(N), none, np.r_[M[0], th], P0, om.theta, 0.0)
    pred, _ = lean_model(om)
    xn, A, _ = pred(np.r_[M[0], th], S[:, 0], U[:, 0], om.theta)
    A = np.asarray(A)
    dm = float(np.asarray(xn).ravel()[0] - M[0])
    wv = SMALL.walk_var()
    Q = np.diag([(SMALL.flow_rel_std * dm) ** 2 + wv[0], *wv[1:]])
    expect = A @ P0 @ A.T + Q
    got = np.asarray(out[4]).reshape(NX, NX, order="F")
    assert np.allclose(got, expect, rtol=1e-6, atol=1e-20)
    ok = np.full(N, float(KIND_OK))
    out2 = fn(M, th, S, U, np.full(N, 20e3), ok, np.r_[M[0], th], P0, om.theta, 0.0)
    got2 = np.asarray(out2[4]).reshape(NX, NX, order="F")
    assert got2[0, 0] < expect[0, 0]


# --- the estimator on rig runs ----------------------------------------------------------------------

def _run(load_g, r1_mm, speed, seed=0, dropout=None, settings=None):
    (trial,) = protocol_trials("nh", platform=Platform(own_mass=0.02), loads_g=[load_g], speeds_pct=[speed],
                               t0_mm=[3.0 if r1_mm > 8 else 2.0], r1_mm=[r1_mm])
    rig = RigSettings(seed=seed)
    (rec,) = simulate_rig([trial], rig)
    if dropout is not None:
        rec.meas = rec.meas.copy()
        rec.meas[dropout] = np.nan
    W = trial.platform.weight
    fs = settings or MHESettings(sample_period=rig.sample_period, sensor_range=rig.sensor_range,
                                 noise_std=rig.noise_std, load_init=W, load_init_std=0.1 * W + 0.01)
    return trial, rec, run_filter("mhe", trial, rec, fs)


@pytest.mark.slow
@pytest.mark.compiling
def test_indexing_newest_reading_constrains_the_newest_node():
    """After step k the window's readings are those of samples k - N + 1 .. k (node j <- sample
    k - N + j), its last interval's command the one acting over the period ending at sample k (the
    command sent before it, through the valve and sensor delays), and the estimate's pressure follows
    the newest reading."""
    (trial,) = protocol_trials("nh", platform=Platform(own_mass=0.02), loads_g=[0.0], speeds_pct=[100.0],
                               t0_mm=[3.0], r1_mm=[12.5])
    rig = RigSettings(seed=0)
    (rec,) = simulate_rig([trial], rig)
    fs = MHESettings(horizon=5, reseed_cost=0.0)  # the MHE's own step at every sample
    f = MHE(trial.actuator, trial.pneumatics, fs)
    timing = CommandTiming(fs.sample_period, fs.valve_delay, fs.sensor_delay)
    N = 5
    for k in range(60):
        u = rec.u[k - 1] if k > 0 else np.zeros(3)
        acting = timing.acting(u, 1 if k > 0 else 0)
        e = f.step(rec.t[k], rec.meas[k], u)
        if k > N:
            assert np.array_equal(f.Z, rec.meas[k - N + 1:k + 1])
            assert np.allclose(f.U[:, -1], acting)
            assert f.last_status == 0
    assert abs(e.p - rec.meas[59]) < 5 * fs.noise_std


@pytest.mark.slow
@pytest.mark.compiling
def test_fallback_is_counted_and_flagged():
    """A failed step (status != 0) gives the EKF's estimate from the MHE's last one, flagged and
    counted; the next step is the MHE's again."""
    trial, rec, _ = _run(400.0, 12.5, 100.0)
    W = trial.platform.weight  # a load prior: no restarts at the companion EKF's lift-off either
    fs = MHESettings(horizon=5, reseed_cost=0.0, load_init=W, load_init_std=0.1 * W + 0.01)
    f = MHE(trial.actuator, trial.pneumatics, fs)
    for k in range(20):
        f.step(rec.t[k], rec.meas[k], rec.u[k - 1] if k > 0 else np.zeros(3))
    assert f.stats()["fallbacks"] == 0
    real = f._fn

    class Failing:
        def __call__(self, *a):
            out = [np.array(o, copy=True) for o in real(*a)]
            out[8][:] = 1.0
            return out

    f._fn = Failing()
    e = f.step(rec.t[20], rec.meas[20], rec.u[19])
    assert "mhe_fallback" in e.flags and f.stats()["fallbacks"] == 1 and f.last_status == -1
    f._fn = real
    f.step(rec.t[21], rec.meas[21], rec.u[20])
    assert f.last_status == 0 and f.stats()["fallbacks"] == 1


@pytest.mark.slow
@pytest.mark.compiling
@pytest.mark.parametrize("load_g,r1_mm", [(0.0, 12.5), (400.0, 12.5), (400.0, 7.5)])
def test_tracks_the_rig_without_breaking_a_constraint(load_g, r1_mm):
    """Nominal load prior, default rig: the height NRMSD within 0.03 or within a quarter of the EKF's
    on the same run (the 7.5 mm chamber saturates the sensor), and no constraint broken."""
    trial, rec, r = _run(load_g, r1_mm, 100.0)
    sc = score(r, trial)
    W = trial.platform.weight
    ekf = score(run_filter("ekf", trial, rec, FilterSettings(load_init=W, load_init_std=0.1 * W + 0.01)), trial)
    assert sc["height_nrmsd"] < max(0.03, 1.25 * ekf["height_nrmsd"])
    assert sc["constraint_violations"] == 0


@pytest.mark.slow
@pytest.mark.compiling
def test_recovers_within_0_2_s_after_a_0_5_s_dropout():
    """50 readings lost mid-inflation (the membrane still rising): 20 samples after the readings
    return the height error is back within 0.3 mm."""
    k0 = 120
    trial, rec, r = _run(200.0, 12.5, 40.0, dropout=slice(k0, k0 + 50))
    err = np.abs(r.est["h"] - rec.truth["h"])
    assert np.all(np.isfinite(r.est["h"][k0:k0 + 50]))
    assert np.max(err[k0 + 50 + 20:k0 + 50 + 60]) < 0.3e-3


@pytest.mark.slow
@pytest.mark.compiling
def test_recovers_within_0_2_s_when_the_readings_leave_saturation():
    """800 g on the 7.5 mm chamber at full speed saturates the 35 kPa sensor; 20 samples after the
    readings come back under the range (venting) the height error is within 0.3 mm."""
    trial, rec, r = _run(800.0, 7.5, 100.0)
    sat = rec.meas >= 35e3
    assert sat.any()
    back = int(np.flatnonzero(sat)[-1]) + 1
    err = np.abs(r.est["h"] - rec.truth["h"])
    assert np.max(err[back + 20:back + 60]) < 0.3e-3
