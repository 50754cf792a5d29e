"""Observability from pressure alone along rig trajectories (rank of the linearised obsv matrix)."""

import json

import numpy as np
import pytest

from hbma_ctrl.estimators.observability import Trajectory, analyse, run, summarise

HOLD = ((0.0, 0.6, 1.0, 0.0), (1.5, 0.0, 0.0, 0.0))


@pytest.mark.slow
def test_regimes_have_the_expected_ranks():
    rows = analyse(Trajectory("dead", 0.4, HOLD, 2.8)) + analyse(Trajectory("heavy", 3.0, HOLD, 2.8))
    by = {}
    for r in summarise(rows):
        by[(r["trajectory"], r["regime"])] = r
    # flat under a load: W and k do not enter the pressure; pumping shows m and the flow factor
    rest = by[("heavy", "resting+flow")]
    assert rest["rank_max"] == 2 and rest["window_rank_max"] <= 2
    # valves closed: one combination of the state only, whatever the regime
    for key in (("heavy", "resting+hold"), ("dead", "contact+hold")):
        assert by[key]["rank_max"] == 1 and by[key]["window_rank_max"] == 1
    # carrying the load while gas flows: more than the pressure level is learnt over a window
    assert by[("dead", "contact+flow")]["window_rank_max"] >= 2


def test_command_output_json(tmp_path):
    summ = run(tmp_path, trajectories=[Trajectory("free", 0.0, HOLD, 3.5)])
    data = json.loads((tmp_path / "observability.json").read_text())
    assert data["state"] == ["m", "W", "b", "k", "c"]
    assert {r["regime"] for r in summ} >= {"free+flow", "free+hold"}
    assert all(np.isfinite(s["window_rank_median"]) for s in summ)
