"""Forward and inverse kinematics of the robot (SI).

Bodies and frames
-----------------
Body 0 is the bottom layer (fixed to the ground), bodies 1..N sit on the chambers of the body
below; chamber layer k (letters A, B, C, ... from the bottom, numbers 1..3, as in Fig. 10) lives
in body k and pushes body k + 1. Body N is the top part (end plate, no chambers used). Frame k sits
at the centre of body k's bottom face, z along the layer's axis. Body k's membranes lie in its top
plane ``z = L`` (L = layer thickness, 9 mm with the flat 2 mm membrane). A chamber's *height* h is
the membrane height of docs/concepts/model.md §1 (``h = h1 - h2``): the gap the chamber opens between body k's top
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
model: a spherical segment pressed by a plane parallel to its retaining disk (docs/concepts/model.md §1); the tilt of
the plane over one membrane (a few mm wide) is neglected.

Rim contact (a limit of the three-point assumption)
---------------------------------------------------
The layers are rigid 44 mm disks. A three-point pose with a flat chamber (h = 0) always makes the
upper layer's rim dip below the lower layer's top face (``RobotPose.rim_gap`` = centre -
R sin(bend) < 0): with one chamber at 17 mm the overlap is about 7 mm. A real layer then rocks on
its rim and the glued, uninflated membranes are pulled up (tension).
:func:`~hbma_ctrl.robot.reach.reach_report` flags such poses, :func:`~hbma_ctrl.robot.reach.workspace`
reports the bend reachable with the rims clear, and :func:`~hbma_ctrl.robot.reach.robot_table2` gives a
``rim_pivot`` reading, which is the one closest to the paper's data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hbma_ctrl.robot.design import RobotDesign


def _rots(theta: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Twist-free rotations (n, 3, 3) mapping z onto (sin t cos psi, sin t sin psi, cos t), for bend
    angles and directions (n,) rad: Rodrigues' formula about u = (-sin psi, cos psi, 0)."""
    sp, cp = np.sin(psi), np.cos(psi)
    K = np.zeros((theta.size, 3, 3))
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = cp, sp, -cp, -sp
    return np.eye(3) + np.sin(theta)[:, None, None] * K + (1.0 - np.cos(theta))[:, None, None] * (K @ K)


def _plane_matrix(design: RobotDesign) -> np.ndarray:
    xy = design.chamber_xy()
    return np.column_stack([np.ones(3), xy])  # h_i = hc' + a x_i + b y_i


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (numpy's is slow for tiny arrays)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _planes(design: RobotDesign, h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre m, bend rad, direction rad), each (n,), of the planes through the contact points of
    layers with chamber heights h (n, 3) m; a level plane (to rounding) has direction 0."""
    cen, a, b = np.linalg.solve(_plane_matrix(design), h.T)
    t = np.hypot(a, b)
    level = t < 1e-12
    return cen, np.where(level, 0.0, np.arctan(t)), np.where(level, 0.0, np.arctan2(-b, -a))


def layer_plane(design: RobotDesign, heights) -> tuple[float, float, float]:
    """(centre height m, bend angle rad in [0, pi/2), bend direction rad in (-pi, pi]) of the plane
    through a layer's three contact points, for its chamber heights (3,) in m.

    The centre height is the plane's height on the layer axis (= mean height for chambers at 120
    degrees). Zero bend has direction 0 by convention.
    """
    c, t, psi = _planes(design, np.asarray(heights, dtype=float).reshape(1, 3))
    return float(c[0]), float(t[0]), float(psi[0])


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
        i.e. the real robot rocks on its rim there (see :func:`~hbma_ctrl.robot.reach.rim_pivot_pose`).
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
    xy = design.chamber_xy()
    L = design.layer_thickness
    # every layer's plane at once (the daemon's load sharing calls this each period)
    cen, bend, dirn = _planes(design, h)
    T = np.zeros((N, 4, 4))
    T[:, :3, :3], T[:, 2, 3], T[:, 3, 3] = _rots(bend, dirn), L + cen, 1.0
    frames = np.zeros((N + 1, 4, 4))
    frames[0] = np.eye(4)
    for k in range(N):
        frames[k + 1] = frames[k] @ T[k]
    # contact points: (x, y, L + h) of each layer's chambers in its lower body's frame k
    local = np.concatenate([np.broadcast_to(xy, (N, 3, 2)), (L + h)[:, :, None]], axis=2)
    contacts = np.einsum("kij,kmj->kmi", frames[:N, :3, :3], local) + frames[:N, None, :3, 3]
    tip = frames[N].copy()
    tip[:3, 3] = frames[N][:3, 2] * L + frames[N][:3, 3]
    return RobotPose(frames, tip, h, cen, bend, dirn, contacts)


def inverse_kinematics(design: RobotDesign, centre, bend, direction) -> np.ndarray:
    """Per-layer targets -> chamber heights (N, 3), m.

    centre : centre height(s) of each layer's upper plane above its membranes, m (scalar = all
    layers); bend : bend angle(s) relative to the layer below, rad, in [0, pi/2); direction : bend
    direction(s), rad. Exact inverse of :func:`layer_plane`. Heights may come out negative or beyond
    a chamber's reach: check them with :func:`~hbma_ctrl.robot.reach.reach_report` (no clamping here).
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
