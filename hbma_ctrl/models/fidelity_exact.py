"""The exact membrane's rungs of the fidelity ladder (:mod:`hbma_ctrl.models.fidelity`).

- :class:`ExactFreeInflation` (:func:`make_exact_free`): free inflation with the exact axisymmetric
  membrane's pressure and volume, from a dimensionless table of :mod:`hbma_ctrl.models.exact`
  (:func:`exact_free_table`) instead of the spherical cap.
- :class:`ExactQuasiStatic` and :class:`ExactPlatform` (:func:`make_exact_loaded`): the loaded rungs with
  the exact flat-plate contact, the cap's chart with the exact law as tabulated ratios
  (:func:`exact_contact_table`, :mod:`hbma_ctrl.models.exact_tables`).
- :func:`make_exact`: the simulator's ``exact`` rung (the platform model with a load, the free
  inflation without one).

Each table is built once per material family and cached on disk; the Functions once per process.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.materials import Material
from hbma_ctrl.models.fidelity import DynamicPlatform, Fidelity, FreeInflation, QuasiStatic, cap_law
from hbma_ctrl.models.piecewise import PiecewiseCubic

__all__ = ["EXACT_X_MAX", "exact_free_table", "ExactFreeInflation", "make_exact_free", "exact_contact_table",
           "ExactQuasiStatic", "ExactPlatform", "make_exact_loaded", "make_exact"]


#: the exact free table's reach, apex height over r1 (past the limit point: 1.17 r1 for NH)
EXACT_X_MAX = 1.8
_EXACT_NODES = 91  # 0.02 r1 spacing: the bspline is within 0.5 % of the solver at mid-nodes (docs/concepts/model.md §9)


def exact_free_table(material: Material) -> dict:
    """The exact membrane's free inflation in dimensionless form, cached on disk (see ``tabulate``).

    Returns x = h/r1 (apex height over the clamp radius, from 0), Pn = p r1 / (mu t0) with mu = Q(1)/12
    the shear modulus, vn = V / r1^3 (volume above the clamp plane) and lam0 (pole stretch). The form
    depends only on the material's parameter ratios: scaling every modulus, r1 or t0 (the rig's
    mismatch, theta in the Functions) rescales p and V exactly, so one table serves a family.
    """
    from hbma_ctrl.models.exact import ExactMembrane
    from hbma_ctrl.models.exact_tables import tabulate

    r1, t0 = 7.5e-3, 3e-3  # any geometry gives the same dimensionless table
    m = ExactMembrane(material, r1, t0)
    reach = float(m.free_pole(m.lam_hi)["h"][0]) / r1
    x_max = min(EXACT_X_MAX, 0.98 * reach)
    x = np.linspace(0.0, x_max, _EXACT_NODES)
    tab = tabulate(m, x[1:] * r1)
    mu = material.modulus_q1 / 12.0
    return {"x": x, "Pn": np.concatenate([[0.0], tab["p"] * r1 / (mu * t0)]),
            "vn": np.concatenate([[0.0], tab["V"] / r1**3]), "lam0": np.concatenate([[1.0], tab["lam0"]])}


class ExactFreeInflation(FreeInflation):
    """Free inflation with the exact axisymmetric membrane (:mod:`hbma_ctrl.models.exact`): x = [h1].

    h1 is the apex height (m). p(h1) = mu t0 / r1 Pn(h1 / r1) and V = V0 + r1^3 vn(h1 / r1) come from
    cubic-spline interpolants of :func:`exact_free_table` (mu = Q(1)/12, symbolic in theta), replacing the
    cap's closed forms; the gas law G = (p + p_env) V = m R T and h1' = q R T / (dG/dh1) are unchanged.
    ``lam`` is the pole stretch. The name stays 'free' (the simulator's hybrid logic and steps are
    those of free inflation); ``membrane`` tells the two apart. Beyond ``x_max`` r1 the cap's law, scaled to meet the table.
    """

    membrane = "exact"

    def __init__(self, material: Material, compressor_csv: str, table: dict):
        super().__init__(material, compressor_csv)
        x = np.asarray(table["x"], dtype=float)
        self.x_max = float(x[-1])
        # the bsplines as their piecewise polynomials (:mod:`hbma_ctrl.models.piecewise`): the same
        # values, derivatives without interpolant calls
        self._free = PiecewiseCubic("exact_free", [x], [table["Pn"], table["vn"], table["lam0"]])

    def law(self, h1, P) -> tuple:
        """Exact p (Pa), membrane volume above the clamp (m^3) and pole stretch at apex height h1 (m).

        Past the table's end (the exact solver stops at a pole stretch of 4: h ~ 1.77 r1 for NH) the
        cap's law continues it, scaled to meet the table there: the cap's error shrinks as the
        membrane rounds (-0.6 % in p at 1.5 r1), and a free inflation past the limit point must not
        run off an interpolant's extrapolation.
        """
        r1, t0 = P["r1"], P["t0"]
        mu = P["material"].Q(1.0) / 12.0
        # a membrane pulled below its clamp (h1 < 0: venting past flat, a vacuum) is the mirror image
        # of the one above: p and the volume it adds are odd in h1, the stretch even (the table holds
        # h1 >= 0 only, and a bspline is 0 outside its grid: a vent from flat diverged there)
        sgn = ca.if_else(h1 < 0, -1.0, 1.0)
        h = ca.if_else(h1 < 0, -h1, h1)  # not fabs: its derivative at 0 is 0, and dG/dh1 there must not be
        x = h / r1
        xm = self.x_max
        hm = xm * r1
        scale = mu * t0 / r1
        # (x clamped to the table for the lookup: past its end the cap's branch below is taken)
        pn, vn, ln = self._free(ca.fmin(x, xm))
        p_tab, v_tab, l_tab = scale * pn, r1**3 * vn, ln
        pm, vm, lm = (float(v) for v in self._free(ca.DM(xm)))
        gm, g = ph.geometry(hm, 0, P), ph.geometry(h, 0, P)
        p_cap = ph.pressure(h, 0, P) * scale * pm / ph.pressure(hm, 0, P)
        v_cap = (g["V"] - P["V0"]) * r1**3 * vm / (gm["V"] - P["V0"])
        l_cap = g["lam"] * lm / gm["lam"]
        beyond = x > xm
        return (sgn * ca.if_else(beyond, p_cap, p_tab), sgn * ca.if_else(beyond, v_cap, v_tab),
                ca.if_else(beyond, l_cap, l_tab))

    def _derivs(self, h1, P):
        s = ca.SX.sym("s")
        p, Vm, _ = self.law(s, P)
        G = (p + P["p_env"]) * (P["V0"] + Vm)
        dG, dp = ca.substitute([ca.jacobian(G, s), ca.jacobian(p, s)], [s], [h1])
        return dG, dp

    def _rhs(self, x, u, P, mode):
        h1 = x[0]
        p, _, _ = self.law(h1, P)
        q, _, _ = ph.net_flow(u, p, P, self.table)
        dG, _ = self._derivs(h1, P)
        return ca.vertcat(q * P["R"] * P["T"] / dG)

    def _out(self, x, u, P, mode):
        h1 = x[0]
        p, Vm, lam = self.law(h1, P)
        dG, dp = self._derivs(h1, P)
        q, q_in, q_out = ph.net_flow(u, p, P, self.table)
        V = P["V0"] + Vm
        m = (p + P["p_env"]) * V / (P["R"] * P["T"])
        return ca.vertcat(h1, 0 * h1, h1, p, 0 * h1, q, q_in, q_out, lam, V, m, dG, dp)


def _normalised(material: Material) -> Material:
    """The material with its shear modulus set to 10 kPa, parameters rounded to 10 digits: the shape of
    its free inflation (what the exact table holds) is that of ``material``, and scaled copies of it
    (a rig's modulus mismatch) map to the same table."""
    norm = material.scaled(1.2e5 / material.modulus_q1)
    kw = {}
    for k, v in norm.as_dict().items():
        kw[k] = tuple(float(f"{e:.10g}") for e in v) if isinstance(v, (tuple, list)) else float(f"{v:.10g}")
    return type(material)(**kw)


def make_exact_free(material: Material, compressor_csv: str) -> ExactFreeInflation:
    """The exact free-inflation rung for a material (its table built once, then cached on disk and here)."""
    norm = _normalised(material)
    key = ("exact_free", type(norm).__name__, repr(norm.as_dict()), str(compressor_csv))
    if key not in _EXACT_CACHE:
        _EXACT_CACHE[key] = ExactFreeInflation(material, str(compressor_csv), exact_free_table(norm))
    return _EXACT_CACHE[key]


def exact_contact_table(material: Material) -> dict:
    """The exact flat-plate contact as ratios to the cap over its chart (u = h1/r1, s = h2/h1), cached on
    disk (:func:`hbma_ctrl.models.exact_tables.contact_ratio_table`); like :func:`exact_free_table`, one
    table serves every geometry and modulus scale of a material's shape."""
    from hbma_ctrl.models.exact import ExactMembrane
    from hbma_ctrl.models.exact_tables import contact_ratio_table

    return contact_ratio_table(ExactMembrane(material, 7.5e-3, 3e-3))


class _ExactContact:
    """The exact membrane's law in the cap's chart (mixed into the loaded fidelities).

    p = Rp(u, s) p_cap(h1, h2) and V = V0 + Rv(u, s) (V_cap - V0), with cubic-spline interpolants of
    :func:`exact_contact_table` over u = h1/r1 and sqrt(s), s = h2/h1 (the ratios are smooth in the
    contact radius, which grows like sqrt(h2)); the contact radius is the cap's, so F = p pi a^2 and
    F -> 0 as the plate leaves (s -> 0, the exact free inflation). Outside the table (u < 0.05 or
    u > 1.6 r1, s > 0.97: nearly flat under the plate) the ratios at its edge continue it; ``lam`` is
    the exact stretch on the plate (the pole's in free inflation).
    """

    membrane = "exact"

    def __init__(self, material: Material, compressor_csv: str, table: dict):
        super().__init__(material, compressor_csv)
        u = np.asarray(table["u"], dtype=float)
        sig = np.sqrt(np.asarray(table["s"], dtype=float))
        self._lims = (float(u[0]), float(u[-1]), float(sig[-1]))
        # the bsplines as their piecewise polynomials: one inline evaluation gives all three ratios,
        # and the roles' Jacobians differentiate arithmetic, not interpolant calls (those calls would
        # be most of the exact EKF step's cost; :mod:`hbma_ctrl.models.piecewise`)
        self._ratios = PiecewiseCubic("exact_ratios", [u, sig], [table["Rp"], table["Rv"], table["lam0"]])

    def _coords(self, h1, h2, P):
        r1 = P["r1"]
        u0, u1, sig1 = self._lims
        u = ca.fmin(ca.fmax(h1 / r1, u0), u1)
        s = ca.fmax(h2 / ca.fmax(h1, 1e-9 * r1), 0)
        # the tiny shift keeps d sqrt(s)/ds finite at s = 0 (airborne, free inflation) for the Jacobians;
        # the clamp after the root: a bspline is zero outside its grid
        return ca.vertcat(u, ca.fmin(ca.sqrt(s + 1e-12), sig1))

    def contact_law(self, h1, h2, P) -> tuple:
        """Exact p (Pa), V (m^3), plate stretch (-) and the cap's a2 (m^2) at chart (h1, h2) (m)."""
        p_cap, V_cap, _, a2 = cap_law(h1, h2, P)
        rp, rv, lam = self._ratios(self._coords(h1, h2, P))
        return (rp * p_cap, P["V0"] + rv * (V_cap - P["V0"]), lam, a2)

    def flat_h1(self, p, P):
        """The chart's flat point at pressure p: the cap's, corrected by the ratio at the flat edge."""
        h = ph.flat_h1_from_pressure(p, P)
        for _ in range(2):
            h = ph.flat_h1_from_pressure(p / self._ratios(self._coords(h, h, P))[0], P)
        return h


class ExactQuasiStatic(_ExactContact, QuasiStatic):
    """:class:`QuasiStatic` with the exact flat-plate contact (:class:`_ExactContact`): x = [m, h1, h2].
    The name stays 'quasi_static' (the simulator's hybrid logic keys on it); ``membrane`` tells them apart.
    A snap-through's far branch is still located on the cap's load path (then projected onto the exact law)."""


class ExactPlatform(_ExactContact, DynamicPlatform):
    """:class:`DynamicPlatform` with the exact flat-plate contact and, airborne, the exact free inflation
    (:class:`_ExactContact`): x = [m, h1, z, v]. The name stays 'platform'."""


def make_exact_loaded(name: str, material: Material, compressor_csv: str) -> Fidelity:
    """The exact membrane's loaded rung: 'quasi_static' or 'platform' (its table built once, then cached)."""
    classes = {"quasi_static": ExactQuasiStatic, "platform": ExactPlatform}
    if name not in classes:
        raise ValueError(f"fidelity: exact contact needs a loaded rung, got '{name}'; allowed: {', '.join(classes)}")
    norm = _normalised(material)
    key = ("exact_loaded", name, type(norm).__name__, repr(norm.as_dict()), str(compressor_csv))
    if key not in _EXACT_CACHE:
        _EXACT_CACHE[key] = classes[name](material, str(compressor_csv), exact_contact_table(norm))
    return _EXACT_CACHE[key]


def make_exact(loaded: bool, material: Material, compressor_csv: str) -> Fidelity:
    """The simulator's ``exact`` rung: the platform model with exact contact for a loaded scene, the
    exact free inflation without a load."""
    if loaded:
        return make_exact_loaded("platform", material, compressor_csv)
    return make_exact_free(material, compressor_csv)


_EXACT_CACHE: dict = {}
