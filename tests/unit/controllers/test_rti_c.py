"""The RTI QP data (one Function: generated C for rti_c_osqp, casadi's virtual machine for rti_osqp)
against the QP written in numpy and IPOPT, and the robot NMPC's held linearisation (lin_every) against
linearising at every stage."""

from dataclasses import replace

import numpy as np
import pytest

from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.controllers.mpc_solvers import _Problem
from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.controllers.mpc_settings import WEIGHTS, weights_of
from hbma_ctrl.controllers.rti_c import _RtiOsqp, qp_data_function
from oracles.rti_qp import qp_matrices
from hbma_ctrl.core.interfaces import Estimate, Reference
from hbma_ctrl.core.params import Actuator, Pneumatics


@pytest.fixture(scope="module")
def model(prediction_model):
    # PredictionModel(Actuator(), Pneumatics(), load_max=MPCSettings().load_max): the shared one, while
    # the MPC's load_max is the model's default
    assert prediction_model.load_max == MPCSettings().load_max
    return prediction_model


def _settings(variant: str) -> MPCSettings:
    # a generous budget: the comparison is of the solutions, never of the machine's load
    return MPCSettings(variant=variant, budget=10.0).validate()


TUNED = dict(w_terminal=2.0, w_rate=(0.05, 0.004, 0.01), w_input=(0.001, 0.003, 0.0), c_input=(0.03, 0.0, 0.01),
             w_slack=500.0, c_slack=2000.0, w_height=1.5)


@pytest.mark.slow
@pytest.mark.parametrize("h_min, weights", [(0.0, {}), (2e-3, {}), (0.0, TUNED)])
def test_qp_data_equals_the_numpy_qp(model, h_min, weights):
    """The generated data (P, A, q, l, u) equals the QP written in numpy, on a
    plan that varies along the horizon (no shift), without a lower height bound (its rows left out of
    the pattern), with one, and with other cost weights (an input of the data, not constants in it)."""
    s = replace(_settings("rti_c_osqp"), h_min=h_min, **weights).validate()
    new = _RtiOsqp(model, s)
    N = s.horizon
    x0 = model.x_at_height(5e-3, 0.4)
    pr = _Problem(x0, 0.4, 1e-4, 200.0, np.linspace(5e-3, 7e-3, N), np.array([0.3, 0.5, 0.1]), s.p_max - s.p_margin)
    Xb = x0 * np.linspace(1.0, 1.2, N + 1)
    Ub = np.tile([0.3, 0.5, 0.1], (N, 1)) * np.linspace(0.5, 1.0, N)[:, None]
    want = qp_matrices(new, pr, Xb, Ub)
    z = np.zeros(new.nz)
    z[new.ix], z[new.iu] = Xb, Ub
    p = new._par
    p[:8] = [pr.x0, pr.W, pr.dh, pr.dp, *pr.u_prev, pr.p_lim]
    p[8:] = pr.r
    out = new.data(None, z, 0.0)
    assert out[6][0] == 1.0
    got = {"P": new.data.dense(0), "A": new.data.dense(1), "q": out[2], "l": out[3], "u": out[4]}
    assert got["A"].shape[0] == want["A"].shape[0] == 1 + 9 * N - 3 + (4 if h_min > 0 else 3) * N
    for key in ("P", "A", "q", "l", "u"):
        np.testing.assert_allclose(got[key], np.clip(want[key], -1e30, 1e30), rtol=1e-10, atol=1e-12, err_msg=key)


@pytest.mark.slow
@pytest.mark.compiling
def test_settings_differing_only_in_weights_share_one_library(model):
    """A tuning study's trials change weights: their QP data is one generated library (one build),
    while another horizon is another."""
    import hbma_ctrl.controllers.rti_c as rc

    if not rc.has_compiler():
        pytest.skip("no C compiler on this machine: no generated library to share")
    a = _RtiOsqp(model, _settings("rti_c_osqp"))
    b = _RtiOsqp(model, replace(_settings("rti_c_osqp"), **TUNED).validate())
    c = _RtiOsqp(model, replace(_settings("rti_c_osqp"), horizon=10).validate())
    assert a.data.fun is b.data.fun and a.data.fun is not c.data.fun
    assert not np.array_equal(a.data.inp[3], b.data.inp[3])


@pytest.mark.slow
def test_looped_qp_data_equals_the_unrolled_one(model):
    """The QP data with the nodes' linearisation as one looped (mapped) call equals the fully unrolled
    SX Function to rounding, on shifted and unshifted steps over random plans."""
    s = _settings("rti_c_osqp")
    rti = _RtiOsqp(model, s)
    looped, unrolled = qp_data_function(rti, looped=True), qp_data_function(rti, looped=False)
    rng = np.random.default_rng(3)
    N = s.horizon
    for shift in (0.0, 1.0, 1.0, 0.0):
        par = np.r_[rng.uniform(0.9, 1.6), rng.uniform(0.0, 4.0), rng.uniform(-1e-3, 1e-3), rng.uniform(-500, 500),
                    rng.uniform(0.0, 1.0, 3), 30e3, rng.uniform(1e-3, 9e-3, N)]
        z = rng.uniform(-0.1, 1.1, rti.nz)  # inputs outside [0, 1] too: the plan clips them
        z[rti.ix] = rng.uniform(0.9, 1.6, N + 1)
        w = weights_of(s) * rng.uniform(0.5, 2.0, len(WEIGHTS))  # weights are an input: any will do
        for name, a, b in zip(looped.name_out(), looped(par, z, shift, w), unrolled(par, z, shift, w)):
            a, b = np.asarray(a).ravel(), np.asarray(b).ravel()
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, np.max(np.abs(b))), err_msg=name)


@pytest.mark.slow
def test_first_inputs_equal_rti_osqp_over_states_and_steps(model):
    """Both variants (the QP data as generated C and on casadi's virtual machine), fed the same estimates
    (three heights, four steps each, warm-started), send the same commands to OSQP's tolerance."""
    ctrls = [NMPC(Actuator(), Pneumatics(), _settings(v), model=model) for v in ("rti_osqp", "rti_c_osqp")]
    assert ctrls[1].stats().get("variant") == "rti_c_osqp" and ctrls[0].backend.mode == "vm"
    for h, p, target in ((2e-3, 9e3, 6e-3), (6e-3, 14e3, 3e-3), (9e-3, 20e3, 12e-3)):
        for c in ctrls:
            c.reset()
        for k in range(4):
            est = Estimate(t=0.02 * k, h1=h + 1e-4 * k, h2=0.0, h=h + 1e-4 * k, F=0.4, p=p)
            cmds = [c.step(0.02 * k, est, Reference(target)).as_array() for c in ctrls]
            assert all(c.last["status"] == "ok" for c in ctrls)
            np.testing.assert_allclose(cmds[1], cmds[0], atol=1e-6)


@pytest.mark.slow
def test_closed_loop_rmse_within_1pct_of_ipopt():
    """On the bench's scenario (2 s: the first step to 2 mm, 400 g) the tracking RMSE of rti_c_osqp is
    within 1 % of IPOPT's."""
    from hbma_ctrl.app.bench.mpc import default_section
    from hbma_ctrl.app.scenes.controller import closed_loop, loop_metrics
    from hbma_ctrl.core.params import Platform
    from hbma_ctrl.sim.rig import RigSettings

    sec0 = default_section()
    rmse = {}
    for v in ("ipopt", "rti_c_osqp"):
        sec = replace(sec0, mpc=replace(sec0.mpc, variant=v, budget=10.0).validate())
        log = closed_loop(Actuator(), Pneumatics(), Platform(load=0.4), sec, 2.0, RigSettings(seed=1))
        m = loop_metrics(log, sec)
        assert m["fallbacks"] == 0
        rmse[v] = m["height_rmse_mm"]
    assert rmse["rti_c_osqp"] <= 1.01 * rmse["ipopt"]


@pytest.fixture(scope="module")
def bank(robot_bank):
    return robot_bank


def _first_qp(bank, monkeypatch, L: int, x0, abar=None):
    """The QP (P, A, q, l, u) the robot NMPC hands OSQP's setup at its first step (not solved)."""
    import hbma_ctrl.controllers.robot_mpc as rm

    ctrl = RobotNMPC(bank, 3, RobotMPCSettings(lin_every=L))
    if abar is not None:
        ctrl.abar[:] = abar
    seen = {}

    class Spy:
        def setup(self, **kw):
            seen.update(kw)
            raise RuntimeError("stop")

    with monkeypatch.context() as mp:
        mp.setattr(rm.osqp, "OSQP", Spy)
        with pytest.raises(RuntimeError, match="stop"):
            ctrl.step(x0, np.ones(3), np.full(3, 0.5), np.full(3, 6e-3))
    return seen


def test_robot_held_linearisation_equals_every_stage_on_a_constant_plan(bank, monkeypatch):
    """With the plan constant along the horizon (a cold start) every stage's linearisation is the
    same, so holding it over stage pairs gives exactly the QP of linearising at every stage."""
    x0 = np.array([1.1, 1.3, 1.5])
    q1, q2 = _first_qp(bank, monkeypatch, 1, x0), _first_qp(bank, monkeypatch, 2, x0)
    for key in ("P", "A"):
        np.testing.assert_allclose(q2[key].toarray(), q1[key].toarray(), rtol=1e-12, atol=1e-15)
    for key in ("q", "l", "u"):
        np.testing.assert_allclose(q2[key], q1[key], rtol=1e-12, atol=1e-15)


def test_robot_held_linearisation_differs_on_a_varying_plan(bank, monkeypatch):
    """On a plan that changes along the horizon the held linearisation is a different QP (the test
    above is not vacuous)."""
    x0 = np.array([1.1, 1.3, 1.5])
    ramp = np.linspace(0.0, 0.9, RobotMPCSettings().horizon)
    q1, q2 = _first_qp(bank, monkeypatch, 1, x0, ramp), _first_qp(bank, monkeypatch, 2, x0, ramp)
    assert np.abs(q2["A"].toarray() - q1["A"].toarray()).max() > 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("topology, L", [("per_chamber", 2), ("shared", 1)])
def test_robot_looped_qp_data_equals_the_unrolled_one(topology, L):
    """The robot QP data with the chambers' linearisations as one looped (mapped) call equals the one
    with every point inlined, to rounding, on random plans and states (both pump topologies, the
    linearisation held over stage pairs and at every stage)."""
    from hbma_ctrl.app.scenes.robot_closed import make_model
    from hbma_ctrl.robot.design import RobotDesign

    bank = make_model(RobotDesign(n_layers=1).validate(), Pneumatics().validate(), topology)
    ctrl = RobotNMPC(bank, 3, RobotMPCSettings(lin_every=L))
    lin = bank.linearisation(ctrl.s.dt, 1, ctrl.s.integrator)
    looped, unrolled = ctrl._qp_data_function(lin, looped=True), ctrl._qp_data_function(lin, looped=False)
    rng = np.random.default_rng(5)
    for _ in range(3):
        args = []
        for i in range(looped.n_in()):
            r, c = looped.size_in(i)
            lo, hi = {"x0": (1.0, 1.6), "xbar": (1.0, 1.6), "b": (0.8, 1.2), "k": (0.8, 1.2), "c": (0.8, 1.2),
                      "W": (0.1, 2.0), "h_ref_mm": (2.0, 9.0)}.get(looped.name_in(i), (0.0, 1.0))
            args.append(rng.uniform(lo, hi, (r, c)))
        for name, a, b in zip(looped.name_out(), looped(*args), unrolled(*args)):
            a, b = np.asarray(a).ravel(), np.asarray(b).ravel()
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, np.max(np.abs(b[b < 1e29]))),
                                       err_msg=name)


@pytest.mark.slow
def test_robot_rmse_within_1pct_of_linearising_every_stage():
    """One layer, bench robot's run (straight 6 mm, then a 15 deg bend): the default settings track the
    chamber heights within 1 % of the RMSE with the linearisation at every stage and OSQP at 1e-4 /
    400 iterations."""
    from hbma_ctrl.app.scenes.robot_closed import bench_robot

    new = bench_robot(layers=(1,), duration=2.0)[0]
    old = bench_robot(layers=(1,), duration=2.0, mpc=RobotMPCSettings(lin_every=1, eps=1e-4, max_iter=400))[0]
    assert new["fallbacks"] == 0 and old["fallbacks"] == 0
    assert new["height_rmse_mm"] <= 1.01 * old["height_rmse_mm"]


@pytest.mark.slow
@pytest.mark.compiling
def test_without_a_compiler_warns_once_and_gives_the_same_data(model, monkeypatch):
    """No C compiler: one RuntimeWarning saying so, the data on casadi's virtual machine, equal to the C."""
    import hbma_ctrl.controllers.rti_c as rc

    if not rc.has_compiler():
        pytest.skip("no C compiler on this machine: no generated C to compare the virtual machine with")
    s = _settings("rti_c_osqp")
    c_path = _RtiOsqp(model, s)
    monkeypatch.setattr(rc, "has_compiler", lambda: False)
    with pytest.warns(RuntimeWarning, match="no C compiler") as rec:
        vm = _RtiOsqp(model, s)
    assert len(rec) == 1 and vm.mode == "vm" and c_path.mode == "c"
    N = s.horizon
    x0 = model.x_at_height(4e-3, 0.4)
    for b in (c_path, vm):
        b._par[:8] = [x0, 0.4, 0.0, 0.0, 0.2, 0.4, 0.0, s.p_max - s.p_margin]
        b._par[8:] = np.full(N, 6e-3)
        b._z[:] = 0.0
        b._z[b.ix] = x0
    outs = [[o.copy() for o in b.data.eval()] for b in (c_path, vm)]
    for got, want in zip(outs[1], outs[0]):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
