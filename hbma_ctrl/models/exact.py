"""The exact axisymmetric equilibrium of a clamped, thin, incompressible hyperelastic membrane (SI).

No shape assumption (docs/concepts/model.md §9; Adkins and Rivlin 1952, Yang and Feng 1970). A
material point at reference radius R in [0, r1] of the flat membrane (thickness t0) moves to
(rho(R), z(R)). With ' = d/dR and phi the meridian's slope below the horizontal
(``rho' = l1 cos phi``, ``z' = -l1 sin phi``; phi > 0 on a dome seen from its pole):

- stretches: meridional ``l1 = sqrt(rho'^2 + z'^2)``, circumferential ``l2 = rho / R``,
  thickness ``l3 = 1 / (l1 l2)``;
- tensions per deformed length: ``T1 = (t0 / l2) W_1``, ``T2 = (t0 / l1) W_2`` with
  ``W(l1, l2)`` the strain energy per reference volume and ``W_i = dW/dl_i``;
- meridian equilibrium ``d(rho T1)/dR = l1 T2 cos phi``; since ``rho T1 = t0 R W_1`` and
  ``l2' = (l1 cos phi - l2) / R`` it reads

      l1' = (W_2 cos phi - W_1 - W_12 (l1 cos phi - l2)) / (R W_11);

- normal equilibrium ``T1 k1 + T2 k2 = p`` with ``k1 = phi' / l1``, ``k2 = sin phi / rho``:

      phi' = (p l1 l2 / t0 - W_2 sin phi / R) / W_1.

(On a sphere of radius a, l1 = l2 = lam and T1 = T2 = T: p = 2 T / a.) The state
``(l1, rho, phi, z, V, U)`` is integrated in the dimensionless radius x = R / r1 with the
pressure P = p r1 / (mu t0) and w = W / mu (mu = W''(1) / 12, the small-strain shear modulus);
``V' = pi rho^2 l1 sin phi`` accumulates the gas volume above the clamp plane and
``U' = 2 pi w R`` the stored energy (``U t0 mu r1^2`` in J).

Boundary conditions and the three problems:

- clamp: ``rho(r1) = r1``, ``z(r1) = 0`` (height measured from the clamp plane);
- free inflation: pole ``rho = 0, phi = 0, l1 = l2 = lam0``; near the pole the shape is a sphere of
  curvature ``p lam0 / (2 t0 W_1)`` (the series start). For a pole stretch lam0, the pressure that
  brings rho back to r1 at the clamp is found by bisection (a larger pressure curls the meridian
  more, so ``rho(r1)`` falls with p), which follows the pressure through its limit point;
- frictionless flat plate at height h: the part on the plate (R < Rc) is flat and, with no shear from
  the plate, uniformly equi-biaxial (``l1 = l2 = lam0`` is the regular solution of the in-plane
  equations); the free part leaves the plate tangentially (``phi(Rc) = 0``); ``F = p pi rho_c^2``
  with ``rho_c = lam0 Rc`` the contact radius. Unknowns (lam0, Rc) for given (h, p);
- rigid disk of radius c bonded at the centre: the material inside c moves with the disk unstretched
  (``rho(c) = c``, ``l2(c) = 1``), the meridian leaves the disk's edge at height h with unknown
  stretch l1c and slope phi_c; the disk's force balance is ``F = p pi c^2 - 2 pi c T1 sin phi_c``:
  a membrane that rises from the edge (phi_c < 0, bulging around the disk) helps lift it, one that
  falls from it pulls it down, so F < 0 is possible (a deflated glued chamber holds its layer).

Integration: classical RK4 on a fixed mesh, graded geometrically near the start (where the 1/R terms
are stiff) and uniform after; the whole march is one casadi Function (``mapaccum``), mapped over a
batch of starts, so one root search solves many points at once. The mesh study in the tests bounds
the discretisation error. Free inflation is parametrised by the pole stretch lam0, which (unlike the
pressure) grows monotonically with the apex height through the limit point.

Tables of these solutions for the simulator (free inflation, contact grids, and the flat contact in the
cap's chart) are in :mod:`hbma_ctrl.models.exact_tables`.
"""

from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np
from scipy.optimize import brentq

from hbma_ctrl.core.codegen import compiled
from hbma_ctrl.core.materials import Gent, Material, MooneyRivlin, NeoHookean, Ogden, Yeoh

__all__ = ["ExactMembrane", "biaxial_energy", "equilibrium", "CONTACTS"]

#: contact types at the membrane's centre: a loose flat plate or a disk glued at the centre
CONTACTS = ("flat", "bonded")
_X0 = 1e-7  # dimensionless start radius of a free pole (series error ~ x0^2)
_N_UNIFORM = 160  # uniform steps (mesh study: the error falls 4x per doubling; p within 5e-7, V 2e-7)
_STATE = 6
_L1_MIN = 0.2  # a meridional stretch below this means the march folded: treated as over-curled
#: dimensionless pressures P = p r1 / (mu t0) scanned to bracket the clamp's crossing
_INNER_SCAN = 24  # stretches scanned to bracket the clamp's crossing at a contact edge
_P_SCAN = np.concatenate([[0.0], np.geomspace(1e-3, 200.0, 47)])


def biaxial_energy(material: Material, l1, l2):
    """Strain energy W(l1, l2) in J/m^3 of an incompressible material at principal in-plane stretches
    (l1, l2) (-), l3 = 1/(l1 l2) (casadi or float). Equals ``material.W(lam)`` when l1 = l2 = lam."""
    i1 = l1**2 + l2**2 + (l1 * l2) ** -2
    i2 = l1**-2 + l2**-2 + (l1 * l2) ** 2
    if isinstance(material, NeoHookean):
        return material.E / 6 * (i1 - 3)
    if isinstance(material, MooneyRivlin):
        return material.C1 * (i1 - 3) + material.C2 * (i2 - 3)
    if isinstance(material, Yeoh):
        return sum(c * (i1 - 3) ** (i + 1) for i, c in enumerate(material.C))
    if isinstance(material, Gent):
        return -(material.mu * material.Jm / 2) * ca.log(1 - (i1 - 3) / material.Jm)
    if isinstance(material, Ogden):
        l3 = 1 / (l1 * l2)
        return sum((m / a) * (l1**a + l2**a + l3**a - 3) for m, a in zip(material.mu, material.alpha))
    raise ValueError(f"material: no biaxial strain energy for {type(material).__name__}")


def _shear_modulus(material: Material) -> float:
    # equi-biaxial W''(1) = 12 mu for every incompressible isotropic material
    return material.modulus_q1 / 12.0


def _u_nodes(n_uniform: int) -> np.ndarray:
    """Nodes in [0, 1]: geometric (ratio 1.5) from ~x0 up to 1/n, then uniform: keeps du/u <= 0.5."""
    du = 1.0 / n_uniform
    geo = [0.0]
    u = _X0
    while u < du:
        geo.append(u)
        u *= 1.5
    return np.concatenate([np.array(geo), np.linspace(du, 1.0, n_uniform)])


@lru_cache(maxsize=32)
def _derivs(material: Material) -> ca.Function:
    """(l1, l2) -> (w, w1, w2, w11, w12) with w = W / mu."""
    l1, l2 = ca.SX.sym("l1"), ca.SX.sym("l2")
    w = biaxial_energy(material, l1, l2) / _shear_modulus(material)
    w1, w2 = ca.gradient(w, l1), ca.gradient(w, l2)
    return ca.Function("w", [l1, l2], [w, w1, w2, ca.gradient(w1, l1), ca.gradient(w1, l2)])


@lru_cache(maxsize=32)
def _march(material: Material, n_uniform: int) -> tuple[ca.Function, np.ndarray]:
    """RK4 march of the membrane equations over the mesh: (s0, x0, P) -> states at every node."""
    d = _derivs(material)
    s = ca.SX.sym("s", _STATE)
    x, P = ca.SX.sym("x"), ca.SX.sym("P")
    l1, rho, phi = s[0], s[1], s[2]
    l2 = rho / x
    w, w1, w2, w11, w12 = d(l1, l2)
    c, sn = ca.cos(phi), ca.sin(phi)
    rhs = ca.vertcat(
        (w2 * c - w1 - w12 * (l1 * c - l2)) / (x * w11),
        l1 * c,
        (P * l1 * l2 - w2 * sn / x) / w1,
        -l1 * sn,
        ca.pi * rho**2 * l1 * sn,
        2 * ca.pi * w * x,
    )
    f = ca.Function("f", [s, x, P], [rhs])
    h = ca.SX.sym("h")
    k1 = f(s, x, P)
    k2 = f(s + h / 2 * k1, x + h / 2, P)
    k3 = f(s + h / 2 * k2, x + h / 2, P)
    k4 = f(s + h * k3, x + h, P)
    step = ca.Function("step", [s, x, h, P], [s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    u = _u_nodes(n_uniform)
    n = len(u) - 1
    acc = step.mapaccum("march", n)
    # inputs: s0 (6), start x0 (1), P (1): nodes x_j = x0 + (1 - x0) u_j
    s0, xs, Ps = ca.MX.sym("s0", _STATE), ca.MX.sym("x0"), ca.MX.sym("P")
    xk = xs + (1 - xs) * ca.DM(u[:-1]).T
    hk = (1 - xs) * ca.DM(np.diff(u)).T
    out = acc(s0, xk, hk, ca.repmat(Ps, 1, n))
    traj = ca.Function("shoot", [s0, xs, Ps], [out])
    # what a root search needs, without copying the whole march back: the end state, the smallest radius
    # and meridional stretch met on the way, and a sum that is NaN where the march broke down
    # and the smallest meridional and hoop tensions (w1, w2): a negative one is a slack (wrinkled) membrane
    _, w1n, w2n, _, _ = d.map(n)(out[0, :], out[1, :] / (xk + hk))
    summary = ca.vertcat(out[:, -1], ca.mmin(out[1, :]), ca.mmin(out[0, :]), ca.sum2(ca.sum1(out[:4, :])),
                         ca.mmin(w1n), ca.mmin(w2n), ca.mmax(ca.fabs(out[2, :])))
    return ca.Function("shoot_end", [s0, xs, Ps], [summary]), traj, u


@lru_cache(maxsize=256)
def _mapped(material: Material, n_uniform: int, batch: int) -> ca.Function:
    # compiled to C once per machine (cached on disk by source): ~20x the virtual machine's speed
    return _compiled_march(material, n_uniform).map(batch)


@lru_cache(maxsize=32)
def _compiled_march(material: Material, n_uniform: int) -> ca.Function:
    return compiled(_march(material, n_uniform)[0])


class ExactMembrane:
    """Exact axisymmetric equilibria of one clamped membrane: free, on a flat plate, or bonded to a disk.

    material : a :class:`hbma_ctrl.core.materials.Material`; r1 : clamp radius, m; t0 : thickness, m;
    contact : 'flat' (loose frictionless plate) or 'bonded' (rigid disk glued at the centre);
    c : the bonded disk's radius, m, in (0, r1) (ignored for 'flat'); n_steps : uniform RK4 steps
    over the radius (accuracy; the default keeps pressures within 5e-7 relative, volumes 2e-7).
    All inputs and outputs SI (m, Pa, N, m^3, J); volumes are above the clamp plane (no dead volume).
    """

    def __init__(self, material: Material, r1: float, t0: float, contact: str = "flat", c: float = 0.0,
                 n_steps: int = _N_UNIFORM):
        if not isinstance(material, Material):
            raise ValueError(f"material: expected a Material, got {type(material).__name__}")
        if not (np.isfinite(r1) and r1 > 0):
            raise ValueError(f"r1 = {r1} m: must be > 0")
        if not (np.isfinite(t0) and t0 > 0):
            raise ValueError(f"t0 = {t0} m: must be > 0")
        if contact not in CONTACTS:
            raise ValueError(f"contact = '{contact}': allowed {', '.join(CONTACTS)}")
        if contact == "bonded" and not (np.isfinite(c) and 0 < c < r1):
            raise ValueError(f"c = {c * 1e3:g} mm: the disk radius must be in (0, {r1 * 1e3:g}) mm")
        if not (isinstance(n_steps, int) and n_steps >= 20):
            raise ValueError(f"n_steps = {n_steps}: must be an integer >= 20")
        material.validate()
        self.material, self.r1, self.t0, self.contact_type, self.c = material, float(r1), float(t0), contact, float(c)
        self.n_steps = n_steps
        self.mu = _shear_modulus(material)
        self._pscale = self.mu * self.t0 / self.r1  # Pa per unit of P
        self.lam_hi = min(4.0, 1.0 + 0.98 * (material.lam_max() - 1.0))
        self._d = _derivs(material)

    # ----------------------------------------------------------------------------------- helpers
    def _w(self, l1, l2) -> tuple[np.ndarray, ...]:
        out = self._d(np.atleast_1d(l1)[None, :], np.atleast_1d(l2)[None, :])
        return tuple(np.asarray(o).ravel() for o in out)

    def _shoot(self, s0: np.ndarray, x0: np.ndarray, P: np.ndarray) -> np.ndarray:
        """Summaries (11, B) of the marches from starts s0 (6, B) at x0 (B,) with pressures P (B,): rows
        0-5 the state at the clamp, 6 the smallest rho, 7 the smallest l1, 8 NaN where the march broke,
        9 and 10 the smallest meridional and hoop tension (w1, w2), 11 the largest |phi|."""
        B = s0.shape[1]
        fun = _mapped(self.material, self.n_steps, B)
        return np.asarray(fun(s0, x0[None, :], P[None, :]))

    def _trajectory(self, s0: np.ndarray, x0: float, P: float) -> np.ndarray:
        """The whole march (6, nodes) of one start s0 (6,) at x0 with pressure P."""
        traj = np.asarray(_march(self.material, self.n_steps)[1](s0, x0, P))
        return np.concatenate([np.asarray(s0, dtype=float).reshape(_STATE, 1), traj], axis=1)

    def _nodes(self, x0: np.ndarray) -> np.ndarray:
        """Mesh nodes (nodes, B), dimensionless radius, of marches starting at x0 (B,)."""
        u = _march(self.material, self.n_steps)[2]
        return x0[None, :] + (1 - x0[None, :]) * u[:, None]

    def _clamp_miss(self, end: np.ndarray) -> np.ndarray:
        """rho(r1)/r1 - 1, or -1 where the meridian curled back to the axis or the march broke down."""
        # a meridian turning past the vertical the other way (|phi| > pi) has curled up on itself: near
        # an edge with almost no tension the march does that before it can come back to the clamp
        bad = ~np.isfinite(end[8]) | (end[6] <= 0) | (end[7] <= _L1_MIN) | (end[11] > np.pi)
        return np.where(bad, -1.0, end[1] - 1.0)

    def _bisect_P(self, make_start, B: int, iters: int = 80) -> tuple[np.ndarray, np.ndarray]:
        """Pressures P (B,) that meet the clamp (rho(r1) = r1); also their trajectories.

        ``make_start(P, k)`` gives the starts for pressures P, each of the B points repeated k times.
        A larger pressure curls the meridian more, so rho(r1) falls with P until the march breaks down
        (the meridian reaches the axis or folds): a scan brackets the first crossing, Illinois refines it.
        """
        grid = _P_SCAN
        k = grid.size
        Pk = np.tile(grid, B)  # point-major: point i's scan is Pk[i k:(i + 1) k]
        s0, x0 = make_start(Pk, k)
        miss = self._clamp_miss(self._shoot(s0, x0, Pk)).reshape(B, k)
        first = np.argmax(miss <= 0, axis=1)
        none = ~np.any(miss <= 0, axis=1)
        first = np.where(none, k - 1, np.maximum(first, 1))
        lo, hi = grid[first - 1], grid[first]
        f_lo, f_hi = miss[np.arange(B), first - 1], miss[np.arange(B), first]
        bad_hi = f_hi <= -1.0  # a broken march: its -1 is a flag, not a value to interpolate
        side = np.zeros(B)
        for _ in range(iters):
            # Illinois regula falsi where both ends are genuine, bisection while the upper one is a flag
            rf = hi - f_hi * (hi - lo) / np.where(f_hi != f_lo, f_hi - f_lo, 1.0)
            mid = np.where(bad_hi, 0.5 * (lo + hi), np.clip(rf, lo, hi))
            s0, x0 = make_start(mid, 1)
            f = self._clamp_miss(self._shoot(s0, x0, mid))
            pos = f > 0
            # Illinois: halve the kept end's value when the same end is kept twice
            f_hi = np.where(~pos, f, np.where(side > 0, 0.5 * f_hi, f_hi))
            f_lo = np.where(pos, f, np.where(side < 0, 0.5 * f_lo, f_lo))
            side = np.where(pos, 1.0, -1.0)
            bad_hi = np.where(pos, bad_hi, f <= -1.0)
            lo, hi = np.where(pos, mid, lo), np.where(pos, hi, mid)
            if np.all((np.abs(f) < 1e-14) | (hi - lo < 1e-14 * np.maximum(hi, 1e-3))):
                lo = hi = mid
                break
        P = np.where(none, np.nan, 0.5 * (lo + hi))
        s0, x0 = make_start(P, 1)
        return P, self._shoot(s0, x0, P)

    def _pole_start(self, lam0: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w, w1, *_ = self._w(lam0, lam0)
        kappa = P * lam0 / (2 * w1)  # curvature of the spherical pole, per r1
        x0 = np.full(lam0.shape, _X0)
        s0 = np.vstack([lam0, lam0 * x0, kappa * lam0 * x0, -0.5 * kappa * (lam0 * x0) ** 2,
                        np.zeros_like(lam0), np.pi * w * x0**2])
        return s0, x0

    def _result(self, P, traj) -> dict:
        s = traj[:_STATE]
        return {"p": P * self._pscale, "h": -s[3] * self.r1, "V": s[4] * self.r1**3,
                "U": s[5] * self.mu * self.t0 * self.r1**2}

    # ------------------------------------------------------------------------------ free inflation
    def free_pole(self, lam0) -> dict:
        """Free inflation at pole stretches lam0 (-, > 1; array): p (Pa), h apex height (m), V (m^3),
        U stored strain energy (J), lam0; vectorised over lam0."""
        lam0 = np.atleast_1d(np.asarray(lam0, dtype=float))
        if not np.all((lam0 > 1.0) & (lam0 <= self.lam_hi)):
            raise ValueError(f"lam0 = {lam0.min():g}..{lam0.max():g}: the pole stretch must be in (1, {self.lam_hi:g}]")
        P, traj = self._bisect_P(lambda Pm, k: self._pole_start(np.repeat(lam0, k), Pm), lam0.size)
        out = self._result(P, traj)
        out["lam0"] = lam0
        return out

    def _lam0_for_h(self, h: float) -> float:
        x = h / self.r1
        # cap guess: lam^2 = 1 + (h/r1)^2; the pole stretches more than the average, so bracket widely
        def f(lam):
            return float(self.free_pole(lam)["h"][0]) - h

        hi = min(self.lam_hi, 1.0 + 2.0 * x * x + 0.5 * x + 1e-3)
        while f(hi) < 0:
            if hi >= self.lam_hi:
                h_max = float(self.free_pole(self.lam_hi)["h"][0])
                raise ValueError(f"h = {h * 1e3:g} mm: beyond this membrane's reach in free inflation; allowed "
                                 f"(0, {h_max * 1e3:.4g}] mm (pole stretch up to {self.lam_hi:g})")
            hi = min(self.lam_hi, 1.0 + 2 * (hi - 1.0))
        return brentq(f, 1.0 + 1e-12, hi, xtol=1e-13, rtol=1e-12)

    def free(self, h: float, profile: bool = False) -> dict:
        """Free inflation at apex height h (m, > 0): p (Pa), V (m^3), U (J), lam0 (pole stretch, -), and
        with ``profile`` the meridian r, z (m, arrays from pole to clamp) and its stretches l1, l2."""
        h = self._check_h(h, "h")
        lam0 = self._lam0_for_h(h)
        P, traj = self._bisect_P(lambda Pm, k: self._pole_start(np.full(k, lam0), Pm), 1)
        out = {k: float(v[0]) for k, v in self._result(P, traj).items()}
        out["lam0"] = lam0
        if profile:
            s0, x0 = self._pole_start(np.array([lam0]), P)
            out.update(self._profile(self._trajectory(s0[:, 0], x0[0], P[0]), x0))
        return out

    def _profile(self, traj: np.ndarray, x0: np.ndarray) -> dict:
        x = self._nodes(x0)[:, 0]
        z = traj[3] - traj[3, -1]
        return {"r": traj[1] * self.r1, "z": z * self.r1, "l1": traj[0], "l2": traj[1] / x, "R": x * self.r1}

    def limit_point(self) -> dict:
        """The free-inflation pressure maximum: p (Pa), h (m), lam0 (-).

        A pole-stretch sweep brackets it; two rounds of 9-point sweeps narrow the bracket and a parabola
        through the top of the last sweep places the maximum (the pressure is smooth there).
        """
        lam = np.linspace(1.02, self.lam_hi, 41)
        for _ in range(3):
            p = self.free_pole(lam)["p"]
            i = int(np.argmax(p))
            if i == len(lam) - 1:
                raise ValueError(f"material {self.material.name}: no pressure maximum up to pole stretch "
                                 f"{self.lam_hi:g}")
            i = min(max(i, 1), len(lam) - 2)
            top = lam[i - 1:i + 2]
            lam = np.linspace(top[0], top[-1], 9)
        p = self.free_pole(lam)["p"]
        i = min(max(int(np.argmax(p)), 1), len(lam) - 2)
        c2, c1, _ = np.polyfit(lam[i - 1:i + 2] - lam[i], p[i - 1:i + 2], 2)
        lam_star = lam[i] - c1 / (2 * c2)
        top = self.free_pole(lam_star)
        return {"p": float(top["p"][0]), "h": float(top["h"][0]), "lam0": float(lam_star)}

    # ------------------------------------------------------------------------------ contact
    def _check_h(self, h, name: str) -> float:
        h = float(h)
        if not (np.isfinite(h) and 0 < h < 5 * self.r1):
            raise ValueError(f"{name} = {h * 1e3:g} mm: must be in (0, {5 * self.r1 * 1e3:g}) mm")
        return h

    def _plate_shoot(self, lam0, xc, P) -> np.ndarray:
        lam0, xc, P = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (lam0, xc, P))
        w = self._w(lam0, lam0)[0]
        s0 = np.vstack([lam0, lam0 * xc, np.zeros_like(xc), np.zeros_like(xc), np.zeros_like(xc), np.pi * w * xc**2])
        return self._shoot(s0, xc, P)

    def _disk_shoot(self, l1c, phic, P) -> np.ndarray:
        l1c, phic, P = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (l1c, phic, P))
        xc = np.full(l1c.shape, self.c / self.r1)
        z = np.zeros_like(xc)
        s0 = np.vstack([l1c, xc, phic, z, z, z])
        return self._shoot(s0, xc, P)

    def contact(self, h: float, p: float) -> dict:
        """Equilibrium with the centre at height h (m) and gauge pressure p (Pa).

        'flat': F = p pi a^2 (N), a_contact (m, the contact radius), V (m^3), lam0 (the stretch on the
        plate). 'bonded': F (N, the force the membrane and gas exert on the disk, up positive),
        a_contact = c, V, l1c and phi_c (the meridian's stretch and slope, rad, at the disk's edge),
        T1 (N/m, meridional tension there).
        """
        h = self._check_h(h, "h")
        p = float(p)
        if not (np.isfinite(p) and p >= 0):
            raise ValueError(f"p = {p * 1e-3:g} kPa: must be >= 0 kPa")
        P = p / self._pscale
        if self.contact_type == "flat":
            return self._flat(h, P)
        return self._bonded(h, P)

    def _inner(self, make, outer: np.ndarray, lo: float, hi: float, P: float, branch: int = 0, iters: int = 60):
        """For each outer value, the inner unknown in [lo, hi] that meets the clamp (rho(r1) = r1).

        ``make(outer, inner, P)`` shoots from the contact edge. rho(r1) first grows with the inner
        stretch (a march that breaks down counts as too short), and above the free limit-point pressure
        falls again: ``branch`` 0 takes the first root of a scan (the rising one), 1 the second.
        Returns (inner, summaries), inner NaN where that root does not exist in [lo, hi].
        """
        B, K = outer.size, _INNER_SCAN
        grid = lo + (hi - lo) * np.linspace(0.0, 1.0, K) ** 2  # denser near lo, where solutions crowd
        miss = self._clamp_miss(make(np.repeat(outer, K), np.tile(grid, B), np.full(B * K, P))).reshape(B, K)
        pos = miss > 0
        a, b = np.full(B, lo), np.full(B, hi)
        ok = np.zeros(B, dtype=bool)
        for n in range(B):
            change = np.flatnonzero(pos[n, 1:] != pos[n, :-1])
            if change.size > branch:
                k = change[branch]
                a[n], b[n], ok[n] = grid[k], grid[k + 1], True
        Pv = np.full(B, P)
        fa, fb = self._clamp_miss(make(outer, a, Pv)), self._clamp_miss(make(outer, b, Pv))
        side = np.zeros(B)
        for _ in range(iters):
            # Illinois regula falsi while both ends are genuine values, bisection next to a broken march
            flagged = (fa <= -1.0) | (fb <= -1.0)
            rf = b - fb * (b - a) / np.where(fb != fa, fb - fa, 1.0)
            mid = np.where(flagged, 0.5 * (a + b), np.clip(rf, np.minimum(a, b), np.maximum(a, b)))
            f = self._clamp_miss(make(outer, mid, Pv))
            same = (f > 0) == (fa > 0)  # the new point replaces the end of its sign
            fb = np.where(~same, f, np.where(side > 0, 0.5 * fb, fb))
            fa = np.where(same, f, np.where(side < 0, 0.5 * fa, fa))
            side = np.where(same, 1.0, -1.0)
            a, b = np.where(same, mid, a), np.where(same, b, mid)
            if np.all(~ok | (np.abs(f) < 1e-14) | (np.abs(b - a) < 1e-14)):
                a = b = mid
                break
        inner = np.where(ok, 0.5 * (a + b), np.nan)
        return inner, make(outer, np.where(ok, inner, hi), Pv)

    def _edge_solve(self, make, grid: np.ndarray, lo: float, hi: float, P: float, x: float):
        """(outer, inner, summary) with the clamp met and the centre at height x (dimensionless), or None.

        On each branch of the inner root the apex-to-clamp drop varies monotonically along ``grid``: a
        scan brackets the first crossing of x (lower branch first), Brent's method refines it (each
        step one vectorised inner solve).
        """
        for branch in (0, 1):
            inner, tr = self._inner(make, grid, lo, hi, P, branch)
            for i, j in self._crossings(inner, tr, x):
                got = self._refine(make, grid[i], grid[j], lo, hi, P, x, branch)
                if got is not None:
                    return got
        return None

    @staticmethod
    def _crossings(inner: np.ndarray, tr: np.ndarray, x: float) -> list[tuple[int, int]]:
        """Pairs (i, j) of successive valid outer values between which the drop minus x changes sign.

        Valid: the inner root exists and the membrane is taut (a slack meridian or hoop, negative
        tension, is outside membrane theory); invalid values in between are skipped.
        """
        taut = (tr[9] > 0) & (tr[10] >= 0)
        g = np.where(np.isfinite(inner) & taut, -tr[3] - x, np.nan)
        idx = np.flatnonzero(np.isfinite(g))
        return [(int(i), int(j)) for i, j in zip(idx[:-1], idx[1:]) if np.sign(g[i]) != np.sign(g[j])]

    def _brent(self, make, a: float, b: float, lo: float, hi: float, P: float, x: float, branch: int):
        """Brent's method on the outer unknown in [a, b]; None where an inner root is missing."""
        class _Missing(Exception):
            pass

        def f(o):
            i, t = self._inner(make, np.array([o]), lo, hi, P, branch)
            if not (np.isfinite(i[0]) and t[9, 0] > 0 and t[10, 0] >= 0):
                raise _Missing
            return -t[3, 0] - x

        try:
            return brentq(f, a, b, xtol=1e-14, rtol=1e-13)
        except (_Missing, ValueError):
            return None

    def _refine(self, make, a: float, b: float, lo: float, hi: float, P: float, x: float, branch: int):
        """Narrow a bracket [a, b] of the outer unknown by nested 9-point sweeps (one vectorised inner solve
        each; they skip outer values whose inner root is missing, where Brent's method would stop)."""
        o = 0.5 * (a + b)
        for _ in range(40):
            sub = np.linspace(a, b, 9)
            inner, tr = self._inner(make, sub, lo, hi, P, branch)
            pairs = self._crossings(inner, tr, x)
            if not pairs:
                return None
            i, j = pairs[0]
            g0, g1 = -tr[3, i] - x, -tr[3, j] - x
            a, b = sub[i], sub[j]
            o = a - g0 * (b - a) / (g1 - g0)  # linear interpolation inside the last bracket
            if b - a < 1e-13:
                break
            if b - a < 1e-3 * (abs(a) + abs(b) + 1e-3):
                # narrow and valid at both ends: Brent's method converges in a few steps (sweeps resume
                # if it meets an outer value without an inner root)
                o_b = self._brent(make, a, b, lo, hi, P, x, branch)
                if o_b is not None:
                    o = o_b
                    break
        i, t = self._inner(make, np.array([o]), lo, hi, P, branch)
        if not (np.isfinite(i[0]) and abs(-t[3, 0] - x) < 1e-9 and t[9, 0] > 0 and t[10, 0] >= 0):
            return None
        return o, float(i[0]), t

    def _flat(self, h: float, P: float) -> dict:
        x = h / self.r1
        if P <= 0:
            raise ValueError("p = 0 kPa: a flat plate needs a positive pressure to be in contact")

        def make(xc, lam0, Pv):
            return self._plate_shoot(lam0, xc, Pv)

        # dense at small contact radii, where the solution turns from one stretch branch to the other
        grid = np.concatenate([[1e-6], 0.98 * np.linspace(0.1, 1.0, 30) ** 2])
        got = self._edge_solve(make, grid, 1.0 + 1e-9, self.lam_hi, P, x)
        if got is None:
            raise ValueError(f"h = {h * 1e3:g} mm: at p = {P * self._pscale * 1e-3:g} kPa the plate does not touch "
                             f"the membrane (or the contact lies beyond pole stretch {self.lam_hi:g}); the free apex "
                             f"at this pressure is below the plate")
        xc, lam0, tr = got
        out = {k: float(v[0]) for k, v in self._result(np.array([P]), tr).items()}
        a = lam0 * xc * self.r1
        out.update(F=out["p"] * np.pi * a * a, a_contact=a, lam0=lam0, h=h)
        return out

    def _bonded(self, h: float, P: float) -> dict:
        x = h / self.r1

        def make(phic, l1c, Pv):
            return self._disk_shoot(l1c, phic, Pv)

        # the meridian leaves the disk's edge between straight up and straight down
        grid = np.linspace(-1.5, 1.5, 31)
        got = self._edge_solve(make, grid, 1.0 + 1e-6, self.lam_hi, P, x)
        if got is None:
            raise ValueError(f"h = {h * 1e3:g} mm, p = {P * self._pscale * 1e-3:g} kPa: no bonded equilibrium with "
                             f"the meridian's stretch in (1, {self.lam_hi:g}]")
        phic, l1c, tr = got
        out = {k: float(v[0]) for k, v in self._result(np.array([P]), tr).items()}
        w1 = self._w(l1c, 1.0)[1][0]
        T1 = self.t0 * self.mu * w1  # l2 = 1 at the disk's edge
        out.update(F=out["p"] * np.pi * self.c**2 - 2 * np.pi * self.c * T1 * np.sin(phic), a_contact=self.c,
                   l1c=l1c, phi_c=float(phic), T1=float(T1), h=h)
        return out


def equilibrium(material: Material, r1: float, t0: float, h: float, p: float | None = None, contact: str = "flat",
                c: float = 0.0, V0: float = 0.0) -> dict:
    """One exact equilibrium, SI in and out (the CLI's ``equilibrium --fidelity exact``).

    Free inflation when ``p`` is None (h: apex height, m); otherwise the centre held at height h (m)
    at gauge pressure p (Pa) by a flat plate (contact 'flat') or a bonded disk of radius c (m).
    Returns p (Pa), F (N), stretch (-: the pole's, the plate's, or the meridian's at the disk's edge),
    V (m^3, gas volume including the dead volume V0), contact_radius (m).
    """
    if not (np.isfinite(V0) and V0 >= 0):
        raise ValueError(f"V0 = {V0 * 1e6:g} cm^3: must be >= 0 cm^3")
    m = ExactMembrane(material, r1, t0, contact, c)
    if p is None:
        r = m.free(h)
        return {"p": r["p"], "F": 0.0, "stretch": r["lam0"], "V": r["V"] + V0, "contact_radius": 0.0}
    r = m.contact(h, p)
    return {"p": r["p"], "F": r["F"], "stretch": r.get("lam0", r.get("l1c")), "V": r["V"] + V0,
            "contact_radius": r["a_contact"]}
