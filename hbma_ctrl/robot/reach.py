"""What each chamber can reach, Table II beside the model, and the workspace (SI).

Why the robot's chambers work past the balloon limit point
----------------------------------------------------------
With Table I and r1 = 4.5 mm, t0 = 2 mm, the free-inflation pressure peaks near 35.5 kPa at
h ~ 5.7 mm (NH); below 35 kPa a chamber reaches about 5 mm and tilts a layer only ~12 degrees,
while Table II reports 28.9. Beyond the peak the pressure *falls* as the membrane grows: under
pressure control that branch is unstable (any excess pressure inflates further), but for a fixed
gas mass it is stable because the gas is compressible and ``G = (p + p_env) V`` keeps increasing
with h (the quasi-static model has no fold there). So the robot holds chambers on the far branch
by gas mass. What limits a chamber then is not the pressure limit (the pressure on the far branch
is below the peak) but (a) whether the pump and the pressure limit allow passing the peak at all
(``min(pressure_limit, pump stall)`` above the load path's peak pressure), and (b) the membrane's
maximum stretch (``RobotDesign.max_stretch``, an assumed safe equi-biaxial stretch: the paper
inflated "without reaching the limit, which would mean breaking the membrane"). See
:func:`chamber_reach`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Pneumatics, check_range
from hbma_ctrl.robot.design import LETTERS, TABLE2_PAPER, RobotDesign
from hbma_ctrl.robot.kinematics import forward_kinematics, inverse_kinematics
from hbma_ctrl.robot.statics import BOND_RADIUS, bonded_chamber, chamber_solver, chamber_states, load_sharing


def pump_stall_pressure(pneumatics: Pneumatics | None = None) -> float:
    """Highest gauge pressure (Pa) at which the pump still delivers flow at full speed."""
    return ph.pump_reach((pneumatics or Pneumatics()).csv_path)[0]


@dataclass(frozen=True)
class ChamberReach:
    """Reach of one chamber under a contact force (SI).

    h_max : largest height reachable holding the gas mass (far branch allowed), m
    limit : what sets h_max: 'max_stretch', 'pressure_limit' or 'pump_stall'
    h_peak, p_peak : height and pressure of the balloon limit point along the load path (m, Pa)
    h_pressure_control : reach if the chamber were pressure-controlled (near branch only), m
    p_at_max : pressure at h_max, Pa
    """

    force: float
    h_max: float
    limit: str
    h_peak: float
    p_peak: float
    h_pressure_control: float
    p_at_max: float


def chamber_reach(design: RobotDesign, force: float, pressure_limit: float = 45e3,
                  pneumatics: Pneumatics | None = None) -> ChamberReach:
    """Reachable height of one robot chamber pushing with contact force ``force`` (N).

    Along the constant-load path the pressure rises to the balloon limit point (p_peak at h_peak)
    and then falls. The usable pressure is ``p_cap = min(pressure_limit, pump stall pressure)``. If
    p_cap >= p_peak the chamber can be driven over the peak and held on the far branch by its gas
    mass, up to the maximum stretch (limit 'max_stretch'; the pump keeps delivering there since the
    far-branch pressure is below the peak). Otherwise the chamber stops on the near branch where
    the pressure reaches p_cap ('pressure_limit' or 'pump_stall'). ``h_pressure_control`` is the
    reach of a pressure-controlled chamber (never past the peak).
    """
    check_range("reach", "pressure_limit", pressure_limit, 0.0, 1e6, "Pa", lo_open=True)
    ch = chamber_solver(design.chamber, pneumatics)
    F = max(float(force), 0.0)
    h_str = float(ch.h_for_stretch(design.max_stretch, F)[0])
    path = ch.load_path(F, h_str)
    hs, ps = path["h"], path["p"]
    stall = pump_stall_pressure(pneumatics)
    p_cap = min(pressure_limit, stall)
    ipk = int(np.argmax(ps))
    h_peak, p_peak = float(hs[ipk]), float(ps[ipk])
    over = np.nonzero(ps > p_cap)[0]
    if over.size == 0:
        i_max, limit = hs.size - 1, "max_stretch"
        h_max = h_str
    else:
        i = int(over[0])
        limit = "pressure_limit" if pressure_limit <= stall else "pump_stall"
        if i == 0:
            h_max, i_max = 0.0, 0
        else:
            w = (p_cap - ps[i - 1]) / (ps[i] - ps[i - 1])
            h_max, i_max = float(hs[i - 1] + w * (hs[i] - hs[i - 1])), i
    h_pc = min(h_peak if ipk < hs.size - 1 else h_str, h_max)
    return ChamberReach(F, float(h_max), limit, h_peak, p_peak, float(h_pc), float(ps[i_max]))


def reach_report(design: RobotDesign, heights, pressure_limit: float = 45e3,
                 pneumatics: Pneumatics | None = None, tip_force=(0.0, 0.0, 0.0)) -> dict:
    """Check chamber heights (N x 3, m) against each chamber's reach at its load share.

    Returns dict(ok, h_max (N, 3), limit (N, 3) names, violations: list of text, rim_gap (N,) m).
    Negative heights are violations too (a chamber cannot push down), and so is a pose whose
    layer rims would overlap (:meth:`~hbma_ctrl.robot.kinematics.RobotPose.rim_gap` < 0).
    """
    h = np.asarray(heights, dtype=float).reshape(design.n_layers, 3)
    names = design.names
    F = load_sharing(design, np.maximum(h, 0), tip_force).forces
    hmax = np.zeros(h.shape)
    lim = np.empty(h.shape, dtype=object)
    viol = []
    for k in range(design.n_layers):
        for i in range(3):
            r = chamber_reach(design, F[k, i], pressure_limit, pneumatics)
            hmax[k, i], lim[k, i] = r.h_max, r.limit
            if h[k, i] < -1e-12:
                viol.append(f"{names[3 * k + i]}: height {U.to_mm(h[k, i]):.2f} mm < 0")
            elif h[k, i] > r.h_max + 1e-9:
                viol.append(f"{names[3 * k + i]}: height {U.to_mm(h[k, i]):.2f} mm > reach "
                            f"{U.to_mm(r.h_max):.2f} mm (limited by {r.limit})")
    gap = forward_kinematics(design, np.maximum(h, 0)).rim_gap(design)
    for k in np.nonzero(gap < -1e-9)[0]:
        viol.append(f"layer {LETTERS[k]}: the layer rims overlap by {U.to_mm(-gap[k]):.2f} mm (rigid three-point "
                    "pose; the real layers rock on the rim)")
    return {"ok": not viol, "h_max": hmax, "limit": lim, "violations": viol, "rim_gap": gap}


def rim_pivot_pose(design: RobotDesign, h_inflated: float, inflated: list[int]) -> tuple[float, float, float]:
    """Layer pose when the inflated chambers stand at ``h_inflated`` (m) and the layer rocks on its rim.

    With some chambers flat, the rigid three-point pose makes the layer rims overlap
    (:meth:`~hbma_ctrl.robot.kinematics.RobotPose.rim_gap` < 0): a real layer pivots on the outer rim
    instead, and the flat chambers' glued membranes are pulled up (tension, outside the membrane
    model). The pose then is the plane that touches the lower rim (centre = R sin(bend)) and passes
    through the inflated chambers, bending away from them (direction opposite their mean angle).
    Returns (centre m, bend rad, direction rad); all three inflated -> level at h_inflated.
    """
    if not inflated:
        return 0.0, 0.0, 0.0
    if len(inflated) == 3:
        return float(h_inflated), 0.0, 0.0

    a = np.asarray(design.chamber_angles)[inflated]
    psi = math.atan2(-np.sin(a).sum(), -np.cos(a).sum())
    c = float(np.cos(psi - a).max())  # the inflated chamber nearest the pivot side sets the height
    R, rc = design.outer_diameter / 2, design.placement_radius
    f = lambda t: R * math.sin(t) - rc * math.tan(t) * c - h_inflated  # noqa: E731
    theta = brentq(f, 0.0, math.radians(89.0))
    return R * math.sin(theta), theta, psi


# ---------------------------------------------------------------------------------------------
# Table II beside the model
# ---------------------------------------------------------------------------------------------
def _solve_inflated(design: RobotDesign, inflated: list[int], height_of, iters: int = 20) -> np.ndarray:
    """Heights of layer A with chambers ``inflated`` driven by ``height_of(F) -> h``, the others flat,
    all upper layers flat; fixed point between the heights and the load sharing."""
    h = np.zeros((design.n_layers, 3))
    for _ in range(iters):
        F = load_sharing(design, h).forces[0]
        new = h.copy()
        for i in inflated:
            new[0, i] = height_of(F[i])
        if np.max(np.abs(new - h)) < 1e-9:
            return new
        h = new
    return h


def robot_table2(design: RobotDesign | None = None, stretch: float | None = None, hold_pressure: float = 35e3
                 ) -> list[dict]:
    """The paper's Table II (one layer of the Fig. 10 robot, 0-3 chambers inflated) beside the model.

    How "inflated" is read. The paper inflated the chambers "without reaching the limit (which
    would mean breaking the membrane)"; it states no pressure or gas mass. Two readings are given:

    - ``far_branch`` (the main one): each inflated chamber is driven past the balloon limit point
      and held by its gas mass at the stretch ``stretch`` (default: the design's ``max_stretch``,
      4.0, an assumed safe limit). Its height then follows from its load share (fixed point with
      the load sharing). With the default 4.0 the three-chamber length lands close to the paper's
      26.7 mm, so that row is effectively the calibration of the one free number; the one- and
      two-chamber rows are predictions.
    - ``near_branch``: each inflated chamber held at ``hold_pressure`` (35 kPa, the rig's sensor
      range) on the near branch, as pressure control would: what the robot reaches without passing
      the limit point.
    - ``rim_pivot``: the far-branch chambers, but the layer rocks on its outer rim
      (:func:`rim_pivot_pose`). In the three-point pose a bend with a flat chamber makes the 44 mm
      rigid layers overlap at the rim (``rim_gap_mm`` < 0, geometrically impossible), so the real
      layer must pivot on its rim and pull the flat chambers' glued membranes up (tension, which
      the membrane model does not cover; their height is then set by the pose, not by their gas).
      This reading is closest to the paper's one- and two-chamber rows.

    The layer evaluated is the bottom chamber layer A of the design (default: the paper's robot
    with 2 chamber layers, A and B, as in Fig. 10); it carries the bodies above, with layer B flat.
    Inflated chambers are A1, then A1-A2, then all three. Angle = bend of the layer above; length =
    distance between the two layers' frames on the axis (layer thickness + centre height);
    extension is relative to each source's own 0-chamber length (the paper's 9.6 mm includes a
    0.6 mm rest gap the model does not have).

    Returns one dict per (reading, chambers inflated) with model and paper values (deg, mm, %),
    the chambers' height (mm), pressure (kPa), stretch and gas mass (mg), and the parameters used.
    """
    d = design or RobotDesign(n_layers=2)
    d.validate()
    lam = d.max_stretch if stretch is None else stretch
    check_range("table2", "stretch", lam, 1.05, d.max_stretch if stretch is None else 20.0)
    ch = chamber_solver(d.chamber)

    def at_stretch(F):
        return float(ch.h_for_stretch(lam, max(F, 0.0))[0])

    def at_pressure(F):
        h_hi = float(ch.h_for_stretch(min(d.max_stretch, 3.0), max(F, 0.0))[0])
        path = ch.load_path(max(F, 0.0), h_hi, 300)
        over = np.nonzero(path["p"] >= hold_pressure)[0]
        if over.size == 0:  # never reaches the hold pressure before the peak: stop at the peak
            return float(path["h"][int(np.argmax(path["p"]))])
        i = int(over[0])
        if i == 0:
            return float(path["h"][0])
        p0, p1 = path["p"][i - 1], path["p"][i]
        return float(path["h"][i - 1] + (hold_pressure - p0) / (p1 - p0) * (path["h"][i] - path["h"][i - 1]))

    params = {"n_layers": d.n_layers, "r1_mm": U.to_mm(d.chamber.r1), "t0_mm": U.to_mm(d.chamber.t0),
              "V0_cm3": U.to_cm3(d.chamber.V0), "material": d.chamber.material.name,
              "material_params": d.chamber.material.as_dict(), "placement_radius_mm": U.to_mm(d.placement_radius),
              "layer_thickness_mm": U.to_mm(d.layer_thickness), "layer_mass_g": U.to_grams(d.layer_mass),
              "stretch": lam, "hold_pressure_kpa": U.to_kpa(hold_pressure)}
    rows = []
    for reading, fn in (("far_branch", at_stretch), ("near_branch", at_pressure)):
        base_len = None
        for n, pa, pl, pe in TABLE2_PAPER:
            h = _solve_inflated(d, list(range(n)), fn)
            pose = forward_kinematics(d, h)
            st = chamber_states(d, h)
            length = float(pose.layer_lengths(d)[0])
            base_len = length if n == 0 else base_len
            infl = list(range(n))
            rows.append({
                "reading": reading, "inflated": n,
                "angle_deg": math.degrees(pose.bend[0]), "length_mm": U.to_mm(length),
                "extension_pct": 100 * (length - base_len) / base_len,
                "paper_angle_deg": pa, "paper_length_mm": pl, "paper_extension_pct": pe,
                "chamber_height_mm": U.to_mm(float(h[0, 0])) if n else 0.0,
                "pressure_kpa": U.to_kpa(float(st["p"][0, 0])) if n else 0.0,
                "stretch": float(st["lam"][0, 0]) if n else 1.0,
                "gas_mass_mg": U.to_mg(float(np.mean(st["m"][0, infl]))) if n else U.to_mg(float(st["m"][0, 0])),
                "rim_gap_mm": U.to_mm(float(pose.rim_gap(d)[0])),
                "params": params,
            })
    # the same inflated chambers, the layer rocking on its rim instead of overlapping it
    for r in [r for r in rows if r["reading"] == "far_branch"]:
        n = r["inflated"]
        c, theta, _ = rim_pivot_pose(d, U.mm(r["chamber_height_mm"]), list(range(n)))
        length = d.layer_thickness + c
        base = d.layer_thickness
        rows.append({**r, "reading": "rim_pivot", "angle_deg": math.degrees(theta), "length_mm": U.to_mm(length),
                     "extension_pct": 100 * (length - base) / base, "rim_gap_mm": 0.0 if 0 < n < 3 else r["rim_gap_mm"]})
    return rows


def _rim_heights(design: RobotDesign, theta: float, psi: float) -> np.ndarray:
    """Chamber heights (3,) m of a layer tilted by theta (rad) towards psi (rad) resting on its lower rim
    (the pose of :func:`rim_pivot_pose`: centre R sin(theta), rim gap 0)."""
    a = np.asarray(design.chamber_angles, dtype=float)
    R, rc = design.outer_diameter / 2, design.placement_radius
    return R * math.sin(theta) - rc * math.tan(theta) * np.cos(psi - a)


def _pivot_balance(design: RobotDesign, h0: np.ndarray, forces: np.ndarray, psi: float) -> tuple[float, float]:
    """Moment (N m) about layer A's rim pivot line of the chamber forces and the weights above, and the
    rim's reaction (N, >= 0 for a real contact) for layer-A heights h0 (3,) and chamber forces (3,) N."""
    H = np.zeros((design.n_layers, 3))
    H[0] = h0
    pose = forward_kinematics(design, H)
    Rm, O = pose.frames[1][:3, :3], pose.frames[1][:3, 3]
    n = Rm[:, 2]
    R = design.outer_diameter / 2
    q = O + Rm @ np.array([R * math.cos(psi), R * math.sin(psi), 0.0])
    axis = Rm @ np.array([-math.sin(psi), math.cos(psi), 0.0])
    L = design.layer_thickness
    masses = design.body_masses
    g = np.array([0.0, 0.0, -design.g])
    com = np.array([pose.frames[j][:3, :3] @ [0, 0, L / 2] + pose.frames[j][:3, 3]
                    for j in range(1, design.n_layers + 1)])
    M = sum(np.cross(pose.contacts[0][i] - q, forces[i] * n) for i in range(3))
    M = M + sum(np.cross(com[j] - q, masses[j] * g) for j in range(design.n_layers))
    reaction = float(masses.sum() * design.g - forces.sum() * n[2])
    return float(M @ axis), reaction


def bonded_layer_pose(design: RobotDesign, inflated: list[int], pressure: float, c: float = BOND_RADIUS) -> dict:
    """Layer A's pose with glued chambers (SI): ``inflated`` held at gauge pressure ``pressure`` (Pa),
    the others vented (p = 0), every upper layer flat.

    Each chamber pushes (or, stretched while vented, pulls) with the exact bonded force F(h, p)
    (:class:`hbma_ctrl.robot.statics.BondedChamber`). All three inflated: the level pose where each
    carries its share. One or two: a vented glued chamber cannot push, so the layer tilts onto its
    outer rim (the rigid three-point pose would overlap the rims) and the tilt is where the moments
    about the rim pivot balance; the vented chambers are pulled up and pull back (tension). Returns
    heights (3,) m, forces (3,) N, centre (m), bend (rad), rim reaction (N), ok (False: no balance
    within the table, i.e. beyond the bonded chamber's reach; the pose is then the last one tried).
    """
    ch = bonded_chamber(design.chamber, c)
    p = np.zeros(3)
    p[list(inflated)] = pressure
    if not inflated:
        return {"heights": np.zeros(3), "forces": np.zeros(3), "centre": 0.0, "bend": 0.0, "reaction": 0.0,
                "ok": True}
    if len(inflated) == 3:
        h = 0.0
        for _ in range(30):  # fixed point with the load sharing (the shares barely move with h)
            H = np.zeros((design.n_layers, 3))
            H[0] = h
            share = load_sharing(design, H).forces[0]
            new = ch.height(float(share.mean()), pressure)
            if not np.isfinite(new) or abs(new - h) < 1e-10:
                break
            h = new
        ok = bool(np.isfinite(new))
        F = share if ok else np.full(3, np.nan)
        return {"heights": np.full(3, h if ok else np.nan), "forces": F, "centre": h if ok else np.nan,
                "bend": 0.0, "reaction": 0.0, "ok": ok}
    a = np.asarray(design.chamber_angles)[list(inflated)]
    psi = math.atan2(-np.sin(a).sum(), -np.cos(a).sum())

    def state(theta):
        h0 = _rim_heights(design, theta, psi)
        F = np.array([ch.force(h0[i], p[i]) for i in range(3)])
        return h0, F

    def residual(theta):
        h0, F = state(theta)
        return _pivot_balance(design, h0, F, psi)[0] if np.all(np.isfinite(F)) else np.nan

    thetas = np.radians(np.linspace(0.05, 60.0, 600))
    res = np.array([residual(t) for t in thetas])
    root = None
    for k in range(thetas.size - 1):
        if np.isfinite(res[k]) and np.isfinite(res[k + 1]) and res[k] * res[k + 1] <= 0:
            root = brentq(residual, thetas[k], thetas[k + 1], xtol=1e-10)
            break
    if root is None:
        last = int(np.nonzero(np.isfinite(res))[0][-1]) if np.isfinite(res).any() else 0
        h0, F = state(thetas[last])
        return {"heights": h0, "forces": F, "centre": float(design.outer_diameter / 2 * math.sin(thetas[last])),
                "bend": float(thetas[last]), "reaction": float("nan"), "ok": False}
    h0, F = state(root)
    reaction = _pivot_balance(design, h0, F, psi)[1]
    return {"heights": h0, "forces": F, "centre": float(design.outer_diameter / 2 * math.sin(root)),
            "bend": float(root), "reaction": reaction, "ok": bool(reaction >= 0)}


def bonded_table2(design: RobotDesign | None = None, pressure: float = 40e3, c: float = BOND_RADIUS) -> list[dict]:
    """Table II rows ('bonded') with glued chambers (:func:`bonded_layer_pose`): the inflated chambers of
    layer A at ``pressure`` (Pa; default 40 kPa, below the robot's 45 kPa limit: the highest 5 kPa step at
    which every row has a taut exact equilibrium, stretch <= 4, for c = 1 mm), the others vented, bond
    radius c (m).
    Same keys as :func:`robot_table2` (stretch NaN: not tabulated), plus ``reaction_n`` (the rim's
    force), ``vented_height_mm``, ``vented_force_n`` and ``within_reach``."""
    d = design or RobotDesign(n_layers=2)
    d.validate()
    check_range("table2", "pressure", pressure, 0.0, 50e3, "Pa", lo_open=True)
    rows = []
    L = d.layer_thickness
    for n, pa, pl, pe in TABLE2_PAPER:
        r = bonded_layer_pose(d, list(range(n)), pressure, c)
        length = L + r["centre"]
        vent = [i for i in range(3) if i >= n]
        rows.append({
            "reading": "bonded", "inflated": n, "angle_deg": math.degrees(r["bend"]), "length_mm": U.to_mm(length),
            "extension_pct": 100 * (length - L) / L, "paper_angle_deg": pa, "paper_length_mm": pl,
            "paper_extension_pct": pe, "chamber_height_mm": U.to_mm(float(r["heights"][0])) if n else 0.0,
            "pressure_kpa": U.to_kpa(pressure) if n else 0.0, "stretch": float("nan"),
            "gas_mass_mg": float("nan"), "rim_gap_mm": 0.0 if 0 < n < 3 else U.to_mm(r["centre"]),
            "reaction_n": r["reaction"], "within_reach": r["ok"],
            "vented_height_mm": U.to_mm(float(r["heights"][vent[0]])) if vent else float("nan"),
            "vented_force_n": float(r["forces"][vent[0]]) if vent else float("nan"),
            "params": {"bond_radius_mm": U.to_mm(c), "pressure_kpa": U.to_kpa(pressure),
                       "r1_mm": U.to_mm(d.chamber.r1), "t0_mm": U.to_mm(d.chamber.t0)},
        })
    return rows


def _finite_or_none(v: float) -> float | None:
    """v, or None where it is not a finite number (JSON has no NaN)."""
    return float(v) if math.isfinite(v) else None


def paper_pose_check(design: RobotDesign | None = None, c: float | None = BOND_RADIUS) -> list[dict]:
    """Whether Table II's one- and two-chamber poses can be a static equilibrium of the rigid-layer robot.

    For each of those rows and two readings of the paper's length (``centre = length - L``, and
    ``length -`` the paper's own 0-chamber length, 9.6 mm, which includes a rest gap), the three-point
    pose through the paper's bend and length (bending away from the inflated chambers) gives the chamber
    heights (:func:`~hbma_ctrl.robot.kinematics.inverse_kinematics`), the forces the load sharing needs
    from each chamber under the bodies' weights (:func:`load_sharing`), the rim gap, and what a vented
    glued chamber gives at its height (:class:`~hbma_ctrl.robot.statics.BondedChamber` at p = 0, glue
    radius ``c``; None past its taut reach; ``c`` None: not computed, an empty list).

    Why it is decisive: at zero gauge pressure a chamber's force is ``-dU/dh`` (virtual work,
    ``F = p dV/dh - dU/dh``) and a membrane lifted from its flat rest state stores energy, so a lifted
    vented chamber pulls, whatever its law. A pose whose vented chambers must push is no equilibrium.
    The layer resting on its rim instead ties the centre to the bend (``R sin(bend)``):
    ``rim_radius_mm`` is the R the paper's row would need, beside the layer's.

    Returns one dict per (row, reading), edge units (deg, mm, N): inflated, reading, paper_angle_deg,
    paper_length_mm, centre_mm, heights_mm (3), needed_forces_n (3), vented_force_n (list, the vented
    chambers'), vented_must_push, rim_gap_mm, rim_radius_mm, layer_radius_mm, equilibrium (False when
    the vented chambers must push).
    """
    d = design or RobotDesign(n_layers=2)
    d.validate()
    ch = None if c is None else bonded_chamber(d.chamber, c)
    rest_len = U.mm(TABLE2_PAPER[0][2])
    L, R = d.layer_thickness, d.outer_diameter / 2
    flat = [0.0] * (d.n_layers - 1)  # the layers above A stay flat, as in robot_table2
    rows = []
    for n, pa, pl, _ in TABLE2_PAPER:
        if n not in (1, 2):
            continue
        inflated = list(range(n))
        vent = [i for i in range(3) if i not in inflated]
        a = np.asarray(d.chamber_angles)[inflated]
        psi = math.atan2(-np.sin(a).sum(), -np.cos(a).sum())  # away from the inflated chambers
        bend = math.radians(pa)
        for reading, centre in (("length - L", U.mm(pl) - L), ("length - paper rest length", U.mm(pl) - rest_len)):
            H = inverse_kinematics(d, [centre] + flat, [bend] + flat, [psi] + flat)
            share = load_sharing(d, H)
            need = share.forces[0]
            must_push = bool(np.all(need[vent] > 0))
            rows.append({
                "inflated": n, "reading": reading, "paper_angle_deg": pa, "paper_length_mm": pl,
                "centre_mm": U.to_mm(centre), "heights_mm": [U.to_mm(float(h)) for h in H[0]],
                "needed_forces_n": [float(f) for f in need],
                "vented_force_n": [] if ch is None else [_finite_or_none(ch.force(float(H[0, i]), 0.0)) for i in vent],
                "vented_must_push": must_push, "rim_gap_mm": U.to_mm(float(share.pose.rim_gap(d)[0])),
                "rim_radius_mm": U.to_mm(centre / math.sin(bend)), "layer_radius_mm": U.to_mm(R),
                "equilibrium": not must_push,
            })
    return rows


def paper_pose_markdown(rows: list[dict]) -> str:
    """Markdown of :func:`paper_pose_check` rows, with the conclusion in a closing line."""
    head = ("| HBMA inflated | paper length read as | centre (mm) | chamber h (mm) | forces needed (N) | "
            "vented glued chamber gives (N) | rim gap (mm) | rim radius needed / layer's (mm) |\n"
            "|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r['inflated']} | {r['reading']} | {r['centre_mm']:.2f} | "
        f"{', '.join(f'{h:.2f}' for h in r['heights_mm'])} | "
        f"{', '.join(f'{f:+.3f}' for f in r['needed_forces_n'])} | "
        f"{', '.join('beyond reach' if f is None else f'{f:+.2f}' for f in r['vented_force_n']) or '-'} | "
        f"{r['rim_gap_mm']:.2f} | {r['rim_radius_mm']:.1f} / {r['layer_radius_mm']:.0f} |\n" for r in rows)
    foot = ""
    if rows and not any(r["equilibrium"] for r in rows):
        foot = ("\nIn the paper's poses (its bend and length, the layer's three-point plane) the vented chambers, "
                "lifted several mm, would have to push; a lifted vented chamber pulls (F = -dU/dh at zero "
                "pressure). Resting on its rim instead, the layer's centre is R sin(bend): the rows would need "
                "the rim radius of the last column, not the layer's. No rigid-layer statics with the chambers "
                "at their places reproduces these rows.\n")
    return head + body + foot


def table2_markdown(rows: list[dict]) -> str:
    """Markdown table of :func:`robot_table2` rows (model vs paper), with the parameters used."""
    p = rows[0]["params"]
    head = ("| reading | HBMA inflated | angle model / paper (deg) | length model / paper (mm) | "
            "extension model / paper (%) | chamber h (mm) | p (kPa) | stretch | rim gap (mm) |\n"
            "|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r['reading']} | {r['inflated']} | {r['angle_deg']:.1f} / {r['paper_angle_deg']:.1f} | "
        f"{r['length_mm']:.1f} / {r['paper_length_mm']:.1f} | {r['extension_pct']:.0f} / "
        f"{r['paper_extension_pct']:.0f} | {r['chamber_height_mm']:.2f} | {r['pressure_kpa']:.1f} | "
        f"{r['stretch']:.2f} | {r['rim_gap_mm']:.2f} |\n".replace("| nan |", "| - |") for r in rows)
    mat = ", ".join(f"{k} = {v:g} Pa" if isinstance(v, float) else f"{k} = {v}" for k, v in p["material_params"].items())
    foot = (f"\nParameters: {p['material'].upper()} ({mat}), r1 = {p['r1_mm']:g} mm, t0 = {p['t0_mm']:g} mm, "
            f"V0 = {p['V0_cm3']:g} cm^3, chamber centres {p['placement_radius_mm']:g} mm from the axis, layer "
            f"{p['layer_thickness_mm']:g} mm / {p['layer_mass_g']:g} g, {p['n_layers']} chamber layers "
            f"(layer A evaluated, B flat). far_branch: inflated chambers held by gas mass at stretch "
            f"{p['stretch']:g}; near_branch: held at {p['hold_pressure_kpa']:g} kPa below the limit point; "
            "rim_pivot: far-branch chambers, the layer rocking on its outer rim instead of the rigid "
            "three-point pose (whose rims would overlap with a flat chamber).\n")
    bonded = [r for r in rows if r["reading"] == "bonded"]
    if bonded:
        b = bonded[0]["params"]
        foot += (f"bonded: chambers glued to the layer above (exact membrane, a rigid glue spot of radius "
                 f"{b['bond_radius_mm']:g} mm at each centre), the inflated ones at {b['pressure_kpa']:g} kPa, the "
                 "others vented; with one or two inflated the layer rests on its outer rim and the vented glued "
                 "chambers, pulled up, pull it back (tension); stretch not tabulated (-).\n")
    return head + body + foot


# ---------------------------------------------------------------------------------------------
# workspace
# ---------------------------------------------------------------------------------------------
def _max_bend(design: RobotDesign, h_max: float, psi: np.ndarray) -> np.ndarray:
    """Largest bend (rad) in directions psi with every chamber height in [0, h_max]."""
    a = np.asarray(design.chamber_angles)
    rc = design.placement_radius
    c = np.cos(psi[:, None] - a[None, :])
    spread = rc * (c.max(1) - c.min(1))
    return np.arctan(h_max / spread)


def _max_bend_clear(design: RobotDesign, h_max: float, psi: np.ndarray) -> np.ndarray:
    """Largest bend (rad) in directions psi with heights in [0, h_max] and no rim overlap."""
    a = np.asarray(design.chamber_angles)
    rc, R = design.placement_radius, design.outer_diameter / 2
    c = np.cos(psi[:, None] - a[None, :])
    cmax, cmin = c.max(1), c.min(1)

    def need(t):  # the highest chamber's height at the lowest feasible centre height
        hc = np.maximum(rc * t * cmax, R * np.sin(np.arctan(t)))
        return hc - rc * t * cmin

    lo, hi = np.zeros(psi.size), np.full(psi.size, 50.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        ok = need(mid) <= h_max
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return np.arctan(lo)


def workspace(design: RobotDesign | None = None, pressure_limit: float = 45e3,
              pneumatics: Pneumatics | None = None, n_dir: int = 72) -> dict:
    """Reachable workspace at the pressure limit, per layer and for the tip (SI, plain data).

    Each chamber's reach is :func:`chamber_reach` at its load share in the straight pose (the
    load changes little with the pose for this light robot); a layer's reach is the smallest of its
    three. Per layer: the centre-height range at zero bend [0, h_max] and the largest bend angle
    against direction (all three heights within [0, h_max]; at the largest bend the centre height
    is fixed). The same numbers for pressure control (near branch only) show what passing the
    limit point buys. ``bend_max_no_rim_contact`` adds the condition that the rigid layers' rims do
    not overlap (:meth:`~hbma_ctrl.robot.kinematics.RobotPose.rim_gap` >= 0): what the three-point
    kinematics can really reach (larger bends make the layer rock on its rim). Tip: every layer bent
    alike (constant curvature).
    """
    d = (design or RobotDesign()).validate()
    F = load_sharing(d, np.zeros((d.n_layers, 3))).forces
    psi = np.linspace(0, 2 * math.pi, n_dir, endpoint=False)
    layers = []
    for k in range(d.n_layers):
        rs = [chamber_reach(d, F[k, i], pressure_limit, pneumatics) for i in range(3)]
        hm = min(r.h_max for r in rs)
        hpc = min(r.h_pressure_control for r in rs)
        layers.append({
            "layer": LETTERS[k], "load_n": F[k].tolist(), "h_max": hm,
            "limit": [r.limit for r in rs], "p_peak": max(r.p_peak for r in rs),
            "h_peak": min(r.h_peak for r in rs), "p_at_max": max(r.p_at_max for r in rs),
            "h_pressure_control": hpc,
            "bend_max": _max_bend(d, hm, psi).tolist(),
            "bend_max_pressure_control": _max_bend(d, hpc, psi).tolist(),
            "bend_max_no_rim_contact": _max_bend_clear(d, hm, psi).tolist(),
        })
    bend_tip = np.sum([ly["bend_max"] for ly in layers], axis=0)
    return {
        "direction": psi.tolist(), "layers": layers,
        "tip_bend_max": bend_tip.tolist(),
        "tip_height_range": [d.n_layers * d.layer_thickness + d.layer_thickness,
                             d.n_layers * d.layer_thickness + d.layer_thickness + sum(ly["h_max"] for ly in layers)],
        "pressure_limit": pressure_limit, "pump_stall": pump_stall_pressure(pneumatics),
        "max_stretch": d.max_stretch,
    }
