"""The hybrid soft-rigid continuum robot (SPEC 8, paper II-C / IV-C): statics and kinematics.

Layers of three HBMA each are stacked along z; every chamber is inflated on its own and its
membrane centre is glued to the layer above. This module holds the robot as data
(:class:`RobotDesign`), its forward and inverse kinematics, the load sharing between the chambers
of a layer, the per-chamber membrane state consistent with that load (through
:mod:`hbma_ctrl.physics`; no physics is re-derived here), each chamber's reachable height and what
limits it, the paper's Table II beside the model, the reachable workspace, and an open-loop scene
(the paper's Fig. 10 sequential inflation). The closed-loop scene (``[robot] mode = "closed_loop"``:
per-chamber EKF bank + structured NMPC, or a pressure-PID baseline, on a mismatched rig) lives in
:mod:`controllers.robot_loop`; :func:`run_scene` dispatches to it.

Bodies and frames
-----------------
Body 0 is the bottom layer (fixed to the ground), bodies 1..N sit on the chambers of the body
below; chamber layer k (letters A, B, C, ... from the bottom, numbers 1..3, as in Fig. 10) lives
in body k and pushes body k + 1. Body N is the top part (end plate, no chambers used). Frame k sits
at the centre of body k's bottom face, z along the layer's axis. Body k's membranes lie in its top
plane ``z = L`` (L = layer thickness, 9 mm with the flat 2 mm membrane). A chamber's *height* h is
the membrane height of SPEC 1 (``h = h1 - h2``): the gap the chamber opens between body k's top
plane and body k + 1's bottom face, at the chamber centre.

Kinematic assumption (stated once, used everywhere)
---------------------------------------------------
Body k + 1's bottom face is the plane through the three contact points
``P_i = (rc cos phi_i, rc sin phi_i, L + h_i)`` (frame k): chamber heights are measured along
body k's axis, and the glued membrane apexes do not move sideways. Because three heights generally
distort the triangle of contact points, the rigid upper layer cannot fit it exactly; the membranes
absorb the small in-plane mismatch in shear. Frame k + 1 is placed at the centroid of the P_i
(on body k's axis, at ``L + mean(h)``) and rotated from frame k without twist: about the in-plane
axis ``(-sin psi, cos psi, 0)`` by the bend angle ``theta``, which maps z onto the plane normal
``(sin theta cos psi, sin theta sin psi, cos theta)``. ``psi`` is the bend *direction* (where the
layer's top leans to); a single inflated chamber at angle phi_i bends the layer toward
``phi_i + 180 deg``. This is the piecewise-constant-curvature view of Webster and Jones (paper ref.
[23]) with one rigid link per layer. Each chamber's membrane is modelled as in the single-actuator
model: a spherical segment pressed by a plane parallel to its retaining disk (SPEC 1); the tilt of
the plane over one membrane (a few mm wide) is neglected.

Rim contact (a limit of the three-point assumption)
---------------------------------------------------
The layers are rigid 44 mm disks. A three-point pose with a flat chamber (h = 0) always makes the
upper layer's rim dip below the lower layer's top face (``RobotPose.rim_gap`` = centre -
R sin(bend) < 0): with one chamber at 17 mm the overlap is about 7 mm. A real layer then rocks on
its rim and the glued, uninflated membranes are pulled up (tension). :func:`reach_report` flags
such poses, :func:`workspace` reports the bend reachable with the rims clear, and
:func:`robot_table2` gives a ``rim_pivot`` reading, which is the one closest to the paper's data.

Statics
-------
The chambers push body k + 1 along its normal (the contact normal). For the sub-assembly of bodies
k + 1..N, its weight and an optional tip load (force and moment, world frame) give three equations
in the three normal forces: force along the normal and the moments about the two in-plane axes
through the contact centroid. The in-plane force and the twisting moment are carried by the glued
membranes in shear (reported, not modelled). A negative force means the glue pulls (tension): the
ballooning-membrane model does not cover it, and such chambers are flagged.

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

import json
import math
import time
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

from . import physics as ph
from . import units as U
from .materials import Material, make_material
from .params import Actuator, Platform, Pneumatics, check_range
from .validation import did_you_mean

__all__ = [
    "RobotDesign", "RobotPneumatics", "RobotSettings", "RobotPose", "ChamberReach",
    "chamber_names", "layer_plane", "layer_transform", "forward_kinematics", "inverse_kinematics",
    "inverse_kinematics_tip", "load_sharing", "chamber_loads", "chamber_states", "chamber_states_from_masses",
    "chamber_reach", "reach_report", "simulate_open_loop", "run_metrics", "pump_stall_pressure",
    "robot_table2", "table2_markdown", "workspace", "parse_section", "run_scene", "TABLE2_PAPER",
    "TOPOLOGIES",
]

LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
TOPOLOGIES = ("per_chamber", "shared")
OUTLETS = ("per_chamber",)

#: the paper's Table II: (HBMA inflated, angle deg, length mm, extension %)
TABLE2_PAPER = ((0, 2.3, 9.6, 0.0), (1, 28.9, 18.0, 88.0), (2, 28.5, 23.0, 140.0), (3, 1.3, 26.7, 179.0))


def _robot_chamber() -> Actuator:
    return Actuator(r1=4.5e-3, t0=2e-3, V0=3e-6, material=make_material("nh"))


# ---------------------------------------------------------------------------------------------
# the robot as data
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RobotDesign:
    """A stack of HBMA layers (SI). Defaults: the paper's robot (SPEC 8, Fig. 1: 9 HBMA).

    Fields
    ------
    n_layers : number of chamber layers N (bodies 0..N; body N is the top part), 1-26.
    placement_radius : chamber centres' distance from the axis, m (15.4 mm: the 8.75-22 mm annulus
        of a 17.5/44 mm layer holds an r1 = 4.5 mm disk with margin).
    chamber_angles : the three chambers' angles about the axis, rad (0, 120, 240 deg); the same in
        every layer (chambers of consecutive layers aligned).
    layer_thickness : body thickness with the flat membrane, m (9 mm).
    outer_diameter, inner_diameter : layer annulus, m (44, 17.5 mm; the tubing passes inside).
    layer_mass : mass of one layer body, kg (17.6 g).
    end_mass : mass of the top body N, kg; None = a layer's mass.
    chamber : the HBMA of every chamber (r1 4.5 mm, t0 2 mm, V0 3 cm^3 assumed as Table I, NH).
    max_stretch : largest equi-biaxial membrane stretch allowed (-), an assumed safe limit below
        rupture (Ecoflex 00-30); it sets the far-branch reach (see :func:`chamber_reach`).
    g : gravity, m/s^2 (acts along -z of the world; the base is level).
    """

    n_layers: int = 3
    placement_radius: float = 15.4e-3
    chamber_angles: tuple = (0.0, 2 * math.pi / 3, 4 * math.pi / 3)
    layer_thickness: float = 9e-3
    outer_diameter: float = 44e-3
    inner_diameter: float = 17.5e-3
    layer_mass: float = 17.6e-3
    end_mass: float | None = None
    chamber: Actuator = field(default_factory=_robot_chamber)
    max_stretch: float = 4.0
    g: float = U.G_STD

    def validate(self) -> "RobotDesign":
        """Check every field; ValueError names the field and its range."""
        if not isinstance(self.n_layers, int) or isinstance(self.n_layers, bool) or not 1 <= self.n_layers <= 26:
            raise ValueError(f"robot.n_layers = {self.n_layers!r} must be an integer in [1, 26]")
        check_range("robot", "layer_thickness", self.layer_thickness, 1e-3, 0.1, "m")
        check_range("robot", "inner_diameter", self.inner_diameter, 0.0, 0.5, "m")
        check_range("robot", "outer_diameter", self.outer_diameter, self.inner_diameter, 0.5, "m",
                    lo_open=True)
        check_range("robot", "layer_mass", self.layer_mass, 0.0, 10.0, "kg")
        if self.end_mass is not None:
            check_range("robot", "end_mass", self.end_mass, 0.0, 10.0, "kg")
        check_range("robot", "g", self.g, 0.0, 100.0, "m/s^2")
        self.chamber.validate()
        r1 = self.chamber.r1
        lo, hi = self.inner_diameter / 2 + r1, self.outer_diameter / 2 - r1
        check_range("robot", "placement_radius", self.placement_radius, lo, hi, "m "
                    f"(the chamber disk r1 = {r1 * 1e3:g} mm must fit the layer annulus)")
        if len(self.chamber_angles) != 3:
            raise ValueError(f"robot.chamber_angles must hold 3 angles, got {len(self.chamber_angles)}")
        for i, a in enumerate(self.chamber_angles):
            check_range("robot", f"chamber_angles[{i}]", a, -2 * math.pi, 2 * math.pi, "rad")
        # the support triangle must contain the axis well (else the 3x3 statics is ill posed) and
        # the chambers must not overlap
        xy = self.chamber_xy()
        for i in range(3):
            for j in range(i + 1, 3):
                if np.linalg.norm(xy[i] - xy[j]) < 2 * r1:
                    raise ValueError(f"robot.chamber_angles: chambers {i + 1} and {j + 1} overlap "
                                     f"(centres {np.linalg.norm(xy[i] - xy[j]) * 1e3:.1f} mm apart, "
                                     f"need >= 2 r1 = {2 * r1 * 1e3:g} mm)")
        gaps = np.diff(np.sort(np.mod(np.asarray(self.chamber_angles), 2 * math.pi)))
        gaps = np.append(gaps, 2 * math.pi - gaps.sum())
        if gaps.max() >= math.pi - 1e-6:
            raise ValueError("robot.chamber_angles: the three chambers must not lie in one half-plane "
                             "(the layer would tip over; every gap between angles must be < 180 deg)")
        check_range("robot", "max_stretch", self.max_stretch, 1.05, min(20.0, self.chamber.material.lam_max()))
        return self

    # derived data --------------------------------------------------------------------------
    def chamber_xy(self) -> np.ndarray:
        """Chamber centres in a layer frame, (3, 2) m."""
        a = np.asarray(self.chamber_angles, dtype=float)
        return self.placement_radius * np.column_stack([np.cos(a), np.sin(a)])

    @property
    def body_masses(self) -> np.ndarray:
        """Masses of the moving bodies 1..N, kg."""
        m = np.full(self.n_layers, self.layer_mass)
        m[-1] = self.layer_mass if self.end_mass is None else self.end_mass
        return m

    @property
    def names(self) -> list[str]:
        return chamber_names(self.n_layers)

    def with_(self, **kw) -> "RobotDesign":
        """A validated copy with some fields replaced."""
        return replace(self, **kw).validate()


def chamber_names(n_layers: int) -> list[str]:
    """Chamber names layer-major, as in Fig. 10: A1, A2, A3, B1, ..."""
    return [f"{LETTERS[k]}{i + 1}" for k in range(n_layers) for i in range(3)]


@dataclass(frozen=True)
class RobotPneumatics:
    """How the chambers are supplied (data now; the robot controller uses it later).

    topology : 'per_chamber' (one compressor per chamber) or 'shared' (one compressor feeding every
        chamber through its own inlet valve; the open-loop scene then runs the pump at the highest
        speed any open inlet asks for and splits its flow equally among the open inlets).
    outlets : 'per_chamber' (each chamber vents through its own outlet valve; the only layout built).
    sensor_range : pressure at which each chamber's sensor saturates, Pa (50 kPa).
    pressure_limit : largest chamber pressure allowed, Pa (45 kPa); must not exceed the sensor range.
    """

    topology: str = "per_chamber"
    outlets: str = "per_chamber"
    sensor_range: float = 50e3
    pressure_limit: float = 45e3

    def validate(self) -> "RobotPneumatics":
        for name, allowed in (("topology", TOPOLOGIES), ("outlets", OUTLETS)):
            v = getattr(self, name)
            if v not in allowed:
                hint = did_you_mean(str(v), allowed)
                raise ValueError(f"robot.{name} = '{v}'{hint}; allowed: {', '.join(allowed)}")
        check_range("robot", "sensor_range", self.sensor_range, 1e3, 1e6, "Pa")
        check_range("robot", "pressure_limit", self.pressure_limit, 1e3, self.sensor_range, "Pa "
                    "(at most the sensor range)")
        return self

    def n_compressors(self, n_chambers: int) -> int:
        return n_chambers if self.topology == "per_chamber" else 1


# ---------------------------------------------------------------------------------------------
# kinematics
# ---------------------------------------------------------------------------------------------
def _rot(theta: float, psi: float) -> np.ndarray:
    """Twist-free rotation mapping z onto (sin t cos psi, sin t sin psi, cos t)."""
    u = np.array([-math.sin(psi), math.cos(psi), 0.0])
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K


def _plane_matrix(design: RobotDesign) -> np.ndarray:
    xy = design.chamber_xy()
    return np.column_stack([np.ones(3), xy])  # h_i = hc' + a x_i + b y_i


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (numpy's is slow for tiny arrays)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _plane_of(Ainv: np.ndarray, h: np.ndarray) -> tuple[float, float, float]:
    c, a, b = Ainv @ h
    t = math.hypot(a, b)
    if t < 1e-12:  # level (to rounding): direction 0 by convention
        return float(c), 0.0, 0.0
    return float(c), math.atan(t), math.atan2(-b, -a)


def layer_plane(design: RobotDesign, heights) -> tuple[float, float, float]:
    """(centre height m, bend angle rad in [0, pi/2), bend direction rad in (-pi, pi]) of the plane
    through a layer's three contact points, for its chamber heights (3,) in m.

    The centre height is the plane's height on the layer axis (= mean height for chambers at 120
    degrees). Zero bend has direction 0 by convention.
    """
    return _plane_of(np.linalg.inv(_plane_matrix(design)), np.asarray(heights, dtype=float).reshape(3))


def layer_transform(design: RobotDesign, heights) -> np.ndarray:
    """4x4 transform from frame k to frame k + 1 for layer k's chamber heights (3,), m."""
    c, theta, psi = layer_plane(design, heights)
    T = np.eye(4)
    T[:3, :3] = _rot(theta, psi)
    T[:3, 3] = [0.0, 0.0, design.layer_thickness + c]
    return T


@dataclass
class RobotPose:
    """Result of :func:`forward_kinematics` (SI, world = frame 0).

    frames : (N + 1, 4, 4) body frames (bottom-face centres); tip : 4x4 frame at the top face of
    body N; heights : (N, 3) chamber heights; centre, bend, direction : (N,) per chamber layer, m and
    rad (relative to the layer below); contacts : (N, 3, 3) contact points in the world, m.
    """

    frames: np.ndarray
    tip: np.ndarray
    heights: np.ndarray
    centre: np.ndarray
    bend: np.ndarray
    direction: np.ndarray
    contacts: np.ndarray

    @property
    def tip_position(self) -> np.ndarray:
        return self.tip[:3, 3]

    @property
    def tip_bend(self) -> float:
        """Angle between the tip axis and the world z axis, rad."""
        return float(math.acos(np.clip(self.tip[2, 2], -1.0, 1.0)))

    def layer_lengths(self, design: RobotDesign) -> np.ndarray:
        """Distance between successive body frames along the layer axes, m (L + centre height)."""
        return design.layer_thickness + self.centre

    def rim_gap(self, design: RobotDesign) -> np.ndarray:
        """Smallest gap between each upper body's bottom rim and the body below's top face, m.

        ``centre - R sin(bend)`` with R the outer radius; negative = the rigid layers would overlap,
        i.e. the real robot rocks on its rim there (see :func:`rim_pivot_pose`).
        """
        return self.centre - design.outer_diameter / 2 * np.sin(self.bend)


def _heights_array(design: RobotDesign, heights) -> np.ndarray:
    h = np.asarray(heights, dtype=float)
    if h.size != 3 * design.n_layers:
        raise ValueError(f"heights: need {3 * design.n_layers} chamber heights ({design.n_layers} layers x 3), "
                         f"got {h.size}")
    h = h.reshape(design.n_layers, 3)
    if not np.all(np.isfinite(h)) or h.min() < 0:
        raise ValueError("heights: chamber heights must be finite and >= 0 m")
    return h


def forward_kinematics(design: RobotDesign, heights) -> RobotPose:
    """Chamber heights (N x 3 or 3N, m) -> every body's frame and the tip frame (see module doc)."""
    h = _heights_array(design, heights)
    N = design.n_layers
    frames = np.zeros((N + 1, 4, 4))
    frames[0] = np.eye(4)
    cen, bend, dirn = np.zeros(N), np.zeros(N), np.zeros(N)
    contacts = np.zeros((N, 3, 3))
    xy = design.chamber_xy()
    L = design.layer_thickness
    Ainv = np.linalg.inv(_plane_matrix(design))
    for k in range(N):
        cen[k], bend[k], dirn[k] = _plane_of(Ainv, h[k])
        T = np.eye(4)
        T[:3, :3] = _rot(bend[k], dirn[k])
        T[:3, 3] = [0.0, 0.0, L + cen[k]]
        frames[k + 1] = frames[k] @ T
        local = np.column_stack([xy, L + h[k], np.ones(3)])
        contacts[k] = (frames[k] @ local.T).T[:, :3]
    tip = frames[N].copy()
    tip[:3, 3] = frames[N][:3, :3] @ np.array([0, 0, L]) + frames[N][:3, 3]
    return RobotPose(frames, tip, h, cen, bend, dirn, contacts)


def inverse_kinematics(design: RobotDesign, centre, bend, direction) -> np.ndarray:
    """Per-layer targets -> chamber heights (N, 3), m.

    centre : centre height(s) of each layer's upper plane above its membranes, m (scalar = all
    layers); bend : bend angle(s) relative to the layer below, rad, in [0, pi/2); direction : bend
    direction(s), rad. Exact inverse of :func:`layer_plane`. Heights may come out negative or beyond
    a chamber's reach: check them with :func:`reach_report` (no clamping here).
    """
    N = design.n_layers
    c = np.broadcast_to(np.asarray(centre, dtype=float), (N,))
    th = np.broadcast_to(np.asarray(bend, dtype=float), (N,))
    ps = np.broadcast_to(np.asarray(direction, dtype=float), (N,))
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(th)) and np.all(np.isfinite(ps))):
        raise ValueError("inverse_kinematics: targets must be finite")
    if th.min() < 0 or th.max() >= math.pi / 2:
        raise ValueError(f"inverse_kinematics: bend must be in [0, 90) deg, got {np.degrees(th)}")
    A = _plane_matrix(design)
    out = np.zeros((N, 3))
    for k in range(N):
        t = math.tan(th[k])
        out[k] = A @ np.array([c[k], -t * math.cos(ps[k]), -t * math.sin(ps[k])])
    return out


def inverse_kinematics_tip(design: RobotDesign, tip_position, h_max: float | None = None) -> np.ndarray:
    """Tip position (3,) m -> chamber heights (N, 3) m, every layer identical (constant curvature).

    The N identical layers give 3 unknowns (centre height, bend, direction) for 3 equations; solved
    by least squares from a straight start. Raises ValueError when no such shape reaches the point
    within 1e-6 m (or, with ``h_max``, within chamber heights 0..h_max).
    """
    from scipy.optimize import least_squares

    target = np.asarray(tip_position, dtype=float).reshape(3)
    if not np.all(np.isfinite(target)):
        raise ValueError("tip_position must be finite")
    N, L = design.n_layers, design.layer_thickness
    psi0 = math.atan2(target[1], target[0]) if np.hypot(target[0], target[1]) > 1e-9 else 0.0

    def tip_of(z):
        hs = inverse_kinematics(design, z[0], abs(z[1]), z[2])
        return forward_kinematics(design, np.maximum(hs, 0)).tip_position, hs

    def res(z):
        p, hs = tip_of(z)
        pen = np.minimum(hs, 0).ravel()
        return np.concatenate([p - target, 10 * pen])

    c0 = max(target[2] / N - 2 * L, 0.0) if target[2] > 0 else 0.0
    best = None
    for th0 in (0.05, 0.3, 0.6):
        sol = least_squares(res, [c0 + 1e-3, th0, psi0], bounds=([0, 0, -2 * math.pi], [1.0, 1.4, 2 * math.pi]),
                            xtol=1e-12, ftol=1e-12)
        if best is None or sol.cost < best.cost:
            best = sol
    hs = inverse_kinematics(design, best.x[0], abs(best.x[1]), best.x[2])
    err = np.linalg.norm(tip_of(best.x)[0] - target)
    if err > 1e-6 or hs.min() < -1e-9 or (h_max is not None and hs.max() > h_max + 1e-9):
        raise ValueError(f"tip_position {np.round(target * 1e3, 2).tolist()} mm is not reachable by "
                         f"{N} identical layers (closest miss {err * 1e3:.2f} mm)")
    return np.maximum(hs, 0.0)


# ---------------------------------------------------------------------------------------------
# statics: load sharing
# ---------------------------------------------------------------------------------------------
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

    @property
    def tension(self) -> np.ndarray:
        return self.forces < 0


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
    gvec = np.array([0.0, 0.0, -design.g])
    masses = design.body_masses
    # centres of mass of bodies 1..N (mid-thickness on their axis)
    com = np.array([pose.frames[j][:3, :3] @ [0, 0, L / 2] + pose.frames[j][:3, 3] for j in range(1, N + 1)])
    tip = pose.tip_position
    forces = np.zeros((N, 3))
    shear = np.zeros((N, 2))
    twist = np.zeros(N)
    for k in range(N):
        Fk = pose.frames[k + 1]
        R, O = Fk[:3, :3], Fk[:3, 3]
        above = slice(k, N)  # bodies k+1..N are rows k..N-1 of com
        f = (masses[above, None] * gvec).sum(0) + f_tip
        M = _cross(com[above] - O, masses[above, None] * gvec).sum(0) + _cross(tip - O, f_tip) + m_tip
        fl, Ml = R.T @ f, R.T @ M
        pts = (R.T @ (pose.contacts[k] - O).T).T  # contact points in frame k+1 (z ~ 0)
        A = np.vstack([np.ones(3), pts[:, 1], pts[:, 0]])
        forces[k] = np.linalg.solve(A, np.array([-fl[2], -Ml[0], Ml[1]]))
        shear[k] = -fl[:2]
        twist[k] = -Ml[2]
    return LoadShare(forces, shear, twist, pose)


# ---------------------------------------------------------------------------------------------
# the chamber model (physics), batched
# ---------------------------------------------------------------------------------------------
@lru_cache(maxsize=8)
def _chamber_fn(space: ph.ParamSpace) -> ca.Function:
    """(h1, h2, theta) -> (p, F, lam, V, G) from hbma_ctrl.physics, for one material family."""
    h1, h2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    theta, P = space.symbols()
    g = ph.geometry(h1, h2, P)
    p = ph.pressure(h1, h2, P)
    return ca.Function("chamber", [h1, h2, theta], [p, ca.pi * g["a2"] * p, g["lam"], g["V"], ph.gas_pv(h1, h2, P)],
                       ["h1", "h2", "theta"], ["p", "F", "lam", "V", "G"])


@lru_cache(maxsize=16)
def _chambers(act: Actuator, pn: Pneumatics | None = None) -> "_Chambers":
    """A cached :class:`_Chambers` (its mapped casadi Functions are reused across calls)."""
    return _Chambers(act, pn)


@lru_cache(maxsize=8)
def _gf_fn(space: ph.ParamSpace) -> ca.Function:
    """(h1, h2, theta) -> (G, F, d(G, F)/d(h1, h2)) from the lead's model.shape_jacobian."""
    from .model import shape_jacobian

    h1, h2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    theta, P = space.symbols()
    G, F, J = shape_jacobian(h1, h2, P)
    return ca.Function("gf", [h1, h2, theta], [G, F, J], ["h1", "h2", "theta"], ["G", "F", "J"])


class _Chambers:
    """Numeric, vectorised access to the single-chamber physics for one actuator."""

    def __init__(self, act: Actuator, pn: Pneumatics | None = None):
        self.act = act
        self.space = ph.ParamSpace.for_material(act.material)
        self.theta = self.space.values(act, pn or Pneumatics(), Platform())
        self.fn = _chamber_fn(self.space)
        self._maps: dict = {}

    def eval(self, h1, h2) -> dict:
        h1 = np.atleast_1d(np.asarray(h1, dtype=float))
        h2 = np.broadcast_to(np.asarray(h2, dtype=float), h1.shape)
        n = h1.size
        if n not in self._maps:
            self._maps[n] = self.fn.map(n)
        th = np.repeat(self.theta[:, None], n, 1)
        out = self._maps[n](h1.ravel()[None, :], h2.ravel()[None, :], th)
        names = ("p", "F", "lam", "V", "G")
        return {k: np.asarray(v).reshape(h1.shape) for k, v in zip(names, out)}

    def newton_gf(self, h1, h2, G, F, iters: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """Newton on (h1, h2) for G(h1, h2) = G and F(h1, h2) = F from a nearby guess (vectorised).

        Keeps 0 <= h2 <= h1 and halves a step that would leave the chart; the guess picks the branch.
        """
        h1, h2 = np.array(h1, dtype=float), np.array(h2, dtype=float)
        n = h1.size
        key = ("gf", n)
        if key not in self._maps:
            self._maps[key] = _gf_fn(self.space).map(n)
        th = np.repeat(self.theta[:, None], n, 1)
        for _ in range(iters):
            Gv, Fv, J = (np.asarray(x) for x in self._maps[key](h1[None, :], h2[None, :], th))
            J = J.reshape(2, n, 2).transpose(0, 2, 1)  # mapped 2x2 blocks side by side -> [row, col, chamber]
            r0, r1 = Gv.ravel() - G, Fv.ravel() - F
            det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
            d1 = (J[1, 1] * r0 - J[0, 1] * r1) / det
            d2 = (-J[1, 0] * r0 + J[0, 0] * r1) / det
            step = np.ones(n)
            for _k in range(30):  # stay in the chart
                n1, n2 = h1 - step * d1, h2 - step * d2
                bad = (n2 < 0) | (n1 - n2 < 0)
                if not bad.any():
                    break
                step = np.where(bad, step / 2, step)
            h1, h2 = h1 - step * d1, np.maximum(h2 - step * d2, 0.0)
            if np.all(np.abs(d1) < 1e-13) and np.all(np.abs(d2) < 1e-13):
                break
        return h1, h2

    def h2_for_force(self, h, F) -> np.ndarray:
        """Cut height h2 with contact force F(h + h2, h2) = F at membrane height h (F > 0, h > 0)."""
        h = np.atleast_1d(np.asarray(h, dtype=float))
        F = np.broadcast_to(np.asarray(F, dtype=float), h.shape)
        lo, hi = np.zeros(h.shape), np.full(h.shape, self.act.r1)
        for _ in range(40):  # grow the bracket: F increases with h2 at fixed h
            small = self.eval(h + hi, hi)["F"] < F
            if not small.any():
                break
            hi = np.where(small, 2 * hi, hi)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            big = self.eval(h + mid, mid)["F"] > F
            hi, lo = np.where(big, mid, hi), np.where(big, lo, mid)
        return 0.5 * (lo + hi)

    def h_for_stretch(self, lam: float, F) -> np.ndarray:
        """Membrane height at stretch lam under contact force F (fixed point on h2)."""
        F = np.atleast_1d(np.asarray(F, dtype=float))
        r1 = self.act.r1
        h2 = np.zeros(F.shape)
        for _ in range(30):
            # lam^2 r1^2 = h1^2 + r1^2 - h2^2 with h1 = h + h2
            h = -h2 + np.sqrt(h2**2 + r1**2 * (lam**2 - 1))
            new = np.where(F > 0, self.h2_for_force(h, np.maximum(F, 1e-12)), 0.0)
            if np.max(np.abs(new - h2)) < 1e-12:
                h2 = new
                break
            h2 = new
        return -h2 + np.sqrt(h2**2 + r1**2 * (lam**2 - 1))

    def load_path(self, F: float, h_hi: float, n: int = 600) -> dict:
        """Chamber state along the constant-load path h in (0, h_hi] at contact force F >= 0."""
        h = np.linspace(h_hi / n, h_hi, n)
        h2 = self.h2_for_force(h, F) if F > 0 else np.zeros(n)
        out = self.eval(h + h2, h2)
        out.update(h=h, h1=h + h2, h2=h2)
        return out


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
    ch = _chambers(design.chamber)
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


def chamber_loads(design: RobotDesign, heights, tip_force=(0.0, 0.0, 0.0), tip_moment=(0.0, 0.0, 0.0),
                  floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-chamber load W (N), flattened A1, A2, ..., for use as each chamber model's dead load.

    Returns (W, tension): W = max(load share, floor) and the mask of chambers whose share is
    negative (the glue pulls; the single-chamber model cannot represent it, so it gets ``floor``).
    This is what a per-chamber estimator/controller bank feeds its models as ``P["W"]``.
    """
    F = load_sharing(design, heights, tip_force, tip_moment).forces.ravel()
    return np.maximum(F, floor), F < 0


def chamber_states_from_masses(design: RobotDesign, masses, tip_force=(0.0, 0.0, 0.0),
                               tip_moment=(0.0, 0.0, 0.0), iters: int = 40, tol: float = 1e-9) -> dict:
    """Static equilibrium of the robot for given gas masses (N x 3 or 3N, kg).

    For every chamber the constant-load path h -> (h1, h2) with F(h1, h2) = its load share is
    searched for G(h1, h2) = m R T (G = (p + p_env) V, SPEC 4); the loads follow from the heights
    by :func:`load_sharing`, iterated to a fixed point. A chamber whose gas cannot lift its share
    rests (h = 0). Along the load path G grows with h for the robot's chambers (no fold: the gas
    is compressible, which is why the far branch is stable at fixed mass), so the height is unique;
    where G is not monotone the lowest crossing is taken and ``ambiguous`` is flagged. Returns
    :func:`chamber_states` of the heights plus ``heights`` and ``ambiguous`` (N, 3).
    """
    N = design.n_layers
    m = np.asarray(masses, dtype=float)
    if m.size != 3 * N or not np.all(np.isfinite(m)) or m.min() <= 0:
        raise ValueError(f"masses: need {3 * N} finite gas masses > 0 kg")
    m = m.ravel()
    act = design.chamber
    ch = _chambers(act)
    rt = act.R * act.T
    lam_hi = min(1.5 * design.max_stretch, act.material.lam_max() * 0.999)
    h_hi = float(ch.h_for_stretch(lam_hi, 0.0)[0])
    n = 3 * N
    h1, h2 = np.zeros(n), np.zeros(n)
    active = np.zeros(n, dtype=bool)
    amb = np.zeros(n, dtype=bool)
    h = np.zeros(n)
    for _ in range(iters):
        F = np.maximum(load_sharing(design, h.reshape(N, 3), tip_force, tip_moment).forces.ravel(), 0.0)
        G_rest = (F / (math.pi * act.r1**2) + act.p_env) * act.V0
        act_now = m * rt > G_rest
        for i in np.nonzero(act_now & ~active)[0]:  # a coarse walk along the load path: the initial guess
            path = ch.load_path(F[i], h_hi, 120)
            G = path["G"] - m[i] * rt
            cross = np.nonzero((G[:-1] < 0) & (G[1:] >= 0))[0]
            if G[0] >= 0:
                cross = np.append([0], cross)
            if cross.size == 0:
                raise ValueError(f"masses: chamber {design.names[i]} holds more gas than the stretch "
                                 f"{lam_hi:g} allows")
            amb[i] = cross.size > 1 or bool(np.any(np.diff(path["G"]) <= 0))
            j = int(cross[0])
            h1[i], h2[i] = path["h1"][j + 1], path["h2"][j + 1]
        active = act_now
        if active.any():
            h1[active], h2[active] = ch.newton_gf(h1[active], h2[active], m[active] * rt, F[active])
        h1[~active], h2[~active] = 0.0, 0.0
        new = h1 - h2
        done = np.max(np.abs(new - h)) < tol
        h = new
        if done:
            break
    h = h.reshape(N, 3)
    amb = amb.reshape(N, 3)
    out = chamber_states(design, h, tip_force, tip_moment)
    out["heights"] = h
    out["ambiguous"] = amb
    return out


# ---------------------------------------------------------------------------------------------
# reach
# ---------------------------------------------------------------------------------------------
def pump_stall_pressure(pneumatics: Pneumatics | None = None) -> float:
    """Highest gauge pressure (Pa) at which the pump still delivers flow at full speed."""
    _, p, grid = ph.load_compressor_table((pneumatics or Pneumatics()).csv_path)
    q = grid[-1]
    pos = np.nonzero(q > 0)[0]
    if pos.size == 0:
        return 0.0
    i = pos[-1]
    if i + 1 >= p.size:
        return float(p[-1])
    return float(p[i] + (p[i + 1] - p[i]) * q[i] / (q[i] - q[i + 1]))


@dataclass(frozen=True)
class ChamberReach:
    """Reach of one chamber under a contact force (SI).

    h_max : largest height reachable holding the gas mass (far branch allowed), m
    limit : what sets h_max: 'max_stretch', 'pressure_limit' or 'pump_stall'
    h_peak, p_peak : height and pressure of the balloon limit point along the load path (m, Pa)
    h_pressure_control : reach if the chamber were pressure-controlled (near branch only), m
    h_stretch : height at the maximum stretch, m
    p_at_max : pressure at h_max, Pa; m_at_max : gas mass at h_max, kg
    """

    force: float
    h_max: float
    limit: str
    h_peak: float
    p_peak: float
    h_pressure_control: float
    h_stretch: float
    p_at_max: float
    m_at_max: float


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
    ch = _chambers(design.chamber, pneumatics)
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
    act = design.chamber
    m_at = float((ps[i_max] + act.p_env) * path["V"][i_max] / (act.R * act.T))
    return ChamberReach(F, float(h_max), limit, h_peak, p_peak, float(h_pc), h_str, float(ps[i_max]), m_at)


def reach_report(design: RobotDesign, heights, pressure_limit: float = 45e3,
                 pneumatics: Pneumatics | None = None, tip_force=(0.0, 0.0, 0.0)) -> dict:
    """Check chamber heights (N x 3, m) against each chamber's reach at its load share.

    Returns dict(ok, h_max (N, 3), limit (N, 3) names, violations: list of text, rim_gap (N,) m).
    Negative heights are violations too (a chamber cannot push down), and so is a pose whose
    layer rims would overlap (:meth:`RobotPose.rim_gap` < 0).
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
                viol.append(f"{names[3 * k + i]}: height {h[k, i] * 1e3:.2f} mm < 0")
            elif h[k, i] > r.h_max + 1e-9:
                viol.append(f"{names[3 * k + i]}: height {h[k, i] * 1e3:.2f} mm > reach "
                            f"{r.h_max * 1e3:.2f} mm (limited by {r.limit})")
    gap = forward_kinematics(design, np.maximum(h, 0)).rim_gap(design)
    for k in np.nonzero(gap < -1e-9)[0]:
        viol.append(f"layer {LETTERS[k]}: the layer rims overlap by {-gap[k] * 1e3:.2f} mm (rigid three-point "
                    "pose; the real layers rock on the rim)")
    return {"ok": not viol, "h_max": hmax, "limit": lim, "violations": viol, "rim_gap": gap}


def rim_pivot_pose(design: RobotDesign, h_inflated: float, inflated: list[int]) -> tuple[float, float, float]:
    """Layer pose when the inflated chambers stand at ``h_inflated`` (m) and the layer rocks on its rim.

    With some chambers flat, the rigid three-point pose makes the layer rims overlap
    (:meth:`RobotPose.rim_gap` < 0): a real layer pivots on the outer rim instead, and the flat
    chambers' glued membranes are pulled up (tension, outside the membrane model). The pose then is
    the plane that touches the lower rim (centre = R sin(bend)) and passes through the inflated
    chambers, bending away from them (direction opposite their mean angle). Returns (centre m,
    bend rad, direction rad); all three inflated -> level at h_inflated.
    """
    if not inflated:
        return 0.0, 0.0, 0.0
    if len(inflated) == 3:
        return float(h_inflated), 0.0, 0.0
    from scipy.optimize import brentq

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
    ch = _chambers(d.chamber)

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
                "gas_mass_mg": float(np.mean(st["m"][0, infl])) * 1e6 if n else float(st["m"][0, 0]) * 1e6,
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
        f"{r['stretch']:.2f} | {r['rim_gap_mm']:.2f} |\n" for r in rows)
    mat = ", ".join(f"{k} = {v:g} Pa" if isinstance(v, float) else f"{k} = {v}" for k, v in p["material_params"].items())
    foot = (f"\nParameters: {p['material'].upper()} ({mat}), r1 = {p['r1_mm']:g} mm, t0 = {p['t0_mm']:g} mm, "
            f"V0 = {p['V0_cm3']:g} cm^3, chamber centres {p['placement_radius_mm']:g} mm from the axis, layer "
            f"{p['layer_thickness_mm']:g} mm / {p['layer_mass_g']:g} g, {p['n_layers']} chamber layers "
            f"(layer A evaluated, B flat). far_branch: inflated chambers held by gas mass at stretch "
            f"{p['stretch']:g}; near_branch: held at {p['hold_pressure_kpa']:g} kPa below the limit point; "
            "rim_pivot: far-branch chambers, the layer rocking on its outer rim instead of the rigid "
            "three-point pose (whose rims would overlap with a flat chamber).\n")
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
    not overlap (:meth:`RobotPose.rim_gap` >= 0): what the three-point kinematics can really reach
    (larger bends make the layer rock on its rim). Tip: every layer bent alike (constant curvature).
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


# ---------------------------------------------------------------------------------------------
# scenario section and the open-loop scene
# ---------------------------------------------------------------------------------------------
SCENE_MODES = ("open_loop", "closed_loop")
CONTROLLERS = ("mpc", "pressure_pid")


@dataclass(frozen=True)
class RobotSettings:
    """The ``[robot]`` scenario table, validated (SI inside; the table uses edge units).

    design : the robot (:class:`RobotDesign`).
    pneumatics : supply topology, sensor range and pressure limit (:class:`RobotPneumatics`).
    mode : 'open_loop' (inputs by schedule) or 'closed_loop' (targets per layer; see below).
    inputs : per-chamber schedules {name: ((t s, speed 0-1, inlet 0-1, outlet 0-1), ...)}; chambers
        not listed keep everything closed. Safety interlocks of the open-loop scene close a chamber's
        inlet while its pressure is at the pressure limit or its stretch at ``design.max_stretch``.
    tip_force : force on the tip, world frame, N; tip_moment : moment on the tip, N m.
    sync_period : how often the load sharing and the interlocks update every chamber's load, s.
    snapshots : number of robot shapes drawn in the shape-over-time plot.

    Closed loop (mode 'closed_loop', see :mod:`controllers.robot_loop`):
    controller : 'mpc' (per-chamber EKF bank + structured NMPC) or 'pressure_pid' (baseline).
    targets : {layer index: ((t s, centre height m, bend rad >= 0, direction rad), ...)}.
    tip_load : ((t s, fx N, fy N, fz N), ...) tip force from each row's time on (a disturbance the
        controller does not know).
    compare_baseline : also run the other controller on the same targets and report it beside.
    settle_time : RMSEs count samples at least this long after a target change, s.
    mpc_horizon, mpc_dt : NMPC stages and prediction step (s).
    """

    design: RobotDesign = field(default_factory=RobotDesign)
    pneumatics: RobotPneumatics = field(default_factory=RobotPneumatics)
    mode: str = "open_loop"
    inputs: dict = field(default_factory=dict)
    tip_force: tuple = (0.0, 0.0, 0.0)
    tip_moment: tuple = (0.0, 0.0, 0.0)
    sync_period: float = 0.01
    snapshots: int = 8
    controller: str = "mpc"
    targets: dict = field(default_factory=dict)
    tip_load: tuple = ()
    compare_baseline: bool = True
    settle_time: float = 2.0
    mpc_horizon: int = 15
    mpc_dt: float = 0.02

    def validate(self) -> "RobotSettings":
        self.design.validate()
        self.pneumatics.validate()
        if self.mode not in SCENE_MODES:
            hint = did_you_mean(str(self.mode), SCENE_MODES)
            raise ValueError(f"robot.mode = '{self.mode}'{hint}; allowed: {', '.join(SCENE_MODES)}")
        names = self.design.names
        for name, rows in self.inputs.items():
            if name not in names:
                hint = did_you_mean(name, names)
                raise ValueError(f"robot.inputs.{name}: no such chamber{hint}; chambers: {', '.join(names)}")
            from .simulate import InputSchedule

            InputSchedule(tuple(tuple(r) for r in rows)).validate(f"robot.inputs.{name}")
        for nm in ("tip_force", "tip_moment"):
            v = getattr(self, nm)
            if len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise ValueError(f"robot.{nm} must be 3 finite numbers, got {v!r}")
        check_range("robot", "sync_period", self.sync_period, 1e-4, 1.0, "s")
        if not isinstance(self.snapshots, int) or not 1 <= self.snapshots <= 50:
            raise ValueError(f"robot.snapshots = {self.snapshots!r} must be an integer in [1, 50]")
        if self.controller not in CONTROLLERS:
            hint = did_you_mean(str(self.controller), CONTROLLERS)
            raise ValueError(f"robot.controller = '{self.controller}'{hint}; allowed: {', '.join(CONTROLLERS)}")
        if self.mode == "closed_loop" and not self.targets:
            raise ValueError("robot.mode = 'closed_loop': closed-loop robot control needs robot.targets "
                             "(a table {all = [[t_s, height_mm, bend_deg, direction_deg], ...]} or one per layer)")
        for j, row in enumerate(self.tip_load):
            if len(row) != 4 or not all(math.isfinite(float(v)) for v in row) or row[0] < 0:
                raise ValueError(f"robot.tip_load_n[{j}] must be [t_s >= 0, fx, fy, fz] (finite)")
        check_range("robot", "settle_time", self.settle_time, 0.0, 1e4, "s")
        if not isinstance(self.mpc_horizon, int) or not 1 <= self.mpc_horizon <= 100:
            raise ValueError(f"robot.mpc_horizon = {self.mpc_horizon!r} must be an integer in [1, 100]")
        check_range("robot", "mpc_dt", self.mpc_dt, 1e-3, 1.0, "s")
        return self


_SECTION_KEYS = {
    "mode": "open_loop | closed_loop", "layers": "number of chamber layers",
    "placement_radius_mm": "", "chamber_angles_deg": "3 angles", "layer_thickness_mm": "",
    "outer_diameter_mm": "", "inner_diameter_mm": "", "layer_mass_g": "", "end_mass_g": "",
    "r1_mm": "", "t0_mm": "", "V0_cm3": "", "material": "", "material_params": "table (SI)",
    "max_stretch": "", "topology": "", "outlets": "", "sensor_range_kpa": "", "pressure_limit_kpa": "",
    "tip_force_n": "[fx, fy, fz]", "tip_moment_nm": "[mx, my, mz]", "sync_ms": "", "snapshots": "",
    "inputs": "table {chamber: [[t_s, speed_pct, inlet_duty, outlet_duty], ...]}",
    "controller": "mpc | pressure_pid", "targets": "table {all|A|B|..: [[t_s, height_mm, bend_deg, direction_deg]]}",
    "tip_load_n": "[[t_s, fx, fy, fz], ...]", "compare_baseline": "bool", "settle_s": "", "mpc_horizon": "",
    "mpc_dt_ms": "",
}


#: allowed ranges of the numeric keys, in the table's own (edge) units
_EDGE_RANGES = {
    "placement_radius_mm": (1.0, 500.0), "layer_thickness_mm": (1.0, 100.0), "outer_diameter_mm": (1.0, 500.0),
    "inner_diameter_mm": (0.0, 500.0), "layer_mass_g": (0.0, 10000.0), "end_mass_g": (0.0, 10000.0),
    "r1_mm": (0.5, 100.0), "t0_mm": (0.05, 20.0), "V0_cm3": (0.001, 1000.0), "max_stretch": (1.05, 20.0),
    "sensor_range_kpa": (1.0, 1000.0), "pressure_limit_kpa": (1.0, 1000.0), "sync_ms": (0.1, 1000.0),
    "settle_s": (0.0, 1e4), "mpc_dt_ms": (1.0, 1000.0),
}


def _num(raw: dict, key: str) -> float:
    v = raw[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"robot.{key} = {v!r} must be a number")
    lo, hi = _EDGE_RANGES[key]
    check_range("robot", key, float(v), lo, hi)
    return float(v)


def parse_section(raw: dict) -> RobotSettings:
    """Validate a ``[robot]`` scenario table (edge units in the key names) -> :class:`RobotSettings`.

    Unknown keys get the closest valid name; out-of-range values name the key and its range (in
    the key's units). Keys: mode, layers, placement_radius_mm, chamber_angles_deg,
    layer_thickness_mm, outer_diameter_mm, inner_diameter_mm, layer_mass_g, end_mass_g, r1_mm,
    t0_mm, V0_cm3, material, material_params, max_stretch, topology, outlets, sensor_range_kpa,
    pressure_limit_kpa, tip_force_n, tip_moment_nm, sync_ms, snapshots, inputs (a table of
    per-chamber schedules, rows [t_s, speed_pct, inlet_duty, outlet_duty]); closed loop: controller,
    targets (a table {all|A|B|...: [[t_s, height_mm, bend_deg, direction_deg], ...]}, a negative
    bend is the opposite direction), tip_load_n ([[t_s, fx, fy, fz], ...]), compare_baseline,
    settle_s, mpc_horizon, mpc_dt_ms. Omitted keys take the
    paper's robot (:class:`RobotDesign`) and :class:`RobotPneumatics` defaults.
    """
    if not isinstance(raw, dict):
        raise ValueError("[robot] must be a table")
    for k in raw:
        if k not in _SECTION_KEYS:
            hint = did_you_mean(k, _SECTION_KEYS)
            raise ValueError(f"robot.{k}: unknown key{hint}; allowed: {', '.join(_SECTION_KEYS)}")
    base = RobotDesign()
    act = base.chamber
    if "material" in raw or "material_params" in raw:
        params = raw.get("material_params", {})
        if not isinstance(params, dict):
            raise ValueError("robot.material_params must be a table of SI values")
        mat: Material = make_material(str(raw.get("material", "nh")), **params)
        act = replace(act, material=mat)
    for key, fld, conv in (("r1_mm", "r1", U.mm), ("t0_mm", "t0", U.mm), ("V0_cm3", "V0", U.cm3)):
        if key in raw:
            act = replace(act, **{fld: conv(_num(raw, key))})
    kw: dict = {"chamber": act}
    if "layers" in raw:
        v = raw["layers"]
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 26:
            raise ValueError(f"robot.layers = {v!r} must be an integer in [1, 26]")
        kw["n_layers"] = v
    for key, fld, conv in (("placement_radius_mm", "placement_radius", U.mm),
                           ("layer_thickness_mm", "layer_thickness", U.mm),
                           ("outer_diameter_mm", "outer_diameter", U.mm),
                           ("inner_diameter_mm", "inner_diameter", U.mm),
                           ("layer_mass_g", "layer_mass", U.grams), ("end_mass_g", "end_mass", U.grams),
                           ("max_stretch", "max_stretch", float)):
        if key in raw:
            kw[fld] = conv(_num(raw, key))
    if "chamber_angles_deg" in raw:
        a = raw["chamber_angles_deg"]
        if not isinstance(a, list) or len(a) != 3 or not all(isinstance(x, (int, float)) for x in a):
            raise ValueError(f"robot.chamber_angles_deg must be a list of 3 numbers, got {a!r}")
        kw["chamber_angles"] = tuple(math.radians(x) for x in a)
    # cross-field checks in the table's units, before the SI validation of the design
    d0 = replace(base, **kw)
    lo, hi = round(U.to_mm(d0.inner_diameter / 2 + act.r1), 3), round(U.to_mm(d0.outer_diameter / 2 - act.r1), 3)
    check_range("robot", "placement_radius_mm", U.to_mm(d0.placement_radius), lo, hi,
                f"mm (the chamber disk, r1 = {U.to_mm(act.r1):g} mm, must fit the layer annulus)")
    try:
        design = d0.validate()
    except ValueError as exc:  # name the table's section
        raise ValueError(str(exc).replace("actuator.", "robot.")
                         .replace("robot.chamber_angles:", "robot.chamber_angles_deg:")) from None
    sensor = _num(raw, "sensor_range_kpa") if "sensor_range_kpa" in raw else 50.0
    limit = _num(raw, "pressure_limit_kpa") if "pressure_limit_kpa" in raw else min(45.0, sensor)
    check_range("robot", "pressure_limit_kpa", limit, 1.0, sensor, "kPa (at most sensor_range_kpa)")
    pn = RobotPneumatics(topology=str(raw.get("topology", "per_chamber")), outlets=str(raw.get("outlets", "per_chamber")),
                         sensor_range=U.kpa(sensor), pressure_limit=U.kpa(limit)).validate()
    inputs = {}
    tab = raw.get("inputs", {})
    if not isinstance(tab, dict):
        raise ValueError("robot.inputs must be a table {chamber: [[t_s, speed_pct, inlet, outlet], ...]}")
    for name, rows in tab.items():
        if not isinstance(rows, list) or not all(isinstance(r, list) and len(r) == 4 for r in rows):
            raise ValueError(f"robot.inputs.{name} must be a list of [t_s, speed_pct, inlet_duty, outlet_duty]")
        for i, r in enumerate(rows):
            check_range(f"robot.inputs.{name}[{i}]", "speed_pct", r[1], 0.0, 100.0, "%")
        inputs[name] = tuple((float(r[0]), U.pct(float(r[1])), float(r[2]), float(r[3])) for r in rows)
    vec = {}
    for key in ("tip_force_n", "tip_moment_nm"):
        v = raw.get(key, [0.0, 0.0, 0.0])
        if not isinstance(v, list) or len(v) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                             and math.isfinite(x) for x in v):
            raise ValueError(f"robot.{key} must be a list of 3 finite numbers, got {v!r}")
        vec[key] = tuple(float(x) for x in v)
    sync = U.mm(_num(raw, "sync_ms")) if "sync_ms" in raw else 0.01  # ms -> s, same factor as mm -> m
    closed: dict = {}
    if "controller" in raw:
        closed["controller"] = str(raw["controller"])
    if "targets" in raw:
        from controllers.robot_loop import parse_targets

        closed["targets"] = parse_targets(raw["targets"], design)
    if "tip_load_n" in raw:
        rows = raw["tip_load_n"]
        if not isinstance(rows, list) or not all(
                isinstance(r, list) and len(r) == 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                            for v in r) for r in rows):
            raise ValueError("robot.tip_load_n must be a list of [t_s, fx, fy, fz] (numbers, N)")
        for j, r in enumerate(rows):
            for v in r[1:]:
                check_range(f"robot.tip_load_n[{j}]", "force", v, -20.0, 20.0, "N")
        closed["tip_load"] = tuple(tuple(float(v) for v in r) for r in rows)
    if "compare_baseline" in raw:
        if not isinstance(raw["compare_baseline"], bool):
            raise ValueError(f"robot.compare_baseline = {raw['compare_baseline']!r} must be true or false")
        closed["compare_baseline"] = raw["compare_baseline"]
    if "settle_s" in raw:
        closed["settle_time"] = _num(raw, "settle_s")
    if "mpc_horizon" in raw:
        closed["mpc_horizon"] = raw["mpc_horizon"]
    if "mpc_dt_ms" in raw:
        closed["mpc_dt"] = _num(raw, "mpc_dt_ms") * 1e-3
    return RobotSettings(design=design, pneumatics=pn, mode=str(raw.get("mode", "open_loop")), inputs=inputs,
                         tip_force=vec["tip_force_n"], tip_moment=vec["tip_moment_nm"], sync_period=sync,
                         snapshots=raw.get("snapshots", 8), **closed).validate()


W_FLOOR = 1e-3  # N: the smallest load a chamber model is given (a chamber in tension is flagged)


@dataclass
class RobotRun:
    """Time series of an open-loop robot scene (SI). Arrays are indexed [time, layer, chamber]."""

    t: np.ndarray
    h: np.ndarray
    p: np.ndarray
    m: np.ndarray
    lam: np.ndarray
    F: np.ndarray
    bend: np.ndarray
    direction: np.ndarray
    tip: np.ndarray
    tip_bend: np.ndarray
    rim_gap: np.ndarray
    inputs: np.ndarray
    events: list
    step_s: np.ndarray
    status: str
    wall_s: float
    tension: np.ndarray


def simulate_open_loop(settings: RobotSettings, pneumatics: Pneumatics | None = None, duration: float = 30.0,
                       integrator: str = "rk4", dt: float | None = None) -> RobotRun:
    """Open-loop robot scene: every chamber's gas mass by the single-chamber model, loads shared.

    Each chamber is the lead's ``quasi_static`` fidelity (gas mass state, dead load W, resting /
    lift-off / far-branch jumps handled by :class:`hbma_ctrl.simulate.Plant`), all chambers in one
    batch. Every ``sync_period`` the robot's pose follows from the chamber heights
    (:func:`forward_kinematics`), the load sharing gives each chamber's new load W (floored at
    1 mN; chambers in tension are flagged), and the interlocks close an inlet while its chamber is
    at the pressure limit or the maximum stretch. With topology 'shared' one pump runs at the
    highest speed any open inlet asks for and its flow is split equally among the open inlets
    (each chamber's ``flow_scale`` divided by their number): a simple, documented scheme, not a
    manifold model. Loads lag the heights by at most one sync period (the layers are light, the
    motion slow).
    """
    from .model import make_fidelity
    from .simulate import InputSchedule, Plant

    s = settings.validate()
    pn = (pneumatics or Pneumatics()).validate()
    check_range("robot scene", "duration", duration, 1e-3, 1e5, "s", lo_open=True)
    if integrator not in ("euler", "rk4"):
        raise ValueError(f"sim.integrator = '{integrator}': the robot scene steps a batch plant, allowed euler, rk4")
    d = s.design
    N = d.n_layers
    n = 3 * N
    names = d.names
    fid = make_fidelity("quasi_static", d.chamber.material, str(pn.csv_path))
    ix = {k: i for i, k in enumerate(fid.space.names)}
    theta0 = fid.space.values(d.chamber, pn, Platform(load=1e-3))
    thetas = np.repeat(theta0[:, None], n, 1)
    F0 = load_sharing(d, np.zeros((N, 3)), s.tip_force, s.tip_moment).forces.ravel()
    thetas[ix["W"]] = np.maximum(F0, W_FLOOR)
    plant = Plant(fid, thetas, integrator, dt)
    th = plant.thetas  # the plant's own parameter matrix: loads and flow shares are updated in place
    scheds = [InputSchedule(s.inputs[nm]).validate(f"robot.inputs.{nm}") if nm in s.inputs else InputSchedule()
              for nm in names]
    k_sync = max(1, int(round(s.sync_period / plant.dt)))
    sync = k_sync * plant.dt
    nsync = int(math.ceil(duration / sync - 1e-9))
    pl, lam_max = s.pneumatics.pressure_limit, d.max_stretch
    rows_t, rows_h, rows_p, rows_m, rows_l, rows_F, rows_u, rows_pose = [], [], [], [], [], [], [], []
    events: list = []
    blocked = np.zeros(n, dtype=bool)
    saturated = np.zeros(n, dtype=bool)
    tension_any = np.zeros(n, dtype=bool)
    steps = []
    status = "ok"
    wall0 = time.perf_counter()

    def record(Uc, pose=None):
        h = np.maximum(plant.output("h"), 0.0)
        pose = pose or forward_kinematics(d, h.reshape(N, 3))
        rows_t.append(plant.t)
        rows_h.append(h)
        rows_p.append(plant.output("p").copy())
        rows_m.append(plant.output("m").copy())
        rows_l.append(plant.output("lam").copy())
        rows_F.append(th[ix["W"]].copy())
        rows_u.append(Uc.copy())
        rows_pose.append((pose.bend.copy(), pose.direction.copy(), pose.tip_position.copy(), pose.tip_bend,
                          pose.rim_gap(d)))
        return h

    h = record(np.zeros((3, n)))
    for _ in range(nsync):
        t = plant.t
        Uc = np.column_stack([sc.at(t + 1e-9) for sc in scheds])
        p, lam = plant.output("p"), plant.output("lam")
        block = (p >= pl) | (lam >= lam_max)
        for i in np.nonzero(block & ~blocked)[0]:
            why = "pressure_limit" if p[i] >= pl else "max_stretch"
            events.append((t, names[i], f"inlet_interlock:{why}"))
        blocked = block
        Uc[1] = np.where(block, 0.0, Uc[1])
        if s.pneumatics.topology == "shared":
            open_ = (Uc[1] > 0) & (Uc[0] > 0)
            speed = Uc[0][open_].max() if open_.any() else 0.0
            Uc[0] = np.where(open_, speed, 0.0)
            th[ix["flow_scale"]] = pn.flow_scale / max(int(open_.sum()), 1)
        t0 = time.perf_counter()
        plant.advance(Uc, sync)
        h = np.maximum(plant.output("h"), 0.0)
        ls = load_sharing(d, h.reshape(N, 3), s.tip_force, s.tip_moment)
        F = ls.forces.ravel()
        th[ix["W"]] = np.maximum(F, W_FLOOR)
        steps.append(time.perf_counter() - t0)
        for i in np.nonzero((F < 0) & ~tension_any)[0]:
            events.append((plant.t, names[i], "tension"))
        tension_any |= F < 0
        sat = plant.output("p") >= s.pneumatics.sensor_range
        for i in np.nonzero(sat & ~saturated)[0]:
            events.append((plant.t, names[i], "sensor_saturated"))
        saturated = sat
        record(Uc, ls.pose)
        if not plant.alive.all():
            status = "diverged"
            break
    for i, evs in enumerate(plant.events):
        events += [(float(tt), names[i], nm) for tt, nm in evs]
    events.sort(key=lambda e: e[0])
    T = len(rows_t)
    return RobotRun(
        t=np.array(rows_t), h=np.array(rows_h).reshape(T, N, 3), p=np.array(rows_p).reshape(T, N, 3),
        m=np.array(rows_m).reshape(T, N, 3), lam=np.array(rows_l).reshape(T, N, 3),
        F=np.array(rows_F).reshape(T, N, 3), bend=np.array([r[0] for r in rows_pose]),
        direction=np.array([r[1] for r in rows_pose]), tip=np.array([r[2] for r in rows_pose]),
        tip_bend=np.array([r[3] for r in rows_pose]), rim_gap=np.array([r[4] for r in rows_pose]),
        inputs=np.array(rows_u), events=events, step_s=np.array(steps), status=status,
        wall_s=time.perf_counter() - wall0, tension=tension_any.reshape(N, 3))


def run_metrics(design: RobotDesign, run: RobotRun) -> dict:
    """The "robot" metrics object of an open-loop run (edge units).

    ``min_rim_gap_mm`` < 0 marks layers whose rigid three-point pose overlapped the layer below at
    the rim (see :meth:`RobotPose.rim_gap`): there the real robot rocks on its rim.
    The tracking keys required of every robot scene (chamber_height_rmse_mm, bend_angle_rmse_deg,
    tip_position_rmse_mm) are null here: an open-loop scene has no reference to track.
    """
    names = design.names
    hmax = run.h.max(0).ravel()
    counts: dict = {}
    for _, _, nm in run.events:
        counts[nm] = counts.get(nm, 0) + 1
    tip0 = run.tip[0]
    return {
        "mode": "open_loop",
        "chamber_height_rmse_mm": None, "bend_angle_rmse_deg": None, "tip_position_rmse_mm": None,
        "step_ms_median": float(np.median(run.step_s) * 1e3) if run.step_s.size else None,
        "step_ms_p99": float(np.percentile(run.step_s, 99) * 1e3) if run.step_s.size else None,
        "max_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, hmax)},
        "min_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, run.h.min(0).ravel())},
        "final_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, run.h[-1].ravel())},
        "max_pressure_kpa": {nm: U.to_kpa(float(v)) for nm, v in zip(names, run.p.max(0).ravel())},
        "max_stretch": {nm: float(v) for nm, v in zip(names, run.lam.max(0).ravel())},
        "max_bend_deg": {LETTERS[k]: math.degrees(float(run.bend[:, k].max())) for k in range(design.n_layers)},
        "final_bend_deg": {LETTERS[k]: math.degrees(float(run.bend[-1, k])) for k in range(design.n_layers)},
        "tip_bend_max_deg": math.degrees(float(run.tip_bend.max())),
        "final_tip_mm": U.to_mm(run.tip[-1]).tolist(),
        "max_tip_lateral_mm": U.to_mm(float(np.max(np.hypot(run.tip[:, 0] - tip0[0], run.tip[:, 1] - tip0[1])))),
        "tip_height_range_mm": [U.to_mm(float(run.tip[:, 2].min())), U.to_mm(float(run.tip[:, 2].max()))],
        "tension_chambers": [nm for nm, f in zip(names, run.tension.ravel()) if f],
        "min_rim_gap_mm": {LETTERS[k]: U.to_mm(float(run.rim_gap[:, k].min())) for k in range(design.n_layers)},
        "events": counts,
        "status": run.status,
        "sim_time_s": float(run.t[-1]),
        "wall_s": run.wall_s,
    }


def write_run_csv(design: RobotDesign, run: RobotRun, path: Path | str) -> None:
    """Write the run as CSV in edge units (mm, kPa, mg, deg), one row per sync period."""
    import csv

    names = design.names
    N = design.n_layers
    cols = ["t_s"] + [f"h_{nm}_mm" for nm in names] + [f"p_{nm}_kpa" for nm in names] + \
        [f"m_{nm}_mg" for nm in names] + [f"load_{nm}_n" for nm in names] + \
        [f"bend_{LETTERS[k]}_deg" for k in range(N)] + [f"dir_{LETTERS[k]}_deg" for k in range(N)] + \
        ["tip_x_mm", "tip_y_mm", "tip_z_mm"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for j in range(run.t.size):
            row = [run.t[j]] + list(U.to_mm(run.h[j].ravel())) + list(U.to_kpa(run.p[j].ravel())) + \
                list(run.m[j].ravel() * 1e6) + list(run.F[j].ravel()) + list(np.degrees(run.bend[j])) + \
                list(np.degrees(run.direction[j])) + list(U.to_mm(run.tip[j]))
            w.writerow([f"{v:.6g}" for v in row])


def run_scene(scn, out_dir) -> dict:
    """Run a scenario with a ``[robot]`` section into out_dir; returns {"robot": metrics}.

    Uses the scenario's pneumatics (compressor map, flow scale), duration and sim integrator/step;
    the robot itself (chambers included) comes from ``[robot]``, not from ``[actuator]``. Writes
    robot_log.csv, robot_events.json, robot_shape.png (shapes over time) and robot_series.png.
    """
    s = None
    if hasattr(scn, "role"):
        s = scn.role("robot")
    if s is None:
        s = parse_section(dict(scn.sections["robot"]))
    if s.mode == "closed_loop":
        from controllers.robot_loop import run_closed_loop_scene

        return run_closed_loop_scene(scn, s, out_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    integ = scn.sim.integrator if scn.sim.integrator in ("euler", "rk4") else "rk4"
    dt = scn.sim.dt
    run = simulate_open_loop(s, scn.pneumatics, scn.duration, integ, dt)
    metrics = run_metrics(s.design, run)
    if integ != scn.sim.integrator:
        metrics["note"] = f"sim.integrator '{scn.sim.integrator}' is not available for the robot batch; used rk4"
    write_run_csv(s.design, run, out / "robot_log.csv")
    (out / "robot_events.json").write_text(json.dumps(
        [{"t_s": float(t), "chamber": c, "event": e} for t, c, e in run.events], indent=1) + "\n")
    idx = np.unique(np.linspace(0, run.t.size - 1, s.snapshots).round().astype(int))
    plot_shapes(s.design, [run.h[i] for i in idx], out / "robot_shape.png",
                labels=[f"t = {run.t[i]:.1f} s" for i in idx], title=f"{scn.name}: robot shape over time")
    plot_run(s.design, run, out / "robot_series.png")
    return {"robot": metrics}


# ---------------------------------------------------------------------------------------------
# plots (matplotlib, Agg)
# ---------------------------------------------------------------------------------------------
def _circle(frame: np.ndarray, z: float, r: float, n: int = 48) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, n)
    pts = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n, z), np.ones(n)])
    return (frame @ pts.T).T[:, :3]


def plot_shapes(design: RobotDesign, heights_list: list, path: Path | str, labels: list | None = None,
                title: str = "") -> None:
    """Draw robot shapes (3D view and x-z side view) for a list of chamber-height sets (m) -> PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11, 5.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    cmap = plt.get_cmap("viridis")
    L, R = design.layer_thickness, design.outer_diameter / 2
    xy = design.chamber_xy()
    extent = 0.0
    for j, hs in enumerate(heights_list):
        pose = forward_kinematics(design, hs)
        col = cmap(j / max(len(heights_list) - 1, 1))
        lab = labels[j] if labels else None
        for k, Fk in enumerate(pose.frames):
            for z in (0.0, L):
                c = U.to_mm(_circle(Fk, z, R))
                ax3.plot(c[:, 0], c[:, 1], c[:, 2], color=col, lw=0.8)
            # side view: the body's outline in its x-z section
            quad = np.array([[-R, 0, 0, 1], [R, 0, 0, 1], [R, 0, L, 1], [-R, 0, L, 1], [-R, 0, 0, 1]])
            q = U.to_mm((Fk @ quad.T).T)
            ax2.plot(q[:, 0], q[:, 2], color=col, lw=1.0, label=lab if k == 0 else None)
            extent = max(extent, float(np.abs(q[:, [0, 2]]).max()))
        for k in range(design.n_layers):
            base = (pose.frames[k] @ np.column_stack([xy, np.full(3, L), np.ones(3)]).T).T[:, :3]
            for i in range(3):
                seg = U.to_mm(np.vstack([base[i], pose.contacts[k, i]]))
                ax3.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="tab:red", lw=2.0)
                ax2.plot(seg[:, 0], seg[:, 2], color="tab:red", lw=1.5, alpha=0.7)
        tp = U.to_mm(pose.tip_position)
        ax3.scatter(*tp, color=col, s=12)
    lim = extent * 1.05
    ax3.set_xlim(-lim / 2, lim / 2)
    ax3.set_ylim(-lim / 2, lim / 2)
    ax3.set_zlim(0, lim)
    ax3.set_xlabel("x (mm)")
    ax3.set_ylabel("y (mm)")
    ax3.set_zlabel("z (mm)")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x (mm)")
    ax2.set_ylabel("z (mm)")
    ax2.set_title("side view (x-z section); red: chambers (membrane centre to contact)", fontsize=8)
    if labels:
        ax2.legend(fontsize=7, loc="upper left")
    fig.suptitle(title or "robot shape")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_run(design: RobotDesign, run: RobotRun, path: Path | str) -> None:
    """Chamber heights, pressures and layer bend angles over time -> PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = design.names
    fig, axs = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    T = run.t.size
    for i, nm in enumerate(names):
        axs[0].plot(run.t, U.to_mm(run.h.reshape(T, -1)[:, i]), label=nm)
        axs[1].plot(run.t, U.to_kpa(run.p.reshape(T, -1)[:, i]), label=nm)
    for k in range(design.n_layers):
        axs[2].plot(run.t, np.degrees(run.bend[:, k]), label=f"layer {LETTERS[k]} -> {LETTERS[k + 1] if k + 1 < design.n_layers else 'top'}")
    axs[0].set_ylabel("chamber height (mm)")
    axs[1].set_ylabel("pressure (kPa)")
    axs[2].set_ylabel("bend (deg)")
    axs[2].set_xlabel("t (s)")
    for ax in axs:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_workspace(ws: dict, path: Path | str, title: str = "") -> None:
    """Polar plot of the largest bend angle against bend direction, per layer -> PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    psi = np.asarray(ws["direction"] + ws["direction"][:1])
    fig = plt.figure(figsize=(6.5, 6.5))
    ax = fig.add_subplot(projection="polar")
    for ly in ws["layers"]:
        b = np.degrees(ly["bend_max"] + ly["bend_max"][:1])
        bp = np.degrees(ly["bend_max_pressure_control"] + ly["bend_max_pressure_control"][:1])
        ax.plot(psi, b, label=f"layer {ly['layer']}: gas-mass hold, h <= {U.to_mm(ly['h_max']):.1f} mm "
                              f"({ly['limit'][0]})")
        bc = np.degrees(ly["bend_max_no_rim_contact"] + ly["bend_max_no_rim_contact"][:1])
        ax.plot(psi, bc, ls=":", label=f"layer {ly['layer']}: gas-mass hold, rims clear")
        ax.plot(psi, bp, ls="--", label=f"layer {ly['layer']}: pressure control, h <= "
                                        f"{U.to_mm(ly['h_pressure_control']):.1f} mm")
    ax.set_title(title or f"largest bend (deg) vs direction, pressure limit {U.to_kpa(ws['pressure_limit']):g} kPa",
                 fontsize=9)
    ax.legend(fontsize=6, loc="lower center", bbox_to_anchor=(0.5, -0.25))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
