"""EKF/UKF against the mismatched rig: API, measurement handling, extremes, convergence, load steps."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from checkout import ROOT
from hbma_ctrl.estimators.common import FilterSettings, guard_cov
from hbma_ctrl.estimators.ekf import EKF
from hbma_ctrl.estimators.ukf import UKF
from hbma_ctrl.app.scenes.evaluate import run_filter, score
from hbma_ctrl.app.metrics import nrmsd
from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.core.interfaces import Command, Estimate
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.chamber import STATE_SCALE
from hbma_ctrl.sim.rig import Rig, RigRecord, RigSettings, simulate_rig
from hbma_ctrl.sim.trial import InputSchedule, Trial


G = 9.80665

def parse_section(raw: dict):
    """The [estimator] table (edge units) -> its SI settings, through the scenario schema."""
    return parse_role("estimator", raw)



def _trial(load=0.4, speed=1.0, r1=12.5e-3, t0=3e-3, t_inf=3.0, dur=4.0, rows=None):
    sched = InputSchedule(rows) if rows else InputSchedule.inflate_deflate(speed, t_inf)
    return Trial(Actuator(r1=r1, t0=t0), Pneumatics(), Platform(load=load, own_mass=0.02 if load > 0 else 0.0),
                 sched, dur, "t")


def _rec(trial, **rig):
    (rec,) = simulate_rig([trial], RigSettings(**rig))
    return rec


def _assert_spd(cov):
    assert np.allclose(cov, cov.T, rtol=0, atol=1e-12 * np.abs(cov).max())
    scale = STATE_SCALE
    w = np.linalg.eigvalsh(cov / np.outer(scale, scale))
    assert w.min() > 0


def _run(kind, trial, rec, settings=None, check_spd=True):
    f = EKF(trial.actuator, trial.pneumatics, settings) if kind == "ekf" else \
        UKF(trial.actuator, trial.pneumatics, settings)
    ests = []
    for k in range(len(rec.t)):
        u = Command(*rec.u[k - 1]) if k > 0 else Command()
        e = f.step(float(rec.t[k]), rec.meas[k], u)
        if check_spd:
            _assert_spd(e.cov)
        ests.append(e)
    return f, ests


@pytest.fixture(scope="module")
def loaded():
    tr = _trial(0.4, 1.0)
    return tr, _rec(tr)


def test_step_api_and_flags(loaded):
    tr, rec = loaded
    f, ests = _run("ekf", tr, rec)
    e = ests[150]
    assert isinstance(e, Estimate)
    assert e.state_names == ("m", "W", "b", "k", "c") and e.mean.shape == (5,) and e.cov.shape == (5, 5)
    assert set(e.std) == {"h1", "h2", "h", "F", "p"}
    assert e.h == pytest.approx(e.h1 - e.h2)
    assert "resting" in ests[0].flags
    assert any("lift_off" in x.flags for x in ests[:50])
    assert not any("not_converged" in x.flags for x in ests[50:250])
    with pytest.raises(ValueError, match="before the last step"):
        f.step(0.0, 0.0, Command())


def test_tracks_height_force_and_beats_open_loop(loaded):
    tr, rec = loaded
    res = run_filter("ekf", tr, rec, FilterSettings())
    from hbma_ctrl.app.scenes.evaluate import _open_loop

    res.open_loop_h = _open_loop([tr], 0.01)[0][: len(rec.t)]
    s = score(res, tr)
    assert s["height_nrmsd"] < 0.05
    assert s["height_nrmsd"] < 0.5 * s["height_nrmsd_open_loop"]
    assert s["force_steady_rel_err"] < 0.10


def test_deterministic(loaded):
    tr, rec = loaded
    _, a = _run("ekf", tr, rec, check_spd=False)
    _, b = _run("ekf", tr, rec, check_spd=False)
    assert [x.h for x in a] == [x.h for x in b]
    assert np.array_equal(a[-1].cov, b[-1].cov)


def test_missing_reading_skips_the_update(loaded):
    tr, rec = loaded
    f = EKF(tr.actuator, tr.pneumatics)
    for k in range(100):
        f.step(float(rec.t[k]), rec.meas[k], Command(*rec.u[k - 1]) if k else Command())
    P0 = f.P.copy()
    e = f.step(float(rec.t[100]), float("nan"), Command(*rec.u[99]))
    assert "missing" in e.flags and f.last_nis is None
    assert np.trace(f.P / np.outer(STATE_SCALE, STATE_SCALE)) >= \
        np.trace(P0 / np.outer(STATE_SCALE, STATE_SCALE))  # predict only: no information
    e = f.step(float(rec.t[101]), None, Command(*rec.u[100]))
    assert "missing" in e.flags


def test_dropouts():
    tr = _trial(0.2, 0.8)
    rec = _rec(tr, dropout_prob=0.3, seed=5)
    f, ests = _run("ekf", tr, rec)
    assert sum("missing" in e.flags for e in ests) > 50
    h = np.array([e.h for e in ests])
    assert nrmsd(h, rec.truth["h"]) < 0.08


@pytest.mark.slow
def test_saturation_for_seconds():
    # 400 g on r1 12.5 mm: contact at about 24 kPa; the sensor tops out at 18 kPa for seconds
    tr = _trial(0.4, 1.0, dur=4.0, t_inf=3.0)
    rec = _rec(tr, sensor_range=18e3)
    s = FilterSettings(sensor_range=18e3)
    f, ests = _run("ekf", tr, rec, s)
    sat = np.array(["saturated" in e.flags for e in ests])
    assert sat.sum() * 0.01 > 2.0
    p = np.array([e.p for e in ests])
    assert np.all(p[sat] > 18e3 - 3 * 200.0)  # the estimate respects "p >= range"
    h = np.array([e.h for e in ests])
    err = np.abs(h - rec.truth["h"])
    # the height rides on the model while saturated: a bounded error, not a collapse
    assert np.max(err[sat]) < 0.2 * rec.truth["h"].max()
    std_h = np.array([e.std["h"] for e in ests])
    i = np.nonzero(sat)[0]
    assert std_h[i[-1]] > std_h[i[0]]  # and the covariance says it knows less and less
    assert np.max(err[~sat][-50:]) < 1e-3  # after the vent: tracking again


def test_flat_membrane_never_lifts():
    tr = _trial(3.0, 1.0, dur=3.0, t_inf=2.0)  # 3 kg: pi r1^2 * 35 kPa = 17 N < 29 N
    rec = _rec(tr)
    assert rec.truth["h"].max() == 0.0
    f, ests = _run("ekf", tr, rec)
    assert all("resting" in e.flags for e in ests)
    assert max(e.h for e in ests) == 0.0
    area = math.pi * tr.actuator.r1 ** 2
    assert all(e.F == pytest.approx(max(area * e.p, 0.0), rel=1e-6, abs=1e-9) for e in ests[5:])


def test_zero_flow_stays_flat_and_spd():
    tr = _trial(0.0, rows=((0.0, 0.0, 0.0, 0.0),), dur=2.0)
    rec = _rec(tr)
    f, ests = _run("ekf", tr, rec)
    assert max(abs(e.h) for e in ests) < 0.5e-3
    assert max(e.std["h"] for e in ests) < 1e-3


@pytest.mark.slow
def test_snap_through_survives():
    # README Model §4: t0 = 2 mm, r1 = 7.5 mm, 400 g: the dead-load path folds near 33-34 kPa
    tr = _trial(0.4, 1.0, r1=7.5e-3, t0=2e-3, dur=4.0, t_inf=3.0)
    rec = _rec(tr, sensor_range=60e3)
    f, ests = _run("ekf", tr, rec, FilterSettings(sensor_range=60e3))
    h = np.array([e.h for e in ests])
    assert np.all(np.isfinite(h))
    assert nrmsd(h, rec.truth["h"]) < 0.15


def _height_errors(f, tr, rec, start):
    err = []
    for k in range(start, len(rec.t)):
        e = f.step(float(rec.t[k]), rec.meas[k], Command(*rec.u[k - 1]) if k else Command())
        err.append(abs(e.h - rec.truth["h"][k]))
    return np.array(err)


@pytest.mark.parametrize("factor", [0.5, 1.5])
def test_converges_from_a_gas_mass_wrong_by_half(loaded, factor):
    # the gas let in so far off by -50 % or +50 %, restarted mid-inflation at 1 s (5.7 mm): from
    # 1 s later on the height is as good as the filter's that never lost track. (Far past the load
    # path's pressure maximum two gas masses give the same pressure, and pressure alone cannot
    # tell the branch: a start there is not covered.)
    tr, rec = loaded
    ref = EKF(tr.actuator, tr.pneumatics)
    k0 = 100  # 1 s: in contact, pumping
    ref_err = _height_errors(ref, tr, rec, 0)
    f0 = EKF(tr.actuator, tr.pneumatics)
    _height_errors(f0, tr, rec.__class__(rec.name, rec.t[:k0 + 1], rec.u[:k0 + 1], rec.meas[:k0 + 1],
                                         {k: v[:k0 + 1] for k, v in rec.truth.items()}), 0)
    x = f0.x.copy()
    m_env = f0.model.m_env
    wrong = x.copy()
    wrong[0] = m_env + factor * (x[0] - m_env)  # the gas let in so far, off by 50 %
    P = f0.P.copy()
    P[0, :] = P[:, 0] = 0.0
    P[0, 0] = (0.5 * (x[0] - m_env)) ** 2
    f = EKF(tr.actuator, tr.pneumatics)
    f.reset(rec.t[k0], wrong, P, resting=False)
    err = _height_errors(f, tr, rec, k0 + 1)
    after = slice(100, 200)  # from 1 s after the start to the end of the inflation
    assert abs(wrong[0] - x[0]) > 5 * math.sqrt(f0.P[0, 0])  # it did start wrong
    assert np.max(err[after]) < max(2 * np.max(ref_err[k0 + 1:][after]), 0.5e-3)


@pytest.mark.parametrize("factor", [0.5, 1.5])
def test_converges_from_a_load_guess_wrong_by_half(loaded, factor):
    # a load guess 50 % heavy: the flat phase holds it until the lift-off shows the true load; 50 %
    # light: the model lifts early, and the contact model's pressure shortfall pulls the load up
    tr, rec = loaded
    ref_err = _height_errors(EKF(tr.actuator, tr.pneumatics), tr, rec, 0)
    f = EKF(tr.actuator, tr.pneumatics, FilterSettings(load_init=factor * tr.platform.weight))
    err = _height_errors(f, tr, rec, 0)
    lift = int(np.argmax(rec.truth["h"] > 0))
    after = slice(lift + 100, 300)  # 1 s after the lift-off to the end of the inflation
    assert np.max(err[after]) < max(2 * np.max(ref_err[after]), 0.5e-3)


@pytest.mark.slow
def test_load_steps_are_tracked():
    act, pn = Actuator(), Pneumatics()
    rig = Rig(act, pn, Platform(load=0.2, own_mass=0.02), RigSettings(seed=2))
    f = EKF(act, pn)
    sched = InputSchedule(((0.0, 0.6, 1.0, 0.0), (1.0, 0.3, 1.0, 0.0)))
    cmd = Command()
    F_est, F_true = [], []
    for k in range(501):
        t = k * 0.01
        if k == 200:
            rig.set_load(0.6)
        if k == 350:
            rig.set_load(0.2)
        e = f.step(t, rig.measure(), cmd)
        F_est.append(e.F)
        F_true.append(rig.truth()["F"])
        cmd = Command(*sched.at(t))
        rig.apply(cmd)
    F_est = np.array(F_est)
    assert np.mean(F_est[300:350]) == pytest.approx(0.62 * G, rel=0.15)  # 1-1.5 s after the step
    assert np.mean(F_est[450:500]) == pytest.approx(0.22 * G, rel=0.15)


def test_ukf_same_api_and_comparable(loaded):
    tr, rec = loaded
    _, ests = _run("ukf", tr, rec)
    h = np.array([e.h for e in ests])
    assert nrmsd(h, rec.truth["h"]) < 0.08
    assert ests[-1].state_names == ("m", "W", "b", "k", "c")


def joseph_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, innov: float, R: float,
                  PHt: np.ndarray | None = None, S: float | None = None):
    """Reference (numpy) scalar Kalman update in Joseph form, against which the compiled one is checked.

    Returns (x+, P+, S, K).

    ``PHt`` (P H^T) and ``S`` may be given (the UKF passes its cross-covariance and innovation
    variance); otherwise they are formed from H. The gain solves S K^T = (P H^T)^T; for a scalar
    measurement that is a division by S > 0, checked.
    """
    H = np.asarray(H, dtype=float).reshape(1, -1)
    if PHt is None:
        PHt = P @ H.T
    if S is None:
        S = float((H @ PHt)[0, 0]) + R
    if not (S > 0 and math.isfinite(S)):
        raise FloatingPointError(f"innovation variance {S} is not positive")
    K = np.linalg.solve(np.array([[S]]), np.reshape(PHt, (-1, 1)).T).T  # (n, 1)
    IKH = np.eye(P.shape[0]) - K @ H
    Pn = IKH @ P @ IKH.T + R * (K @ K.T)
    return x + K[:, 0] * innov, Pn, S, K[:, 0]


def test_numerics_guards():
    # Joseph update keeps a PSD covariance even with a gain far from optimal (huge R)
    P = np.diag([1e-14, 1.0, 0.01, 0.01, 0.01])
    P[2, 4] = P[4, 2] = 0.009  # the flat phase's ridge: b and c strongly correlated
    H = np.array([2e10, 300.0, 0.0, 1e4, 0.0])
    x, Pn, S, K = joseph_update(np.zeros(5), P, H, 100.0, 4e4)
    assert S > 4e4 and np.allclose(Pn, Pn.T)
    bad = np.array([[1.0, 2.0], [2.0, 1.0]])  # indefinite
    G = guard_cov(bad, 1e-6, np.ones(2))
    assert np.linalg.eigvalsh(G).min() >= 1e-6 * (1 - 1e-9)
    # the compiled update agrees with the numpy reference
    f = EKF(Actuator(), Pneumatics())
    out = f._upd(np.zeros(5), P, H, 100.0, 4e4, 0.0, np.ones(5))
    assert np.allclose(out[1].reshape(5, 5, order="F"), Pn, rtol=1e-9, atol=1e-30)
    # held states (Schmidt): they do not move, and the covariance is the Joseph form of the
    # masked gain -- the exact covariance of that suboptimal update, still SPD
    keep = np.array([1.0, 1.0, 0.0, 0.0, 0.0])
    out = f._upd(np.zeros(5), P, H, 100.0, 4e4, 0.0, keep)
    Km = keep * (P @ H) / (H @ P @ H + 4e4)
    IKH = np.eye(5) - np.outer(Km, H)
    ref = IKH @ P @ IKH.T + 4e4 * np.outer(Km, Km)
    assert np.all(out[0][2:] == 0.0) and out[0][0] != 0.0
    assert np.allclose(out[1].reshape(5, 5, order="F"), ref, rtol=1e-9, atol=1e-30)
    assert np.allclose(ref[2:, 2:], P[2:, 2:], rtol=1e-12)  # held states keep their spread
    _assert_spd(ref)


def test_settings_and_section_errors():
    with pytest.raises(ValueError, match="estimator.noise_std"):
        FilterSettings(noise_std=0.0).validate()
    with pytest.raises(ValueError, match="estimator.nsub"):
        FilterSettings(nsub=0).validate()
    with pytest.raises(ValueError, match="did you mean filter"):
        parse_section({"filtr": "ekf"})
    with pytest.raises(ValueError, match=r"\[estimator\] filter = 'pf' is not allowed"):
        parse_section({"filter": "pf"})
    sec = parse_section({"noise_std_kpa": 0.3, "load_steps_g": [[1.0, 200.0]], "compare_ukf": True})
    assert sec.tuning["noise_std"] == pytest.approx(300.0)
    assert sec.load_steps == ((1.0, 0.2),)
    with pytest.raises(ValueError, match="load_steps_g"):
        parse_section({"load_steps_g": [[2.0, 100.0], [1.0, 50.0]]})


@pytest.mark.slow
def test_scene_writes_estimate_and_metrics(tmp_path):
    from hbma_ctrl.app.scenario import load_scenario
    from hbma_ctrl.app.scenes.estimator import run_scene

    p = tmp_path / "s.toml"
    p.write_text("""
[scenario]
name = "t"
kind = "single"
duration_s = 1.5
[load]
mass_g = 200.0
own_mass_g = 20.0
[inputs]
schedule = [[0.0, 80.0, 1.0, 0.0], [1.0, 0.0, 0.0, 1.0]]
[rig]
seed = 1
[estimator]
filter = "ekf"
compare_ukf = true
load_steps_g = [[0.8, 300.0]]
""")
    m = run_scene(load_scenario(p), tmp_path / "out")
    est = m["estimator"]
    for key in ("height_nrmsd", "height_nrmsd_open_loop", "pressure_nrmsd", "force_rmse_n", "nees_mean",
                "nis_mean", "step_us_median"):
        assert est[key] is not None and est[key] >= 0
    assert "ukf" in est and est["ukf"]["height_nrmsd"] >= 0
    head = (tmp_path / "out" / "estimate.csv").read_text().splitlines()[0]
    assert "h_true_mm" in head and "h_est_mm" in head and "F_est_n" in head and "dead_volume_factor" in head
    assert len((tmp_path / "out" / "estimate.csv").read_text().splitlines()) == 152


def test_record_type():
    rec = _rec(_trial(0.0, 1.0, dur=0.2, t_inf=0.1))
    assert isinstance(rec, RigRecord) and rec.u.shape == (len(rec.t), 3)


@pytest.mark.slow
def test_nominal_load_prior_predicts_a_lift_off_the_saturated_sensor_hides():
    """r1 7.5 mm with 800 g lifts off at ~44 kPa, above the 35 kPa sensor range: a filter that must
    detect the lift-off cannot; one that starts from the protocol's calibrated weight predicts it."""
    from hbma_ctrl.estimators.common import FilterSettings
    from hbma_ctrl.app.scenes.evaluate import evaluate_trials
    from hbma_ctrl.core.params import Platform
    from hbma_ctrl.sim.batch import protocol_trials

    (tr,) = protocol_trials("nh", platform=Platform(own_mass=0.02), loads_g=(800,), speeds_pct=(100,),
                            t0_mm=(3,), r1_mm=(7.5,))
    (blind,) = evaluate_trials([tr], "ekf", settings=FilterSettings(), with_series=False)
    (prior,) = evaluate_trials([tr], "ekf", settings=FilterSettings(load_prior="nominal"), with_series=False)
    assert prior.scores["height_nrmsd"] < 0.5 * blind.scores["height_nrmsd"]
    assert prior.scores["height_nrmsd"] < 0.6 * prior.scores["height_nrmsd_open_loop"]
    with pytest.raises(ValueError, match="estimator.load_prior"):
        FilterSettings(load_prior="guess").validate()


@pytest.mark.sweep  # a count over 6 rig seeds and 48 filter runs: minutes, with the sweeps
def test_a_load_prior_rules_out_the_false_lift_offs_of_a_heavy_loads_flat_rise():
    """600 and 800 g on the 7.5 mm chamber lift at 34-46 kPa, at or above the 35 kPa range. Through
    their long flat rise the rig's flow falls short of the model's and the lift-off detector fired
    (800 g taken as lifting at 21 kPa, height NRMSD 4.1 in the protocol). The lift-off sum's drift
    now covers the default rig's tilted pump map (LIFT_RISE_DRIFT: 0 and 1 false lift-offs of 24 with
    and without a prior); on a map tilted twice as much (compressor_tilt 0.4) the sum still fires.
    There a filter told the load (10 %) rejects a lift-off more than LIFT_PRIOR_SIGMAS below it; the
    same prior at 100 % (no floor) does not. Six rig noise seeds, four trials each: 3 false lift-offs
    of 24 against 11 when measured (README, Estimation)."""
    from hbma_ctrl.estimators.common import FilterSettings
    from hbma_ctrl.estimators.ekf_step import lift_floor
    from hbma_ctrl.app.scenes.evaluate import aggregate, evaluate_trials
    from hbma_ctrl.core.params import Platform
    from hbma_ctrl.sim.batch import protocol_trials

    trials = protocol_trials("nh", platform=Platform(own_mass=0.02, damping=20.0), loads_g=(600, 800),
                             speeds_pct=(100,), t0_mm=(2, 3), r1_mm=(7.5,))
    W = trials[-1].platform.weight
    assert lift_floor(FilterSettings(load_init=W, load_init_std=0.1 * W)) == pytest.approx(0.7 * W)
    assert lift_floor(FilterSettings(load_init=W, load_init_std=W)) == 0.0
    assert lift_floor(FilterSettings()) == 0.0  # no prior, no floor
    false_lifts, rejected = {}, {}
    for rel in (0.1, 1.0):
        n = m = 0
        for seed in range(6):
            rig = RigSettings(seed=seed, modulus_scale=1.15, flow_scale=0.9, V0_scale=1.2, sensor_range=35e3,
                              compressor_tilt=0.4)
            res = evaluate_trials(trials, "ekf", rig, FilterSettings(load_prior="nominal", load_prior_rel_std=rel),
                                  with_series=False)
            n += sum(r.scores["height_nrmsd"] > 0.5 for r in res)
            m += aggregate(res)["trials_with_implausible_lift_off"]
        false_lifts[rel], rejected[rel] = n, m
    assert false_lifts[0.1] <= 4 and false_lifts[1.0] >= 8, false_lifts
    # the rejections are counted (metrics.json: lift_offs_implausible, trials_with_implausible_lift_off)
    assert rejected[0.1] >= 4 and rejected[1.0] == 0, rejected


@pytest.mark.slow
def test_a_free_membrane_lifting_in_the_pumps_first_samples_is_not_taken_as_flat():
    """Unknown load, the free 7.5 mm chamber at 60-100 % speed on the structured rig: the membrane
    lifts within the pump's first samples, while the flow and dead-volume factors are still wide.
    Filtered as flat, the shortfall went into them (b / c 0.38 in 50 ms) and the membrane was held
    flat for seconds (height NRMSD 0.46-0.57 on 3 of these 36 runs when measured). A b / c more than
    FLAT_RATIO_SIGMAS below its prior now lifts it, re-filtered from the last posterior at ambient
    pressure: every run within 0.15 (0.09 at most when measured)."""
    from dataclasses import replace

    from hbma_ctrl.app.scenes.evaluate import evaluate_trials
    from hbma_ctrl.app.scenario import load_scenario
    from hbma_ctrl.system.sections import filter_settings_for

    scn = load_scenario(ROOT / "scenarios" / "ekf_protocol_unknown_load.toml")
    rig = scn.role("rig").validate()
    fs = filter_settings_for(scn.role("estimator"), rig).validate()
    assert fs.load_init is None
    names = [f"t{t0}_r7.5_m0_s{v}" for t0 in (2, 3) for v in (60, 80, 100)]
    trials = [tr for tr in scn.trials() if tr.name in names]
    assert len(trials) == 6
    worst, by_ratio = {}, 0
    for seed in range(6):
        for r in evaluate_trials(trials, "ekf", replace(rig, seed=seed), fs, with_series=True):
            worst[(seed, r.name)] = r.scores["height_nrmsd"]
            by_ratio += r.scores["lift_offs_ratio"]  # counted (flag lift_off_ratio; metrics.json)
            first = next(k for k, f in enumerate(r.flags) if "resting" not in f)
            assert r.t[first] <= 0.1, (seed, r.name, r.t[first])  # lifted within 0.1 s
    assert max(worst.values()) <= 0.15, max(worst.items(), key=lambda kv: kv[1])
    assert by_ratio >= 3, by_ratio  # the three runs held flat before, at least


def test_aggregate_scores_each_protocol_scenario():
    """The estimator's per-scenario criterion: trials grouped by protocol cell (t0 x r1 x load), the
    EKF's mean NRMSD over the cell's speeds against the open loop's; never-lifting trials (NaN)
    left out."""
    from hbma_ctrl.app.scenes.evaluate import TrialResult, aggregate

    def res(name, e, o):
        sc = {k: 1.0 for k in ("pressure_nrmsd", "force_rmse_n", "nees_mean", "nis_mean",
                               "step_us_median", "height_rmse_mm")}
        sc.update(height_nrmsd=e, height_nrmsd_open_loop=o, force_steady_rel_err=float("nan"),
                  rig_status="ok")
        z = np.zeros(1)
        return TrialResult(name, z, {}, {}, z, None, z, z, z, [], sc)

    agg = aggregate([res("t3_r10_m200_s20", 0.02, 0.10), res("t3_r10_m200_s60", 0.08, 0.10),
                     res("t3_r10_m400_s20", 0.06, 0.10), res("t3_r10_m400_s60", float("nan"), float("nan")),
                     res("t2_r10_m400_s60", 0.01, 0.10)])
    assert agg["n_trials"] == 5 and agg["n_scenarios"] == 3
    assert agg["scenarios_at_half_open_loop"] == 2  # (0.02 + 0.08) / 0.2 = 0.5 counts; 0.6 does not
    assert agg["worst_ratio_scenario"] == "t3_r10_m400"
    assert agg["scenario_ratio_to_open_loop_max"] == pytest.approx(0.6)
    assert agg["height_ratio_to_open_loop_max"] == pytest.approx(0.8)  # the worst single trial


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.5, 3.0), st.floats(-1.0, 20.0), st.floats(0.5, 2.0), st.floats(0.5, 2.0), st.floats(0.5, 2.0),
       st.booleans(), st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
       st.one_of(st.floats(-2e3, 60e3), st.just(float("nan"))))
def test_one_step_from_anywhere_keeps_the_covariance_spd(excess, W, b, k, c, resting, u, z):
    """Over the whole state space (gas from below ambient to 3x the chamber's, loads from the dead
    zone to 20 N, every factor over its allowed range, either mode, any command, any reading incl.
    saturated and missing): a step returns finite outputs or flags the model, and the covariance
    stays symmetric positive definite."""
    f = EKF(Actuator(), Pneumatics())
    m_env = f.model.m_env
    f.reset(0.0, [m_env * (1.0 + excess), W, b, k, c], resting=resting)
    e = f.step(0.01, z, Command(*u))
    _assert_spd(e.cov)
    assert np.all(np.isfinite(e.mean))
    assert np.isfinite(e.h) or "not_converged" in e.flags or "model_failure" in e.flags
