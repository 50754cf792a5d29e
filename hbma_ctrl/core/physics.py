"""The HBMA physics, written once in casadi (docs/concepts/model.md §1-§5). Everything else calls these expressions.

All quantities are SI. Symbolic helpers take casadi (or float) arguments and a ``P`` mapping of
parameter expressions (see :class:`ParamSpace`), so the same expressions serve numeric evaluation,
batched simulation (parameters as inputs, ``map`` over trials), Jacobians for the EKF and the
discretised dynamics of the NMPC.

The pressure is evaluated in the regular closed form of docs/concepts/model.md §3,

    p = 2 t0 h1^2 Q(lam) (h1 + h2) / (lam r1^2 (lam + 1) (h1^2 + r1^2)),   Q = W'(lam)/(lam - 1),

which is finite and smooth at the flat limit ``h2 -> h1`` and at ``h1 -> 0``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

from hbma_ctrl.core.materials import Material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics

__all__ = [
    "ParamSpace",
    "geometry",
    "pressure",
    "gas_pv",
    "orifice_flow",
    "load_compressor_table",
    "pump_reach",
    "compressor_interpolant",
    "flat_h1_from_pressure",
    "RHO0_ISO",
    "T0_ISO",
]

RHO0_ISO = 1.185  # ISO 6358 reference density, kg/m^3
T0_ISO = 293.15  # ISO 6358 reference temperature, K
_EPS_H = 1e-12  # m; only guards 0/0 in h2/h1 at the exact origin


# ---------------------------------------------------------------------------------------------
# parameters as a vector, so batches of trials (different r1, t0, loads) share one Function
# ---------------------------------------------------------------------------------------------
BASE_NAMES = ("r1", "t0", "V0", "R", "T", "p_env", "W", "M", "c", "flow_scale",
              "C_out", "b_out", "lam_out")


def _material_field_sizes(mat: Material) -> list[tuple[str, int]]:
    out = []
    for f in fields(mat):
        v = getattr(mat, f.name)
        out.append((f.name, len(v) if isinstance(v, tuple) else 0))
    return out


@dataclass(frozen=True)
class ParamSpace:
    """Layout of the parameter vector theta for one material family.

    theta = [r1, t0, V0, R, T, p_env, W (platform weight, N), M (moving mass, kg), c (damping,
    N s/m), flow_scale, C_out, b_out, lam_out, <material parameters>].
    """

    material_cls: type
    material_sizes: tuple  # ((field, size or 0 for scalar), ...)

    @staticmethod
    def for_material(mat: Material) -> "ParamSpace":
        return ParamSpace(type(mat), tuple(_material_field_sizes(mat)))

    @property
    def names(self) -> list[str]:
        out = list(BASE_NAMES)
        for name, n in self.material_sizes:
            out += [name] if n == 0 else [f"{name}{i}" for i in range(n)]
        return out

    @property
    def size(self) -> int:
        return len(self.names)

    def values(self, act: Actuator, pn: Pneumatics | None = None, plat: Platform | None = None) -> np.ndarray:
        """Numeric theta for an actuator, pneumatics and platform."""
        pn = pn or Pneumatics()
        plat = plat or Platform()
        if type(act.material) is not self.material_cls:
            raise ValueError("material family differs from this ParamSpace")
        base = [act.r1, act.t0, act.V0, act.R, act.T, act.p_env, plat.weight, max(plat.mass, 1e-6),
                plat.damping, pn.flow_scale, pn.outlet.C, pn.outlet.b, pn.outlet.laminar_ratio]
        mat = []
        for name, n in self.material_sizes:
            v = getattr(act.material, name)
            mat += list(v) if n else [v]
        return np.array(base + mat, dtype=float)

    def symbols(self) -> tuple[ca.SX, dict]:
        """theta as an SX vector and a dict of named entries; 'material' holds a symbolic Material."""
        theta = ca.SX.sym("theta", self.size)
        P = {n: theta[i] for i, n in enumerate(BASE_NAMES)}
        k = len(BASE_NAMES)
        kw = {}
        for name, n in self.material_sizes:
            if n == 0:
                kw[name] = theta[k]
                k += 1
            else:
                kw[name] = tuple(theta[k + i] for i in range(n))
                k += n
        P["material"] = self.material_cls(**kw)
        return theta, P


# ---------------------------------------------------------------------------------------------
# Model §1-§3: geometry, stretch, volume, pressure, force
# ---------------------------------------------------------------------------------------------
def geometry(h1, h2, P) -> dict:
    """Spherical-segment geometry (docs/concepts/model.md §1) for virtual cap height h1 and cut height h2 (m).

    Returns dict with h (m), a2 (contact radius squared, m^2), lam (-), V (gas volume, m^3).
    """
    r1, V0 = P["r1"], P["V0"]
    h = h1 - h2
    # a^2 = h2 ((h1^2 + r1^2)/h1 - h2), written with the ratio h2/h1 in [0, 1]
    ratio = h2 / ca.fmax(h1, _EPS_H)
    a2 = ratio * (h1**2 + r1**2 - h1 * h2)
    lam2 = (h1**2 + r1**2 - h2**2) / r1**2
    lam = ca.sqrt(lam2)
    V = V0 + (ca.pi / 6) * h * (3 * r1**2 + 3 * a2 + h**2)
    return {"h": h, "a2": a2, "lam": lam, "V": V}


def pressure(h1, h2, P):
    """Equilibrium gauge pressure p = f(h1, h2) in Pa, regular closed form (docs/concepts/model.md §3)."""
    r1, t0 = P["r1"], P["t0"]
    lam = ca.sqrt((h1**2 + r1**2 - h2**2) / r1**2)
    Q = P["material"].Q(lam)
    return 2 * t0 * h1**2 * Q * (h1 + h2) / (lam * r1**2 * (lam + 1) * (h1**2 + r1**2))


def gas_pv(h1, h2, P):
    """G = (p + p_env) V = m R T in J: the gas 'energy' that the gas mass fixes."""
    return (pressure(h1, h2, P) + P["p_env"]) * geometry(h1, h2, P)["V"]


def flat_h1_from_pressure(p, P):
    """Virtual cap height h1 (m) of a flat membrane (h2 = h1) carrying gauge pressure p (Pa).

    The flat limit of docs/concepts/model.md §3 is p = 2 t0 Q(1) h1^3 / (r1^2 (h1^2 + r1^2)) for every material (NH:
    Q(1) = 4E gives the Model's 8 E t0 h1^3 / ...). With k = p r1^2 / (2 t0 Q(1)) this is the cubic
    h1^3 - k h1^2 - k r1^2 = 0, which has one positive root for k > 0 (Cardano). p <= 0 gives 0.
    """
    r1, t0 = P["r1"], P["t0"]
    q1 = P["material"].Q(1.0)
    k_raw = p * r1**2 / (2 * t0 * q1)
    # k is floored above zero so that no square or cube root is taken of zero: their infinite
    # slopes times a zero seed are NaN in a Jacobian (casadi colours columns together, so one NaN
    # spoils its neighbours); below the floor (h1 < 1e-4 r1) the height is reported as 0
    k_min = 1e-12 * r1
    k = ca.fmax(k_raw, k_min)
    # depressed cubic y^3 + py y + qy = 0 with h1 = y + k/3
    py = -(k**2) / 3
    qy = -2 * k**3 / 27 - k * r1**2
    disc = (qy / 2) ** 2 + (py / 3) ** 3  # > 0 for k > 0: one real root
    sq = ca.sqrt(disc)
    # Cardano's two cube roots u v = -py / 3: the second from the first (the direct cube root of
    # -qy/2 - sq cancels to zero for small k)
    u = (-qy / 2 + sq) ** (1.0 / 3.0)
    h = u - py / (3 * u) + k / 3
    # Cardano cancels digits for small k (two nearly opposite cube roots): polish with Newton on the
    # cubic, whose slope h (3h - 2k) is positive at the root (h > k)
    for _ in range(2):
        slope = h * (3 * h - 2 * k)
        h = ca.if_else(slope > 0, h - (h**3 - k * h**2 - k * r1**2) / ca.fmax(slope, 1e-300), h)
    return ca.if_else(k_raw > k_min, h, 0.0)


# ---------------------------------------------------------------------------------------------
# docs/concepts/model.md §5: pneumatics
# ---------------------------------------------------------------------------------------------
def orifice_flow(p_up_abs, p_down_abs, C, b, lam_ratio, T):
    """ISO 6358 mass flow (kg/s) from p_up to p_down (absolute, Pa); negative if reversed.

    Choked for pressure ratio <= b, elliptic subsonic law above, blended to a linear (laminar) law
    for ratio > lam_ratio so the flow is Lipschitz at zero pressure drop.
    """
    hi = ca.fmax(p_up_abs, p_down_abs)
    lo = ca.fmin(p_up_abs, p_down_abs)
    sgn = ca.sign(p_up_abs - p_down_abs)
    r = lo / hi

    def phi_sub(x):
        return ca.sqrt(ca.fmax(1 - ((x - b) / (1 - b)) ** 2, 0))

    phi = ca.if_else(r <= b, 1.0,
                     ca.if_else(r <= lam_ratio, phi_sub(r), phi_sub(lam_ratio) * (1 - r) / (1 - lam_ratio)))
    return sgn * C * RHO0_ISO * hi * ca.sqrt(T0_ISO / T) * phi


def load_compressor_table(path: Path | str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a compressor map CSV (speed 0-1, gauge pressure Pa, mass flow kg/s) as a full grid.

    Returns (speeds, pressures, flow[speed, pressure]). Raises ValueError naming the problem when
    the table is not a complete rectangular grid or has negative/non-finite values.
    """
    path = Path(path)
    rows = []
    with path.open() as fh:
        lines = [ln for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.DictReader(lines)
    need = {"speed", "pressure_pa", "mass_flow_kgs"}
    if not reader.fieldnames or not need <= set(reader.fieldnames):
        raise ValueError(f"compressor table {path}: columns must be {sorted(need)}, got {reader.fieldnames}")
    for i, row in enumerate(reader):
        try:
            rows.append((float(row["speed"]), float(row["pressure_pa"]), float(row["mass_flow_kgs"])))
        except ValueError as exc:
            raise ValueError(f"compressor table {path}: row {i + 1} is not numeric ({exc})") from None
    arr = np.array(rows)
    if not np.all(np.isfinite(arr)) or np.any(arr[:, 2] < 0):
        raise ValueError(f"compressor table {path}: values must be finite and mass_flow_kgs >= 0")
    s = np.unique(arr[:, 0])
    p = np.unique(arr[:, 1])
    if s.min() > 0 or s.max() < 1:
        raise ValueError(f"compressor table {path}: speed must span [0, 1], got [{s.min()}, {s.max()}]")
    if len(arr) != len(s) * len(p):
        raise ValueError(f"compressor table {path}: need a full grid of speed x pressure ({len(s)} x {len(p)})")
    grid = np.full((len(s), len(p)), np.nan)
    for si, pi, q in arr:
        grid[np.searchsorted(s, si), np.searchsorted(p, pi)] = q
    if np.isnan(grid).any():
        raise ValueError(f"compressor table {path}: grid has duplicate or missing points")
    return s, p, grid


def pump_reach(path: Path | str) -> tuple[float, bool]:
    """The highest gauge pressure (Pa) a compressor map says its pump reaches at full speed, and whether
    that is its stall (flow falls to 0 there; False: the map still delivers flow at its last pressure,
    which is then the end of what it knows, read past as constant)."""
    _, p, grid = load_compressor_table(path)
    q = grid[-1]
    pos = np.nonzero(q > 0)[0]
    if pos.size == 0:
        return 0.0, True
    i = pos[-1]
    if i + 1 >= p.size:
        return float(p[-1]), False
    return float(p[i] + (p[i + 1] - p[i]) * q[i] / (q[i] - q[i + 1])), True


@lru_cache(maxsize=8)
def compressor_interpolant(path: str) -> ca.Function:
    """casadi linear interpolant q(speed, p) in kg/s from a compressor map CSV."""
    s, p, grid = load_compressor_table(path)
    # casadi wants the values in Fortran order (first grid dimension fastest)
    return ca.interpolant("compressor", "linear", [s, p], grid.ravel(order="F"))


def compressor_flow(speed, p, P, table: ca.Function):
    """Pump mass flow, kg/s: the map scaled by flow_scale, never negative (the pump's check valves)."""
    q = table(ca.vertcat(speed, p))
    return P["flow_scale"] * ca.fmax(q, 0)


def net_flow(u, p, P, table: ca.Function):
    """Net mass flow into the chamber, kg/s, for inputs u = [speed, inlet duty, outlet duty] (0-1).

    Duties are the relaxed (PWM-averaged) valve commands: the averaged flow through a valve held open
    a fraction d of each PWM period is d times its open flow.
    """
    q_in = u[1] * compressor_flow(u[0], p, P, table)
    q_out = u[2] * orifice_flow(p + P["p_env"], P["p_env"], P["C_out"], P["b_out"], P["lam_out"], P["T"])
    return q_in - q_out, q_in, q_out
