"""The EKF's compiled step (hbma_ctrl.estimators.ekf_step) against the reference path, and the robot bank's
mapped call against per-chamber calls. No timing is asserted here (see ``hbma-ctrl bench ekf``)."""

from __future__ import annotations

import math
from dataclasses import replace

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.ekf import EKF
from hbma_ctrl.estimators.ekf_step import DET_NAMES, KIND_OK, STEP_IN, STEP_OUT, ekf_step_function
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings, _step_function
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.chamber import STATE_SCALE

ACT = Actuator()
PN = Pneumatics()
FS = FilterSettings()
#: relative agreement of the two paths (the same operations; only the order of a few sums differs)
RTOL = 1e-9


@pytest.fixture(scope="module")
def pair():
    """A filter on the compiled step and one on the reference path, same actuator and settings."""
    return EKF(ACT, PN, FS), EKF(ACT, PN, FS)


def _close(a, b, scale=1.0) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return bool(np.all(np.abs(a - b) <= RTOL * (np.abs(a) + np.abs(b)) + 1e-12 * scale))


def _set(f: EKF, x, P, resting: bool, det) -> None:
    f.reset(0.0, x, P, resting=resting)
    (f._cusum, f._lift, f._lift_start, f._p_lift, f._p_post, f._gated, f._lift_floor, f._excess,
     f._ratio_min) = det
    f._snap, f._replay = None, []


states = st.tuples(
    st.floats(0.0, 45e3),        # the flat pressure the gas mass m gives, Pa
    st.floats(-1.0, 15.0),       # load W, N
    st.floats(0.6, 1.6), st.floats(0.6, 1.6), st.floats(0.7, 1.5),  # b, k, c
    st.floats(-3.0, 1.0),        # log10 of the covariance's spread (scaled)
    st.floats(-0.9, 0.9),        # a correlation between m and the factors
)
detectors = st.tuples(st.floats(0.0, 25.0), st.floats(0.0, 8.0), st.floats(0.0, 5.0),
                      st.floats(0.0, 30e3), st.floats(0.0, 40e3), st.integers(0, 3),
                      st.sampled_from([0.0, 0.0, 1.0, 4.0, 15.0]),  # the load prior's floor on a lift-off, N
                      st.floats(0.0, 12.0),  # the contact phase's excess sum
                      st.sampled_from([0.0, 0.47, 0.8]))  # the lowest b / c taken as flat
commands = st.sampled_from([(1.0, 1.0, 0.0), (0.4, 1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 0.5, 0.2)])


def _state(v):
    p_flat, W, b, k, c, lg, rho = v
    m = (p_flat + ACT.p_env) * ACT.V0 / (ACT.R * ACT.T)
    sd = STATE_SCALE * 10 ** lg * np.array([0.01, 1.0, 0.1, 0.1, 0.1])
    Cr = np.eye(5)
    Cr[0, 2] = Cr[2, 0] = rho
    Cr[0, 4] = Cr[4, 0] = -0.5 * rho
    return np.array([m, W, b, k, c]), Cr * np.outer(sd, sd)


@pytest.mark.parametrize("resting", [True, False], ids=["resting", "contact"])
@pytest.mark.parametrize("reading", ["ok", "missing", "saturated", "outlier"])
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(v=states, det=detectors, u=commands, dz=st.one_of(st.floats(-3e3, 3e3), st.floats(-2e4, 2e4)))
def test_compiled_step_equals_the_reference_path_on_random_states(pair, resting, reading, v, det, u, dz):
    fc, fr = pair
    x, P = _state(v)
    _set(fc, x, P, resting, det)
    _set(fr, x, P, resting, det)
    z = {"ok": max(fr._p_pred + dz, 0.0), "missing": None, "saturated": FS.sensor_range + 1.0,
         "outlier": -1e9}[reading]
    cmd = Command(*u)
    ec = fc.step(0.01, z, cmd)
    er = fr.step_reference(0.01, z, cmd)
    for name in ("h1", "h2", "h", "F", "p"):
        assert _close(getattr(ec, name), getattr(er, name)), name
    assert _close(ec.mean / STATE_SCALE, er.mean / STATE_SCALE)
    assert _close(ec.cov / np.outer(STATE_SCALE, STATE_SCALE), er.cov / np.outer(STATE_SCALE, STATE_SCALE))
    assert _close(fc.last_output_cov, fr.last_output_cov, scale=1e-9)
    assert _close([ec.std[k] for k in ec.std], [er.std[k] for k in ec.std], scale=1e-6)
    assert ec.flags == er.flags
    assert fc.resting == fr.resting
    assert (fc.last_nis is None) == (fr.last_nis is None)
    if fc.last_nis is not None:
        assert _close(fc.last_nis, fr.last_nis)
    assert _close(fc.detector_state(), fr.detector_state())
    assert _close(fc.s, fr.s) and _close(fc.last_A, fr.last_A)


def test_compiled_step_is_the_normal_path_and_agrees_over_a_run():
    """A lifting, loaded run: the Function decides nearly every step (``exact``), and the run's
    estimates equal the reference path's step by step."""
    fc, fr = EKF(ACT, PN, FS), EKF(ACT, PN, FS)
    fc.reset(0.0, [ACT.p_env * ACT.V0 / (ACT.R * ACT.T), 3.0], resting=True)
    fr.reset(0.0, [ACT.p_env * ACT.V0 / (ACT.R * ACT.T), 3.0], resting=True)
    rng = np.random.default_rng(1)
    exact = 0
    p = 0.0
    for i in range(1, 301):
        cmd = Command(1.0, 1.0, 0.0) if i < 200 else Command(0.0, 0.0, 1.0)
        p = p + (60.0 if i < 200 else -80.0)
        z = max(p, 0.0) + 200.0 * rng.standard_normal()
        ec = fc.step(0.01 * i, z, cmd)
        exact += int(fc._step_fn.out[STEP_OUT.index("exact")][0] > 0.5)
        er = fr.step_reference(0.01 * i, z, cmd)
        assert _close([ec.h, ec.F, ec.p], [er.h, er.F, er.p], scale=1e-3) and ec.flags == er.flags
    assert exact >= 290


def test_step_function_is_one_numeric_generable_function():
    f = ekf_step_function(ACT, PN, FS)
    assert f.name_in() == list(STEP_IN) and f.name_out() == list(STEP_OUT)
    assert not f.has_free()
    assert f.size1_in(STEP_IN.index("det")) == len(DET_NAMES)
    cg = ca.CodeGenerator("ekf_step_check.c")
    cg.add(f)  # fails for a Function holding Python callbacks
    assert "ekf_step" in cg.dump()
    # the same Function for another actuator of the family: its numbers come in through theta
    assert ekf_step_function(Actuator(r1=10e-3), PN, FS) is f
    # ... and a trial's own load prior does not build (and compile) another
    assert ekf_step_function(ACT, PN, replace(FS, load_init=2.0, load_init_std=0.2)) is f
    assert ekf_step_function(ACT, PN, replace(FS, noise_std=300.0)) is not f


def test_kind_codes_select_the_update():
    """Input ``kind``: a reading updates (NIS reported), none does not (the predict alone)."""
    f = ekf_step_function(ACT, PN, FS)
    filt = EKF(ACT, PN, FS)
    filt.reset(0.0, [1.05 * ACT.p_env * ACT.V0 / (ACT.R * ACT.T), 2.0], resting=False)
    args = dict(x=filt.x, P=filt.P, s=filt.s, u=[1.0, 1.0, 0.0], theta=filt.theta, resting=0.0,
                z=filt._p_pred + 500.0, det=np.zeros(len(DET_NAMES)))
    upd = f.call({**args, "kind": KIND_OK})
    none = f.call({**args, "kind": 1.0})
    assert float(upd["nis"]) > 0 and float(none["nis"]) == 0.0
    assert not np.allclose(np.asarray(upd["x_next"]), np.asarray(none["x_next"]))


def test_flat_ratio_floor_is_relative_to_the_prior_with_a_sigma_floor():
    """flat_ratio_min: the prior's b / c times exp(-3 sigma), sigma the relative spread of b / c
    (at least FLAT_RATIO_STD_MIN); 0 when b and c are held. A filter's reset sets it from its prior
    (a calibration's hand-over included)."""
    from hbma_ctrl.estimators.ekf_step import FLAT_RATIO_SIGMAS, FLAT_RATIO_STD_MIN, flat_ratio_min

    x = np.array([1e-5, 1.0, 1.0, 1.0, 1.0])
    P = np.diag([1e-16, 1.0, 0.15 ** 2, 0.15 ** 2, 0.2 ** 2])  # the default prior
    assert flat_ratio_min(x, P) == pytest.approx(math.exp(-FLAT_RATIO_SIGMAS * 0.25))
    xc = x.copy()
    xc[2], xc[4] = 0.9, 1.2
    Pc = np.diag([1e-16, 1.0, (0.9 * 0.01) ** 2, 0.01, (1.2 * 0.01) ** 2])  # a tight calibration
    assert flat_ratio_min(xc, Pc) == pytest.approx(0.75 * math.exp(-FLAT_RATIO_SIGMAS * FLAT_RATIO_STD_MIN))
    Pcorr = Pc.copy()
    Pcorr[2, 4] = Pcorr[4, 2] = 0.9 * 1.2 * 0.2 ** 2  # b and c moving together: the ratio is pinned
    Pcorr[2, 2], Pcorr[4, 4] = (0.9 * 0.2) ** 2, (1.2 * 0.2) ** 2
    assert flat_ratio_min(xc, Pcorr) == pytest.approx(0.75 * math.exp(-FLAT_RATIO_SIGMAS * FLAT_RATIO_STD_MIN))
    assert flat_ratio_min(x, np.diag([1e-16, 1.0, 0.0, 0.0, 0.0])) == 0.0
    f = EKF(ACT, PN, FS)
    f.reset(0.0, xc, Pc, resting=True)
    assert f._ratio_min == pytest.approx(flat_ratio_min(xc, Pc))


@pytest.mark.parametrize("path", ["compiled", "reference"])
def test_the_flat_ratio_test_is_off_once_the_membrane_has_left_rest(path):
    """The ratio test's threshold comes from the prior (a calibration's flat b / c of 1.4 gives 1.04);
    once the membrane has left rest the factors are learnt (b / c = 0.92 in contact) and the test is
    off: a loaded chamber that touches down and is pumped again is not taken as free. Armed with the
    prior's threshold, the same pump from rest fires it at once (the control)."""
    m0 = ACT.p_env * ACT.V0 / (ACT.R * ACT.T)
    x_contact = np.array([1.3 * m0, 3.0, 0.97, 1.0, 1.055])  # b / c = 0.92, in contact under 3 N
    P = np.diag(np.array([0.01 * m0, 0.1, 0.01, 0.01, 0.01]) ** 2)
    det = [0.0] * len(DET_NAMES)
    det[DET_NAMES.index("ratio_min")] = 1.04
    step = (lambda f, *a: f.step(*a)) if path == "compiled" else (lambda f, *a: f.step_reference(*a))
    f = EKF(ACT, PN, FS)
    _set(f, x_contact, P, False, det)
    step(f, 0.01, f._p_pred, Command(0.0, 0.0, 0.0))
    assert not f.resting and f.detector_state()[DET_NAMES.index("ratio_min")] == 0.0
    # back at rest (vented) with the learnt factors, then pumped: no ratio lift-off
    x_rest = np.array([m0, 3.0, 0.97, 1.0, 1.055])
    fired = {}
    for armed in (False, True):
        g = EKF(ACT, PN, FS)
        d = list(det)
        d[DET_NAMES.index("ratio_min")] = 1.04 if armed else 0.0
        _set(g, x_rest, P, True, d)
        flags = set()
        for i in range(1, 6):
            est = step(g, 0.01 * i, g._p_pred, Command(1.0, 1.0, 0.0))  # readings as a flat chamber's
            flags |= set(est.flags)
        fired[armed] = "lift_off_ratio" in flags
    assert fired == {False: False, True: True}


def test_a_persistent_excess_in_contact_declares_a_load_change():
    """In contact, with the pressure rising, readings one sigma above the prediction add
    1 - EXCESS_DRIFT to the excess sum per step; above EXCESS_THRESHOLD a load change is declared
    (flag ``load_change``, the load's variance widened) and the sum restarts. Readings at the
    prediction leave it at zero, and a resting membrane does not sum."""
    from hbma_ctrl.estimators.ekf_step import EXCESS_DRIFT, EXCESS_THRESHOLD, FLAG_BITS

    f = ekf_step_function(ACT, PN, FS)
    filt = EKF(ACT, PN, FS)
    filt.reset(0.0, [1.15 * ACT.p_env * ACT.V0 / (ACT.R * ACT.T), 1.0], resting=False)  # lifted
    i_ex = DET_NAMES.index("excess")
    base = dict(x=filt.x, P=filt.P, s=filt.s, u=[0.0, 0.0, 0.0], theta=filt.theta, resting=0.0, kind=1.0)
    for _ in range(5):  # converge the shape's warm start (no reading, valves shut)
        base["s"] = np.asarray(f.call({**base, "z": 0.0, "det": np.zeros(len(DET_NAMES))})["s_next"]).ravel()
    base.update(u=[1.0, 1.0, 0.0], kind=KIND_OK)
    # the innovation is (z - p_pred) / sqrt(S): two readings give the prediction and sqrt(S), Pa
    r0, r1 = (float(f.call({**base, "z": z, "det": np.zeros(len(DET_NAMES))})["innov"]) for z in (0.0, 1e3))
    sqrt_S = 1e3 / (r1 - r0)
    p_pred = -r0 * sqrt_S

    def step(z_sigmas, excess, p_post=0.0):
        det = np.zeros(len(DET_NAMES))
        det[DET_NAMES.index("p_post")] = p_post  # below the prediction: the pressure rises
        det[i_ex] = excess
        return f.call({**base, "z": p_pred + z_sigmas * sqrt_S, "det": det})

    change = 1 << FLAG_BITS.index("load_change")
    out = step(1.0, 0.0)
    assert float(out["det_next"][i_ex]) == pytest.approx(1.0 - EXCESS_DRIFT, rel=1e-6)
    assert not int(out["flags"]) & change
    assert float(step(0.0, 0.0)["det_next"][i_ex]) == 0.0
    out = step(1.0, EXCESS_THRESHOLD - 0.5)  # crosses the threshold
    assert int(out["flags"]) & change and float(out["det_next"][i_ex]) == 0.0
    assert int(out["flags"]) & 1 << FLAG_BITS.index("load_excess")  # told from the NIS sum's
    P_next = np.asarray(out["P_next"]).reshape(5, 5, order="F")
    P_quiet = np.asarray(step(1.0, 0.0)["P_next"]).reshape(5, 5, order="F")
    assert P_next[1, 1] > P_quiet[1, 1]  # the load's variance was widened before the update
    # the pressure falling (p_post above the prediction): no sum
    assert float(step(1.0, 5.0, p_post=p_pred + 1e3)["det_next"][i_ex]) == 0.0
    # resting: the sum is the contact phase's only (a reading at the flat prediction, so not gated)
    det = np.zeros(len(DET_NAMES))
    det[i_ex] = 5.0
    zs = (0.14 * ACT.p_env, 0.16 * ACT.p_env)  # about the flat chamber's 0.15 p_env
    r0, r1 = (float(f.call({**base, "resting": 1.0, "z": z, "det": det})["innov"]) for z in zs)
    rest = f.call({**base, "resting": 1.0, "z": zs[0] - r0 * (zs[1] - zs[0]) / (r1 - r0), "det": det})
    assert not int(rest["flags"]) & 1  # not gated
    assert float(rest["det_next"][i_ex]) == 0.0


@pytest.fixture(scope="module")
def bank_model(robot_bank):
    return robot_bank  # make_model(RobotDesign(n_layers=1).validate(), Pneumatics(), "per_chamber")


def test_robot_bank_mapped_call_equals_per_chamber_calls(bank_model):
    n = 3
    s = ChamberEKFSettings()
    bank = ChamberEKFBank(bank_model, n, s)
    single = _step_function(bank_model, s)
    rng = np.random.default_rng(0)
    bank.reset(np.array([1e3, 5e3, 12e3]))
    X = bank.X + np.vstack([rng.uniform(0, 0.05, n), rng.uniform(-0.1, 0.1, (3, n))])
    P = bank.P
    w = rng.uniform(0, 1, (3, n))
    W = np.array([0.2, 1.0, 3.0])
    z, use, reopen = np.array([2e3, 6e3, 30e3]), np.array([1.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0])
    out = bank._call(X, P, w, W, z, use, reopen)
    for i in range(n):
        ref = single(X[:, i], P[:, i], w[:, i], W[i], z[i], use[i], reopen[i])
        for j, r in enumerate(ref):
            got = out[j].reshape(n, -1)[i]
            assert _close(got, np.asarray(r).ravel(), scale=1e-6), (i, j)


@pytest.mark.slow
def test_bench_ekf_rows_share_the_rig_runs_and_report_ratios():
    """``bench ekf`` on one trial: the EKF's compiled step and reference path score the same; the
    filterpy row runs on the same model and its ratio is reported (its value is not asserted)."""
    from hbma_ctrl.app.cli.estimators import bench_ekf
    from hbma_ctrl.app.scenes.evaluate import BENCH_FILTERS

    res = bench_ekf({"loads_g": [400.0], "speeds_pct": [100.0], "t0_mm": [3.0], "r1_mm": [7.5]},
                    filters=("ekf", "ekf_reference", "filterpy"))
    f = res["filters"]
    assert set(f) == {"ekf", "ekf_reference", "filterpy"} and set(f) <= set(BENCH_FILTERS)
    for k in ("height_nrmsd", "force_rmse_n", "nis_mean", "nees_mean"):
        assert _close(f["ekf"][k], f["ekf_reference"][k]), k
    assert np.isfinite(f["filterpy"]["height_nrmsd"]) and f["filterpy"]["height_nrmsd"] < 0.5
    assert set(res["ratios"]) == {"ekf_reference_over_ekf_step_median", "filterpy_over_ekf_step_median"}
    assert all(v > 0 for v in res["ratios"].values())


@pytest.mark.slow
def test_bench_ekf_axes_add_rows_with_their_settings_and_the_pareto_reads_them(tmp_path):
    """``substeps`` and ``membranes`` add an EKF and a UKF row per value other than the default's,
    each scored on the same rig runs with its own settings; the estimator Pareto plot takes every row
    (grouped by filter); bad values name the flag."""
    import json

    import pytest

    from hbma_ctrl.app.bench.plots import estimator_points
    from hbma_ctrl.app.cli.estimators import bench_ekf, parse_axes

    res = bench_ekf({"loads_g": [400.0], "speeds_pct": [100.0], "t0_mm": [3.0], "r1_mm": [12.5]},
                    filters=("ekf", "ukf"), substeps=(1, 2), membranes=("exact", "cap"))
    f = res["filters"]
    assert set(f) == {"ekf", "ukf", "ekf nsub=2", "ukf nsub=2", "ekf cap", "ukf cap"}
    assert (f["ekf nsub=2"]["nsub"], f["ekf nsub=2"]["membrane"]) == (2, "exact")
    assert (f["ukf cap"]["nsub"], f["ukf cap"]["membrane"]) == (1, "cap")
    # on the default rig (the exact membrane) the cap's law costs accuracy
    assert f["ekf cap"]["height_nrmsd"] > 2 * f["ekf"]["height_nrmsd"]
    (tmp_path / "b.json").write_text(json.dumps(res))
    pts, _ = estimator_points(tmp_path / "b.json")
    assert {(p[1][0], p[0]) for p in pts} >= {("ekf", "nsub=2"), ("ukf", "cap")}
    with pytest.raises(ValueError, match="--substeps"):
        parse_axes("0,2", "cap")
    with pytest.raises(ValueError, match="--membranes: 'plate'"):
        parse_axes("1", "plate")


def test_classify_expr_gives_classify_measurements_kind_for_every_reading():
    """The casadi twin of classify_measurement (the generated steps' reading test) gives the same kind
    for dropouts, +-inf, both physical bounds and the sensor range, at and beside each edge."""
    from hbma_ctrl.estimators.common import (MEAS_MISSING, MEAS_OK, MEAS_OUTLIER, MEAS_SATURATED, classify_expr,
                                   classify_measurement)

    rng, lo, hi = 50e3, -101e3, 75e3
    z = ca.SX.sym("z")
    f = ca.Function("kind", [z], [ca.vertcat(*classify_expr(z, rng, lo, hi))])
    names = (MEAS_MISSING, MEAS_OUTLIER, MEAS_SATURATED, MEAS_OK)
    edges = [lo, hi, rng, 0.0]
    values = [math.nan, math.inf, -math.inf] + [e + d for e in edges for d in (-1e-9 * abs(e) - 1e-12, 0.0,
                                                                               1e-9 * abs(e) + 1e-12)]
    for v in values:
        flags = np.asarray(f(v)).ravel()
        assert flags.sum() == 1.0, v
        assert names[int(np.argmax(flags))] == classify_measurement(v, rng, lo, hi), v
