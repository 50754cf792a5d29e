"""Statics: load sharing between a layer's chambers and each chamber's membrane state (SI).

Statics
-------
The chambers push body k + 1 along its normal (the contact normal). For the sub-assembly of bodies
k + 1..N, its weight and an optional tip load (force and moment, world frame) give three equations
in the three normal forces: force along the normal and the moments about the two in-plane axes
through the contact centroid. The in-plane force and the twisting moment are carried by the glued
membranes in shear (reported, not modelled). A negative force means the glue pulls (tension): the
ballooning-membrane model does not cover it, and such chambers are flagged.

Bonded chambers
---------------
The paper glues each membrane's centre to the layer above (Sil-Poxy). :class:`BondedChamber` models
that glue spot as a rigid disk of radius ``c`` (:data:`BOND_RADIUS`, an assumption: the paper gives no
size) on the exact membrane (:class:`hbma_ctrl.models.exact.ExactMembrane`, contact 'bonded', docs/concepts/model.md
§9): the force on the layer ``F(h, p)`` can exceed ``p pi c^2`` (a membrane bulging around the
disk lifts it) and is negative for a vented chamber pulled up (the glue pulls the layer down). The
table of F over (h, p) is solved once per chamber, material and c and cached on disk like the exact
membrane's other tables; :meth:`BondedChamber.pressure` gives a chamber's pressure for its height and
force, tension allowed. Its limits are the exact solver's: membrane stretches up to 4, no slack (wrinkled)
membrane; outside them the table holds NaN and the chamber is reported as beyond its reach.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

from pathlib import Path

import numpy as np

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.exact import ExactMembrane
from hbma_ctrl.models.exact_tables import _cached, _key, table_cache_dir
from hbma_ctrl.models.shape import ShapeSolver
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.kinematics import (
    RobotPose,
    _cross,
    _heights_array,
    forward_kinematics,
)

__all__ = ["LoadShare", "load_sharing", "chamber_solver", "chamber_states", "BOND_RADIUS", "BOND_H", "BOND_P",
           "bonded_table", "BondedChamber", "bonded_chamber"]


@dataclass
class LoadShare:
    """Chamber normal forces and what the membranes carry in shear (SI).

    forces : (N, 3) normal force each chamber pushes the layer above with, N (negative = tension,
    the glue pulls); shear : (N, 2) in-plane force on the membranes of each layer, N; twist : (N,)
    moment about the layer normal, N m; pose : the :class:`RobotPose` used.
    """

    forces: np.ndarray
    shear: np.ndarray
    twist: np.ndarray
    pose: RobotPose


def load_sharing(design: RobotDesign, heights, tip_force=(0.0, 0.0, 0.0), tip_moment=(0.0, 0.0, 0.0)
                 ) -> LoadShare:
    """Each chamber's contact force from the weight of the bodies above and an optional tip load.

    heights : chamber heights (N x 3), m; tip_force (N) and tip_moment (N m) act on the top body at
    the tip point, world frame. For chamber layer k the sub-assembly of bodies k + 1..N is in
    equilibrium under its weight, the tip load and the three normal forces (plus membrane shear):
    3 equations (force along the layer normal, moments about the two in-plane axes through the
    contact centroid) for 3 forces.
    """
    pose = forward_kinematics(design, heights)
    f_tip = np.asarray(tip_force, dtype=float).reshape(3)
    m_tip = np.asarray(tip_moment, dtype=float).reshape(3)
    if not (np.all(np.isfinite(f_tip)) and np.all(np.isfinite(m_tip))):
        raise ValueError("tip_force and tip_moment must be finite")
    N, L = design.n_layers, design.layer_thickness
    # every layer at once (the daemon computes this each period; a loop over the layers cost 0.45 ms)
    frames = pose.frames[1:]
    R, O = frames[:, :3, :3], frames[:, :3, 3]  # frame k + 1 of each chamber layer k, (N, 3, 3), (N, 3)
    w = design.body_masses[:, None] * np.array([0.0, 0.0, -design.g])  # weights of bodies 1..N, (N, 3)
    # centres of mass of bodies 1..N (mid-thickness on their axis)
    com = R[:, :, 2] * (L / 2) + O
    # bodies k+1..N are rows k..N-1: suffix sums of the weights and of their moments about the origin
    f = np.cumsum(w[::-1], axis=0)[::-1] + f_tip
    m0 = np.cumsum(_cross(com, w)[::-1], axis=0)[::-1]
    # about O_k: sum (com_j - O_k) x w_j + (tip - O_k) x f_tip + m_tip
    M = m0 - _cross(O, f) + _cross(pose.tip_position, f_tip) + m_tip
    fl, Ml = np.einsum("kji,kj->ki", R, f), np.einsum("kji,kj->ki", R, M)
    pts = np.einsum("kji,kmj->kmi", R, pose.contacts - O[:, None, :])  # contacts in frame k+1 (z ~ 0)
    A = np.stack([np.ones((N, 3)), pts[:, :, 1], pts[:, :, 0]], axis=1)
    rhs = np.stack([-fl[:, 2], -Ml[:, 0], Ml[:, 1]], axis=1)
    forces = np.linalg.solve(A, rhs[:, :, None])[:, :, 0]
    shear = -fl[:, :2]
    twist = -Ml[:, 2]
    return LoadShare(forces, shear, twist, pose)


# ---------------------------------------------------------------------------------------------
# the chamber model (physics), batched
# ---------------------------------------------------------------------------------------------
@lru_cache(maxsize=16)
def chamber_solver(act: Actuator, pn: Pneumatics | None = None) -> ShapeSolver:
    """The shape solver of one robot chamber (cached: its mapped casadi Functions are reused)."""
    space = ph.ParamSpace.for_material(act.material)
    return ShapeSolver(space, space.values(act, pn or Pneumatics(), Platform()))


def chamber_states(design: RobotDesign, heights, tip_force=(0.0, 0.0, 0.0), tip_moment=(0.0, 0.0, 0.0),
                   forces=None) -> dict:
    """Each chamber's membrane state consistent with the layer equilibrium, for chamber heights (m).

    Returns a dict of (N, 3) arrays: h1, h2 (m), p (Pa), F (N, the load share), lam (-), V (m^3),
    m (gas mass, kg), and boolean flags ``resting`` (h = 0: the upper layer sits on the lower one,
    the stop carries F, the chamber is vented: p = 0) and ``tension`` (F < 0: the glue pulls; the
    membrane is treated as free, h2 = 0, its contact force 0). ``forces`` overrides the load
    sharing (e.g. a controller's per-chamber load estimate, used as the load W of each model).
    """
    h = _heights_array(design, heights)
    F = load_sharing(design, h, tip_force, tip_moment).forces if forces is None else \
        np.asarray(forces, dtype=float).reshape(h.shape)
    ch = chamber_solver(design.chamber)
    resting = h <= 0
    tension = (F < 0) & ~resting
    push = (F > 0) & ~resting
    h2 = np.zeros(h.shape)
    if push.any():
        h2[push] = ch.h2_for_force(h[push], F[push])
    h1 = h + h2
    out = ch.eval(h1, h2)
    act = design.chamber
    p = np.where(resting, 0.0, out["p"])
    V = np.where(resting, act.V0, out["V"])
    m = (p + act.p_env) * V / (act.R * act.T)
    return {"h1": h1, "h2": h2, "p": p, "F": F, "lam": np.where(resting, 1.0, out["lam"]), "V": V, "m": m,
            "resting": resting, "tension": tension}


# ---------------------------------------------------------------------------------------------
# chambers glued to the layer above (exact membrane, bonded disk)
# ---------------------------------------------------------------------------------------------
#: radius of the glue spot joining a membrane's centre to the layer above, m: an assumption (the paper
#: says only that Sil-Poxy was glued to the membranes' centres); ``robot table2 --bond-radius-mm`` sets it
BOND_RADIUS = 1.0e-3
#: the bonded force table's grid: centre height (m) x gauge pressure (Pa); the robot's limit is 45 kPa
BOND_H = np.concatenate([[0.1e-3], np.arange(0.25e-3, 8.01e-3, 0.25e-3)])
BOND_P = np.arange(0.0, 50.01e3, 5e3)


def bonded_table(act: Actuator, c: float = BOND_RADIUS, cache: Path | str | None = None, h: np.ndarray = BOND_H,
                 p: np.ndarray = BOND_P, low_misses: bool = False) -> dict:
    """Force F (N, up positive) and membrane volume V (m^3, above the clamp) of a chamber glued at its
    centre to a rigid disk of radius c (m), over the grid h x p (centre heights > 0, m, and gauge
    pressures >= 0, Pa, both increasing; default the robot's :data:`BOND_H` x :data:`BOND_P`).

    Each node is one exact bonded equilibrium (:meth:`ExactMembrane.contact`); NaN where there is none
    (a stretch beyond 4 or a slack membrane: past the chamber's reach at that pressure); two misses in a
    row end a pressure's column, or with ``low_misses`` only after its first equilibrium (a high pressure
    can overstretch the annulus of a disk held low and still balance a disk lifted higher). Cached on disk
    (npz keyed by every input and the exact modules' source; ``cache`` a directory, default the exact
    tables' one); a first build takes a few minutes. Returns h, p, F, V, build_s, path.
    """
    if not (np.isfinite(c) and 0 < c < act.r1):
        raise ValueError(f"bond radius = {c * 1e3:g} mm is out of range (0, {act.r1 * 1e3:g}) mm (the chamber's r1)")
    m = ExactMembrane(act.material, act.r1, act.t0, contact="bonded", c=c)
    h, p = np.asarray(h, dtype=float), np.asarray(p, dtype=float)
    folder = Path(cache) if cache is not None else table_cache_dir()
    grids = {"h": h, "p": p} | ({"low_misses": 1.0} if low_misses else {})
    path = folder / f"bonded_robot_{_key(m, 'bonded_robot_v1', grids)}.npz"

    def build():
        F, V = np.full((h.size, p.size), np.nan), np.full((h.size, p.size), np.nan)
        for j, pj in enumerate(p):
            misses, reached = 0, False
            for i, hi in enumerate(h):
                try:
                    r = m.contact(hi, pj)
                except ValueError:
                    misses += 1
                    if misses >= 2 and (reached or not low_misses):
                        break  # past the reach at this pressure: higher centres are out of reach too
                    continue
                misses, reached = 0, True
                F[i, j], V[i, j] = r["F"], r["V"]
        return {"h": h, "p": p, "F": F, "V": V}

    return _cached(path, build)


class BondedChamber:
    """One glued robot chamber: F(h, p) from :func:`bonded_table` and its inverses (SI).

    F is interpolated bilinearly on the table (NaN outside its valid part); below the first height
    node it is continued linearly to F(0, 0) = 0 for a vented chamber (flat membrane, no force).
    Along a fixed pressure F falls as the centre rises (the stretched membrane pulls the disk down);
    at a fixed height it grows with the pressure.
    """

    def __init__(self, act: Actuator, c: float = BOND_RADIUS):
        tab = bonded_table(act, c)
        self.act, self.c = act, float(c)
        self.h, self.p, self.F, self.V = tab["h"], tab["p"], tab["F"], tab["V"]

    def _column(self, p: float) -> np.ndarray:
        """F over the height grid at pressure p (Pa), linear between pressure columns."""
        j = int(np.clip(np.searchsorted(self.p, p) - 1, 0, self.p.size - 2))
        w = (p - self.p[j]) / (self.p[j + 1] - self.p[j])
        return (1 - w) * self.F[:, j] + w * self.F[:, j + 1]

    def force(self, h: float, p: float) -> float:
        """Force (N, up positive) on the layer above at centre height h (m) and gauge pressure p (Pa)."""
        if not (0.0 <= p <= self.p[-1]):
            return float("nan")
        col = self._column(p)
        if h <= self.h[0]:
            f0 = 0.0 if p == 0.0 else col[0] - (col[1] - col[0]) / (self.h[1] - self.h[0]) * self.h[0]
            return float(f0 + (col[0] - f0) * h / self.h[0])
        if h > self.h[-1]:
            return float("nan")
        return float(np.interp(h, self.h, col))  # NaN next to a NaN node: beyond the reach

    def reach(self, p: float) -> float:
        """Largest tabulated centre height (m) with an equilibrium at pressure p (Pa)."""
        ok = np.isfinite(self._column(p))
        return float(self.h[np.nonzero(ok)[0][-1]]) if ok.any() else 0.0

    def height(self, F: float, p: float) -> float:
        """Centre height (m) at which the chamber at pressure p (Pa) pushes with F (N); 0 when it cannot
        push that hard even flat (it rests), NaN when F lies below what it reaches (beyond the table)."""
        col = self._column(p)
        ok = np.isfinite(col)
        hs, fs = np.concatenate([[0.0], self.h[ok]]), np.concatenate([[self.force(0.0, p)], col[ok]])
        if F >= fs[0]:
            return 0.0
        if F < fs.min():
            return float("nan")
        k = int(np.nonzero(fs <= F)[0][0])  # first node at or below F: F falls along the column
        return float(hs[k - 1] + (F - fs[k - 1]) / (fs[k] - fs[k - 1]) * (hs[k] - hs[k - 1]))

    def pressure(self, h: float, F: float) -> float:
        """Gauge pressure (Pa) that makes the chamber at centre height h (m) push with F (N; negative =
        the glue pulls); NaN outside the table."""
        fs = np.array([self.force(h, pj) for pj in self.p])
        ok = np.isfinite(fs)
        if ok.sum() < 2 or not (fs[ok].min() <= F <= fs[ok].max()):
            return float("nan")
        return float(np.interp(F, fs[ok], self.p[ok]))


@lru_cache(maxsize=8)
def bonded_chamber(act: Actuator, c: float = BOND_RADIUS) -> BondedChamber:
    """The :class:`BondedChamber` of a robot chamber and bond radius (cached here and on disk)."""
    return BondedChamber(act, c)
