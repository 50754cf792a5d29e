"""The robot with glued chambers (README Model §8, §9): the bonded force table against the exact solver,
tension in a vented glued chamber, the load sharing with tension allowed, the layer's rim-pivot pose in
balance, and Table II's bonded reading through the CLI. The first use builds the 1 mm table (about a
minute here), then it loads from the cache."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app
from hbma_ctrl.models.exact import ExactMembrane
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.kinematics import forward_kinematics
from hbma_ctrl.robot.reach import _pivot_balance, bonded_layer_pose, paper_pose_check
from hbma_ctrl.robot.statics import BOND_RADIUS, bonded_chamber, bonded_table
from oracles.statics import bonded_chamber_states

# slow as a whole: on a clean machine (as CI is) the first of these tests builds the table, a minute and
# a half, and on two workers two of them build it side by side
pytestmark = pytest.mark.slow

D = RobotDesign(n_layers=2)
ACT = D.chamber
W_ABOVE = float(D.body_masses.sum() * D.g)  # layers B and the top rest on layer A's chambers


@pytest.fixture(scope="module")
def ch():
    return bonded_chamber(ACT, BOND_RADIUS)


def test_bonded_table_matches_the_solver_between_nodes_within_3_percent(ch):
    # halfway between height and pressure nodes, where the interpolation is least exact
    h, p = 1.125e-3, 22.5e3
    ref = ExactMembrane(ACT.material, ACT.r1, ACT.t0, contact="bonded", c=BOND_RADIUS).contact(h, p)["F"]
    assert ch.force(h, p) == pytest.approx(ref, rel=0.03)


def test_a_bulging_glued_membrane_lifts_its_disk_with_more_than_p_pi_c2(ch):
    p = 45e3
    assert ch.force(0.25e-3, p) > 3 * p * math.pi * BOND_RADIUS**2


def test_a_vented_glued_chamber_pulled_up_pulls_the_layer_down(ch):
    for h in (1e-3, 2e-3, 4e-3):
        assert ch.force(h, 0.0) < 0
    assert ch.force(2e-3, 0.0) < ch.force(1e-3, 0.0)  # the further it is pulled, the harder it pulls back


def test_height_and_pressure_invert_the_force(ch):
    h = ch.height(0.3, 30e3)
    assert ch.force(h, 30e3) == pytest.approx(0.3, abs=1e-9)
    p = ch.pressure(2e-3, -0.2)
    assert ch.force(2e-3, p) == pytest.approx(-0.2, abs=1e-3)  # linear in p between columns


def test_load_sharing_with_tension_gives_each_glued_chamber_its_pressure():
    # a tilt with A3 low: A3 carries more; raising A1 puts it in tension only if the statics say so
    H = np.zeros((2, 3))
    H[0] = [3.0e-3, 2.0e-3, 1.0e-3]
    st = bonded_chamber_states(D, H)
    assert st["F"][0].sum() == pytest.approx(W_ABOVE * math.cos(forward_kinematics(D, H).bend[0]), rel=1e-6)
    ch = bonded_chamber(ACT, BOND_RADIUS)
    for i in range(3):
        assert ch.force(H[0, i], st["p"][0, i]) == pytest.approx(st["F"][0, i], abs=2e-3)
    # 1 N lifting the tip of a level pose at 2 mm: every glue spot holds the layer down (tension), the
    # stretched membranes pull back with a little pressure left (about 5 kPa); 3 N would need a vacuum
    H[0] = [2.0e-3, 2.0e-3, 2.0e-3]
    st = bonded_chamber_states(D, H, tip_force=(0.0, 0.0, 1.0))
    assert st["tension"][0].all() and not st["beyond"][0].any()
    assert np.allclose(st["F"][0], (W_ABOVE - 1.0) / 3) and np.all((st["p"][0] > 0) & (st["p"][0] < 10e3))
    assert bonded_chamber_states(D, H, tip_force=(0.0, 0.0, 3.0))["beyond"][0].all()


@pytest.mark.parametrize("inflated", [[0], [0, 1]])
def test_bonded_layer_pose_balances_on_its_rim_with_vented_chambers_in_tension(inflated):
    r = bonded_layer_pose(D, inflated, 40e3)
    assert r["ok"]
    a = np.asarray(D.chamber_angles)[inflated]
    psi = math.atan2(-np.sin(a).sum(), -np.cos(a).sum())
    moment, reaction = _pivot_balance(D, r["heights"], r["forces"], psi)
    assert abs(moment) < 1e-9 and reaction >= 0
    H = np.zeros((2, 3))
    H[0] = r["heights"]
    assert forward_kinematics(D, H).rim_gap(D)[0] == pytest.approx(0.0, abs=1e-12)
    vented = [i for i in range(3) if i not in inflated]
    assert np.all(r["forces"][vented] < 0) and np.all(r["heights"][vented] > 0)
    # vertical balance: the chambers' normal forces and the rim carry the weight above
    n_z = math.cos(r["bend"])
    assert r["forces"].sum() * n_z + reaction == pytest.approx(W_ABOVE, rel=1e-9)


@pytest.mark.slow
def test_robot_table2_prints_the_bonded_reading_beside_the_paper(tmp_path):
    res = CliRunner().invoke(app, ["robot", "table2", "--out", str(tmp_path / "t2")])
    assert res.exit_code == 0, res.output
    rows = [r for r in json.loads((tmp_path / "t2" / "table2.json").read_text()) if r["reading"] == "bonded"]
    assert [r["inflated"] for r in rows] == [0, 1, 2, 3]
    assert all(r["within_reach"] for r in rows)
    # the glued chambers reach ~4 mm: no taut exact equilibrium beyond ~6 mm (slack hoop), far from the paper's poses
    assert rows[3]["length_mm"] < rows[3]["paper_length_mm"] - 10
    md = (tmp_path / "t2" / "table2.md").read_text()
    assert "| bonded | 1 |" in md and "No rigid-layer statics" in md
    poses = json.loads((tmp_path / "t2" / "paper_poses.json").read_text())
    assert [r["inflated"] for r in poses] == [1, 1, 2, 2] and not any(r["equilibrium"] for r in poses)


def test_the_papers_one_and_two_chamber_poses_are_no_rigid_layer_equilibrium():
    """Table II's rows 1-2 as a three-point pose: the pose has the paper's bend and centre; the load sharing
    needs every vented chamber to push, where a lifted vented glued chamber pulls (or has no taut state);
    row 1's rims overlap, and a rim pivot would need another layer radius than the robot's 22 mm."""
    from hbma_ctrl.robot.design import TABLE2_PAPER

    rows = paper_pose_check(D)
    assert [(r["inflated"], r["reading"]) for r in rows] == [
        (1, "length - L"), (1, "length - paper rest length"), (2, "length - L"), (2, "length - paper rest length")]
    paper = {n: (a, ln) for n, a, ln, _ in TABLE2_PAPER}
    for r in rows:
        n = r["inflated"]
        H = np.zeros((2, 3))
        H[0] = np.array(r["heights_mm"]) * 1e-3
        pose = forward_kinematics(D, H)
        assert math.degrees(pose.bend[0]) == pytest.approx(paper[n][0], abs=1e-9)
        assert pose.centre[0] * 1e3 == pytest.approx(r["centre_mm"], abs=1e-9)
        vented = list(range(n, 3))
        assert min(r["heights_mm"][i] for i in vented) > 4.0  # lifted, not resting on the layer below
        assert all(r["needed_forces_n"][i] > 0.1 for i in vented)  # they would have to push
        assert all(f is None or f < -1.0 for f in r["vented_force_n"])  # they pull (or have no taut state)
        assert not r["equilibrium"] and r["vented_must_push"]
        assert abs(r["rim_radius_mm"] - r["layer_radius_mm"]) > 3.0
        # vertical balance of the needed forces: the weight above along the layer normal
        assert sum(r["needed_forces_n"]) == pytest.approx(W_ABOVE * math.cos(pose.bend[0]), rel=1e-9)
    assert all(r["rim_gap_mm"] < 0 for r in rows if r["inflated"] == 1)  # the rigid rims would overlap
    assert all(f is not None for r in rows if r["inflated"] == 1 for f in r["vented_force_n"])
    assert all(f is None for r in rows if r["inflated"] == 2 for f in r["vented_force_n"])  # past 5.5 mm


@pytest.mark.parametrize("args, key", [(["--bond-radius-mm", "4.5"], "--bond-radius-mm"),
                                       (["--bond-radius-mm", "0"], "--bond-radius-mm"),
                                       (["--bond-kpa", "60"], "--bond-kpa")])
def test_bad_bonded_options_are_one_error_line_exit_2(tmp_path, args, key):
    res = CliRunner().invoke(app, ["robot", "table2", "--out", str(tmp_path / "t2"), *args])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and key in lines[0]


def test_bond_radius_outside_the_membrane_is_refused():
    with pytest.raises(ValueError, match="bond radius"):
        bonded_table(ACT, 5e-3)
