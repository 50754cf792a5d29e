"""hbma-ctrl tune: outputs, resuming after a killed worker, two processes on one study, bad flags.

A tiny estimator scenario (1.5 s, one train and one test seed) keeps every study to seconds.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import optuna
import pytest
from cli_checks import one_line_error
from typer.testing import CliRunner

from hbma_ctrl.app.tuning import tune as T
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.scenario import load_scenario

runner = CliRunner()

TINY = """
[scenario]
name = "tiny_est"
duration_s = 1.5

[actuator]
r1_mm = 12.5
t0_mm = 3.0
material = "nh"

[load]
mass_g = 200.0

[inputs]
schedule = [[0.0, 100.0, 1.0, 0.0], [0.7, 0.0, 0.0, 1.0]]

[rig]
noise_std_kpa = 0.2
seed = 0

[estimator]
filter = "ekf"
"""

FAST = ["--role", "estimator", "--train-seeds", "0", "--test-seeds", "10",
        "--param-set", "model_rel_std", "--param-set", "flow_rel_std"]


@pytest.fixture()
def scn(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return path


def _tune(*args: str):
    return runner.invoke(app, ["tune", *map(str, args)])


def _counts(db: Path, study: str = "tiny_est-estimator") -> tuple[list[int], dict]:
    st = optuna.load_study(study_name=study, storage=f"sqlite:///{db}")
    nums = [t.number for t in st.trials]
    states: dict = {}
    for t in st.trials:
        states[t.state.name] = states.get(t.state.name, 0) + 1
    return nums, states




@pytest.mark.slow
@pytest.mark.subprocess
def test_tiny_study_writes_outputs_and_resumes_after_a_killed_worker(scn, tmp_path):
    out = tmp_path / "t"
    res = _tune(scn, *FAST, "--trials", "2", "--out", out)
    assert res.exit_code == 0, res.output
    for name in ("tuned.toml", "tune.json", "history.png", "importance.png", "manifest.json"):
        assert (out / name).is_file(), name
    info = json.loads((out / "tune.json").read_text())
    assert set(T.TUNE_KEYS) <= set(info)
    assert info["objective"] == "estimator.height_nrmsd"
    assert info["n_trials"] == 2
    assert set(info["best_params"]) == {"model_rel_std", "flow_rel_std"}
    assert info["default_value_test"] > 0 and info["best_value_test"] > 0
    # trial 0 is the scenario's own settings (the defaults): the best can only match or beat it on train
    assert info["default_params"] == {"model_rel_std": 0.05, "flow_rel_std": 0.15}
    assert info["best_value_train"] <= info["default_value_train"]
    tuned = load_scenario(out / "tuned.toml")  # a valid scenario holding the best settings
    raw = tomllib.loads((out / "tuned.toml").read_text())
    assert raw["estimator"]["model_rel_std"] == pytest.approx(info["best_params"]["model_rel_std"])
    assert tuned.name == "tiny_est"
    head = (out / "tuned.toml").read_text().splitlines()[:3]
    assert any("study 'tiny_est-estimator'" in h for h in head) and any("sha256" in h for h in head)

    # a worker killed mid-trial leaves a RUNNING trial: a real process takes one and is killed
    db = Path(f"{out}.study.db")
    code = ("import optuna, os, socket, sys, time; st = optuna.load_study(study_name='tiny_est-estimator', "
            f"storage='sqlite:///{db}'); t = st.ask(); t.set_user_attr('host', socket.gethostname()); "
            "t.set_user_attr('pid', os.getpid()); print('running', flush=True); time.sleep(600)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "running"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert _counts(db)[1].get("RUNNING") == 1

    # the same command again continues the study (its results directory is replaced, no --overwrite)
    # and fails the dead worker's trial
    res = _tune(scn, *FAST, "--trials", "1", "--out", out)
    assert res.exit_code == 0, res.output
    assert "left RUNNING by a process that is gone" in res.output
    info = json.loads((out / "tune.json").read_text())
    assert info["n_trials"] == 4 and info["trials_this_run"] == 1
    nums, states = _counts(db)
    assert sorted(nums) == list(range(4)) and states["FAIL"] == 1 and "RUNNING" not in states
    assert states.get("COMPLETE", 0) + states.get("PRUNED", 0) == 3


def test_other_study_in_out_is_refused_without_overwrite(scn, tmp_path):
    out = tmp_path / "t"
    out.mkdir()
    (out / "something.txt").write_text("a run")
    one_line_error(_tune(scn, *FAST, "--trials", "1", "--out", out), "--out", "--overwrite")


@pytest.mark.slow
@pytest.mark.subprocess
def test_two_processes_share_one_sqlite_study(scn, tmp_path):
    out = tmp_path / "w"
    res = _tune(scn, *FAST, "--trials", "3", "--workers", "2", "--out", out)
    assert res.exit_code == 0, res.output
    nums, states = _counts(Path(f"{out}.study.db"))
    assert len(nums) == 3 and sorted(nums) == [0, 1, 2]  # none lost, none repeated
    assert states.get("COMPLETE", 0) + states.get("PRUNED", 0) == 3
    trials = optuna.load_study(study_name="tiny_est-estimator", storage=f"sqlite:///{out}.study.db").trials
    # the enqueued defaults (trial 0) run in the command's process before the workers start (optuna's
    # SQLite storage could hand one enqueued trial to both); the other trials are shared by both workers
    assert trials[0].user_attrs.get("default") and trials[0].user_attrs["pid"] == os.getpid()
    pids = {t.user_attrs["pid"] for t in trials[1:]}
    assert len(pids) == 2 and os.getpid() not in pids  # both worker processes did trials


def test_running_trial_of_a_live_process_is_left_alone(tmp_path):
    st = optuna.create_study(storage=f"sqlite:///{tmp_path / 's.db'}", study_name="s")
    live = st.ask()
    st._storage.set_trial_user_attr(live._trial_id, "host", __import__("socket").gethostname())
    st._storage.set_trial_user_attr(live._trial_id, "pid", os.getpid())
    assert T.fail_orphans(st) == []
    assert st.trials[0].state == optuna.trial.TrialState.RUNNING


@pytest.mark.parametrize("args,needles", [
    (["--objective", "estimator.height_rms"], ["--objective", "estimator.height_nrmsd", "estimator.force_rmse_n"]),
    (["--train-seeds", "5-2"], ["--train-seeds", "5-2"]),
    (["--test-seeds", "x"], ["--test-seeds"]),
    (["--train-seeds", "0-3", "--test-seeds", "3-5"], ["--test-seeds", "held-out"]),
    (["--trials", "0"], ["--trials", "[1, 100000]"]),
    (["--role", "robot"], ["--role", "controller, estimator"]),
    (["--param-set", "w_terminal"], ["--param-set", "w_terminal", "model_rel_std"]),
    (["--param-set", "model_rel_std=0.5:0.1"], ["--param-set", "LO < HI"]),
    (["--duration-s", "0.3"], ["--duration-s", "duration_s"]),
    (["--role", "controller"], ["no [controller] table"]),
])
def test_bad_flags_are_one_line_exit_2(scn, tmp_path, args, needles):
    base = ["--role", "estimator", "--trials", "2", "--out", str(tmp_path / "bad")]
    one_line_error(_tune(scn, *base, *args), *needles)
    assert not (tmp_path / "bad").exists() and not Path(f"{tmp_path / 'bad'}.study.db").exists()


def test_objective_missing_from_the_metrics_names_the_keys_there():
    m = {"controller": {"height_rmse_mm": 1.0, "kind": "pid", "fallbacks": 0}}
    with pytest.raises(ValueError, match=r"--objective controller.solve_ms_median: .*controller.height_rmse_mm, "
                                         r"controller.fallbacks$"):
        T.objective_value(m, "controller.solve_ms_median")


def test_journal_storage_url_holds_a_study(tmp_path):
    storage = T.make_storage(f"journal:{tmp_path / 'j.log'}")
    st = optuna.create_study(storage=storage, study_name="j")
    st.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    again = optuna.load_study(study_name="j", storage=T.make_storage(f"journal:{tmp_path / 'j.log'}"))
    assert len(again.trials) == 2


def test_bad_storage_url_is_one_line_exit_2(scn, tmp_path):
    one_line_error(_tune(scn, *FAST, "--trials", "1", "--storage", "nosuchdb://x", "--out", tmp_path / "s"),
                    "--storage nosuchdb://x")
    assert not (tmp_path / "s").exists()


def test_space_uses_declared_bounds_and_log_scale():
    data = {"controller": {"kind": "mpc", "targets_mm": [[0, 2]]}}
    dims = {d.name: d for d in T.make_space(data, "controller")}
    w = dims["w_terminal"]  # default 5 within [5/20, 5*20]: 2.6 decades -> log
    assert (w.lo, w.hi, w.log, w.default) == (0.25, 100.0, True, 5.0)
    d = {x.name: x for x in T.make_space(data, "controller", ["p_margin_kpa", "horizon=5:30"])}
    assert (d["p_margin_kpa"].lo, d["p_margin_kpa"].log) == (0.0, False)  # declared bounds [0, 1000] kPa
    assert (d["horizon"].lo, d["horizon"].hi, d["horizon"].kind) == (5, 30, "int")


def test_apply_params_sets_vector_elements_from_defaults():
    out = T.apply_params({"controller": {}}, "controller", {"w_rate[2]": 0.5, "w_terminal": 7.0})
    assert out["controller"]["w_rate"] == [0.02, 0.002, 0.5] and out["controller"]["w_terminal"] == 7.0


def test_controller_penalty_counts_fallbacks_and_guard():
    m = {"controller": {"height_rmse_mm": 1.0, "fallbacks": 3, "guard_activations": 2,
                        "pressure_limit_respected": True}}
    assert T.objective_value(m, "controller.height_rmse_mm") == pytest.approx(1.05)
    m["controller"]["pressure_limit_respected"] = False
    assert T.objective_value(m, "controller.height_rmse_mm") == pytest.approx(11.05)
    assert T.objective_value(m, "controller.fallbacks") == 3.0  # other objectives: no penalty


def test_parse_seeds():
    assert T.parse_seeds("0-3,7", "--x") == [0, 1, 2, 3, 7]
    with pytest.raises(ValueError, match="--x"):
        T.parse_seeds("-1", "--x")
