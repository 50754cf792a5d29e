"""Fit a membrane material to static equilibrium data: ``hbma-ctrl fit`` (SI inside).

Static data are equilibrium points of one chamber (docs/concepts/model.md §1-§3): CSV columns ``h_mm``,
``p_kpa`` and, for a chamber lifting a load or pressed by a flat plate, ``F_n`` or ``load_g``.
Each point's model pressure comes from the package's physics:

- ``free``: a free cap of height h (h2 = 0), ``p = pressure(h, 0)``;
- ``flat``: the contact shape (h1, h2) with ``h1 - h2 = h`` and ``F(h1, h2) = F``, solved by the one
  shape solver (:meth:`hbma_ctrl.models.shape.ShapeSolver.h2_for_force`), then ``p = pressure(h1, h2)``;
- ``bonded``: the membrane's centre glued to a rigid disk of radius c at height h pushing it with F: the
  exact membrane's bonded tables (:mod:`hbma_ctrl.app.tuning.fit_bonded`; ``nh`` or ``gent``, the exact
  law only); a row at h = 0 is the disk resting on its stop, whose pressure is at most the lift-off one.

The law is the spherical cap's (``fidelity = "cap"``, docs/concepts/model.md §3) or the exact axisymmetric
membrane's (``"exact"``, Model §9): the same tabulated law, in the same chart, that the rig, the EKF
and the MPC take with ``membrane = "exact"`` (:func:`hbma_ctrl.models.tables.exact_shape_function`).
Its tables hold one material *shape* (the parameters' ratios) at any modulus scale, so they serve a
material whose one modulus is its only parameter (``nh``), free or on a plate. The other materials'
free-inflation points are fitted with the exact solver itself (:class:`_ExactFree`: the free curve
of each trial's parameters, :meth:`hbma_ctrl.models.exact.ExactMembrane.free_pole` over pole
stretches, refined from the cap's fit); their plate contact would need a table at every trial value.

The material parameters (flattened as in :class:`hbma_ctrl.core.physics.ParamSpace`: ``E``; ``C1``,
``C2``; ``C0..C2`` for Yeoh; ``mu``, ``Jm``; ``mu0, mu1, alpha0, alpha1``) are fitted by
``scipy.optimize.least_squares`` through :mod:`hbma_ctrl.core.identify` on the pressure residuals
divided by the data's pressure span, each parameter in units of its default, from several starts.
Intervals (95 %) come from the Jacobian at the optimum with the residual variance and a t quantile;
what the data cannot separate is named by :func:`hbma_ctrl.core.identify.weak_directions`.

Nothing here touches files (:mod:`hbma_ctrl.app.tuning.fit_output` writes them); :func:`parse_data` takes the
file's bytes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hbma_ctrl.app.metrics import nrmsd
from hbma_ctrl.app.tuning.run_data import P_KPA_MAX, check_height_unit, data_number, data_rows
from hbma_ctrl.core import physics as ph
from hbma_ctrl.core import units as U
from hbma_ctrl.core.identify import Coordinates, estimate, finite_residuals, solve, summary
from hbma_ctrl.core.materials import MATERIALS, make_material
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE
from hbma_ctrl.models.exact_tables import RATIO_U
from hbma_ctrl.models.shape import ShapeSolver
from hbma_ctrl.models.tables import exact_shape_function

__all__ = [
    "CONTACTS",
    "FIDELITIES",
    "FIT_KEYS",
    "StaticData",
    "FitReport",
    "FitResult",
    "parse_data",
    "rising",
    "param_names",
    "model_pressure",
    "check_options",
    "check_exact_material",
    "check_disk_radius",
    "resolve_fidelity",
    "exact_shapes_fixed",
    "fit_static",
    "split_fix",
    "unflatten",
]

#: contact modes of this command: free inflation, a loose flat plate, a rigid disk glued at the centre
CONTACTS = ("free", "flat", "bonded")
#: membrane laws of this command: the spherical cap, or the exact axisymmetric membrane's tables
FIDELITIES = ("cap", "exact")
#: the keys of fit.json
FIT_KEYS = ("material", "params", "ci95", "nrmsd", "n_points", "unidentifiable", "correlation")
#: start factors on the default moduli (log-spaced)
_START_FACTORS = (0.1, 0.3, 1.0, 3.0, 10.0)
#: pole stretches of the exact solver's free curve for one trial of a shape-changing material
EXACT_FREE_POLES = 48
#: the exact solver's refinement of a shape-changing material's fit: at most this many steps (each its
#: curve and one per free parameter for the Jacobian)
_EXACT_NFEV = 20


@dataclass(frozen=True)
class StaticData:
    """Static equilibrium points, SI: heights h (m), pressures p (Pa), contact loads F (N; None = no column)."""

    h: np.ndarray
    p: np.ndarray
    F: np.ndarray | None = None
    force_column: str | None = None


@dataclass
class FitReport:
    """What fit.json holds of any fit (:data:`FIT_KEYS`): material name, fitted parameters (SI,
    flattened names), 95 % intervals, NRMSD of the pressure (paper eq. 16), the number of points, the
    unidentified directions in words and the correlations; and the geometry r1, t0 (m) it was fitted for,
    the fixed parameters, the data's source and the data and model pressures (Pa) for the plot."""

    material: str
    params: dict
    ci95: dict
    nrmsd: float
    n_points: int
    unidentifiable: list
    correlation: dict
    r1: float
    t0: float
    fixed: dict = field(default_factory=dict)
    source: str = ""
    p_data: np.ndarray = field(default_factory=lambda: np.zeros(0))
    p_model: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def as_json(self) -> dict:
        """fit.json content: exactly :data:`FIT_KEYS`."""
        return {k: getattr(self, k) for k in FIT_KEYS}


@dataclass(kw_only=True)
class FitResult(FitReport):
    """A static fit: the report, the contact and the data heights (m) of the pressures."""

    contact: str
    h: np.ndarray = field(default_factory=lambda: np.zeros(0))
    fidelity: str = "cap"
    #: the bonded disk's radius, m (None for free or flat contact)
    disk_radius: float | None = None
    #: what the fit says beside its numbers (rows kept beyond the law's reach)
    notes: list = field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------------
#: the largest load a static point may carry, per column: a scenario's [load] mass_g range (50 kg)
LOAD_MAX = {"load_g": (50000.0, "g"), "F_n": (50000.0 * 1e-3 * U.G_STD, "N")}

def parse_data(raw: bytes) -> StaticData:
    """Static data from a CSV file's bytes (h_mm, p_kpa, optional F_n or load_g) in SI.

    One ValueError naming the column and the 1-based data row for a bad value; lines starting
    with '#' and blank lines are skipped. A ``t_s`` column (dynamic data) is refused.
    """
    header, rows = data_rows(raw, "h_mm,p_kpa[,F_n|load_g] and data rows")
    if "t_s" in header:
        raise ValueError("data: column 't_s' means a recorded run; read it with "
                         "hbma_ctrl.app.tuning.fit_dynamic.parse_run (static points: h_mm, p_kpa[, F_n|load_g])")
    for col in ("h_mm", "p_kpa"):
        if col not in header:
            hint = did_you_mean(col, header)
            raise ValueError(f"data: missing column '{col}'{hint}; columns: {', '.join(header)}")
    if "F_n" in header and "load_g" in header:
        raise ValueError("data: columns 'F_n' and 'load_g' both given; keep one")
    fcol = "F_n" if "F_n" in header else "load_g" if "load_g" in header else None
    cols = ["h_mm", "p_kpa"] + ([fcol] if fcol else [])
    idx = {c: header.index(c) for c in cols}
    vals = {c: [] for c in cols}
    for row, cells in enumerate(rows, start=1):
        for c in cols:
            cell = cells[idx[c]].strip() if idx[c] < len(cells) else ""
            if cell == "":
                raise ValueError(f"data: column '{c}', row {row}: empty value")
            v = data_number(cell, c, row)
            if v < 0:
                what = {"h_mm": "height", "p_kpa": "pressure"}.get(c, "load")
                raise ValueError(f"data: column '{c}', row {row}: {what} {v:g} is negative")
            if c in LOAD_MAX and v > LOAD_MAX[c][0]:
                most, unit = LOAD_MAX[c]
                raise ValueError(f"data: column '{c}', row {row}: {v:g} {unit} is out of range [0, {most:g}] {unit}")
            if c == "p_kpa" and v > P_KPA_MAX:
                raise ValueError(f"data: column 'p_kpa', row {row}: {v:g} kPa is above {P_KPA_MAX:g} kPa; the "
                                 "values look like Pa: convert them to kPa")
            vals[c].append(v)
    if not vals["h_mm"]:
        raise ValueError("data: no data rows below the header")
    check_height_unit(np.array(vals["h_mm"]), np.array(vals["p_kpa"]), "h_mm")
    F = None
    if fcol == "F_n":
        F = np.array(vals["F_n"])
    elif fcol == "load_g":
        F = U.grams(np.array(vals["load_g"])) * U.G_STD
    return StaticData(U.mm(np.array(vals["h_mm"])), U.kpa(np.array(vals["p_kpa"])), F, fcol)


# ---------------------------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------------------------
def param_names(material: str) -> list[str]:
    """Flattened parameter names of a material ('C0', 'alpha1' for tuple entries)."""
    space = ph.ParamSpace.for_material(make_material(material))
    return space.names[len(ph.BASE_NAMES):]


def unflatten(material: str, values: dict) -> dict:
    """Flattened {name: value} -> make_material keyword arguments (tuples for tuple fields)."""
    space = ph.ParamSpace.for_material(make_material(material))
    return {name: float(values[name]) if n == 0 else [float(values[f"{name}{i}"]) for i in range(n)]
            for name, n in space.material_sizes}


class _Model:
    """Model pressures at the data points for flattened material parameter vectors (SI)."""

    def __init__(self, material: str, r1: float, t0: float, data: StaticData, contact: str,
                 fidelity: str = "cap"):
        mat = make_material(material)
        act = Actuator(r1=r1, t0=t0, material=mat).validate()
        self.space = ph.ParamSpace.for_material(mat)
        theta = self.space.values(act)
        self.base = theta[:len(ph.BASE_NAMES)]
        self.default = theta[len(ph.BASE_NAMES):]
        self.data, self.contact, self.r1 = data, contact, r1
        # the exact law's Function is built once (its table once per material shape, then from the
        # disk cache); every trial value of the modulus enters through theta
        self._exact = (exact_shape_function(self.space, mat, str(Pneumatics().csv_path))
                       if fidelity == "exact" else None)

    def solver(self, values: np.ndarray) -> ShapeSolver:
        theta = np.concatenate([self.base, values])
        return ShapeSolver(self.space, theta, self._exact)

    def shapes(self, values: np.ndarray) -> tuple[ShapeSolver, np.ndarray]:
        """The solver for ``values`` and the cut height h2 (m) of each data point (0 for free points)."""
        solver = self.solver(values)
        h = self.data.h
        h2 = np.zeros_like(h)
        if self.contact != "free" and self.data.F is not None:
            F = self.data.F
            on = F > 0
            if on.any():
                h2[on] = solver.h2_for_force(h[on], F[on])
        return solver, h2

    def pressure(self, values: np.ndarray) -> np.ndarray:
        solver, h2 = self.shapes(values)
        return solver.eval(self.data.h + h2, h2)["p"]

    def check_reach(self, values: np.ndarray) -> None:
        """ValueError naming the first data row whose shape lies beyond the exact law's table (its chart
        height h1 = h + h2 over r1 past :data:`hbma_ctrl.models.exact_tables.RATIO_U`'s end: the table
        would only be continued there)."""
        if self._exact is None:
            return
        _, h2 = self.shapes(values)
        h1 = self.data.h + h2
        top = float(RATIO_U[-1]) * self.r1
        beyond = np.flatnonzero(h1 > top * (1 + 1e-9))
        if beyond.size:
            i = int(beyond[0])
            what = "" if h2[i] == 0 else f" under its load (the contact's chart height {U.to_mm(h1[i]):.3g} mm)"
            raise ValueError(f"data: column 'h_mm', row {i + 1}: {U.to_mm(self.data.h[i]):g} mm{what} is beyond the "
                             f"exact law's table, {RATIO_U[-1]:g} r1 = {U.to_mm(top):g} mm; use --fidelity cap")


def rising(h: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points (h m, p Pa) of a free-inflation curve that a spline from the flat membrane (h = 0) can
    take: finite, above h = 0 and each above every point before it. A shooting that goes astray for some
    trial parameters returns heights at or below zero or a fold back; those points are not the curve."""
    ok = np.isfinite(h) & np.isfinite(p)
    h, p = h[ok], p[ok]
    before = np.maximum.accumulate(np.concatenate([[0.0], h[:-1]])) if h.size else h
    keep = h > before
    return h[keep], p[keep]


class _ExactFree:
    """Free-inflation pressures (Pa) at the data heights from the exact membrane's own solver, for a
    material whose parameters change its shape (the tables cannot follow them): each call solves the
    free curve of those parameters over :data:`EXACT_FREE_POLES` pole stretches and interpolates it
    (a cubic in height, which the curve's 1e-5 to 4 stretch spacing keeps within the solver's 1e-6)."""

    def __init__(self, material: str, r1: float, t0: float, data: StaticData):
        self.material, self.r1, self.t0, self.data = material, r1, t0, data
        self.names = param_names(material)
        self._last: tuple = (None, None)  # (values' bytes, curve): the optimum is asked for several times

    def curve(self, values: np.ndarray):
        """(h m, p Pa) of the free inflation for flattened ``values`` (SI), h increasing; None for
        parameters that are not a valid material."""
        key = np.asarray(values, dtype=float).tobytes()
        if self._last[0] != key:
            self._last = (key, self._solve(values))
        return self._last[1]

    def _solve(self, values: np.ndarray):
        from hbma_ctrl.models.exact import ExactMembrane

        try:
            mat = make_material(self.material, **unflatten(self.material, dict(zip(self.names, values))))
            m = ExactMembrane(mat, self.r1, self.t0)
            lam = 1.0 + np.geomspace(1e-5, 0.999 * (m.lam_hi - 1.0), EXACT_FREE_POLES)
            out = m.free_pole(lam)
        except (ValueError, RuntimeError, FloatingPointError):
            # parameters the material refuses, or a shooting the solver cannot finish: no curve (the
            # fit's residual for it is the penalty, never a traceback)
            return None
        return rising(np.asarray(out["h"], dtype=float), np.asarray(out["p"], dtype=float))

    def pressure(self, values: np.ndarray) -> np.ndarray:
        from scipy.interpolate import CubicSpline

        c = self.curve(values)
        out = np.full(self.data.h.size, np.nan)
        if c is None or c[0].size < 4:
            return out
        h, p = c
        inside = (self.data.h >= 0) & (self.data.h <= h[-1])
        # the membrane is flat at h = 0: the curve starts there
        hh, pp = np.concatenate([[0.0], h]), np.concatenate([[0.0], p])
        out[inside] = CubicSpline(hh, pp)(self.data.h[inside])
        return out

    def reach(self, values: np.ndarray) -> float:
        """The highest free apex height (m) of the curve for ``values`` (0 when it has none)."""
        c = self.curve(values)
        return float(c[0][-1]) if c is not None and c[0].size else 0.0


def model_pressure(material: str, params: dict, r1: float, t0: float, data: StaticData, contact: str,
                   fidelity: str = "cap") -> np.ndarray:
    """Model pressure (Pa) at the data points for flattened parameters (SI), r1, t0 (m), with the cap's
    or the exact membrane's law (``fidelity``)."""
    model = _Model(material, r1, t0, data, contact, fidelity)
    names = param_names(material)
    return model.pressure(np.array([params[n] for n in names], dtype=float))


def _bounds(material: str, names: list[str], default: np.ndarray, data: StaticData, r1: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Physical bounds (SI): positive moduli, Gent Jm above the data's largest I1 - 3."""
    lo = np.full(len(names), -np.inf)
    hi = np.full(len(names), np.inf)
    for i, n in enumerate(names):
        if material == "mr" and n == "C2":
            lo[i] = 0.0
        elif material == "yeoh" and n in ("C1", "C2"):
            pass  # higher Yeoh terms may be negative (softening then stiffening)
        elif material == "gent" and n == "Jm":
            # the free-cap stretch at h is the smallest stretch a point of height h can have (a
            # contact h2 > 0 only stretches more): a lower bound of the data's I1 - 3
            lam2 = (data.h.max() ** 2 + r1 ** 2) / r1 ** 2
            lo[i] = 1.001 * (2 * lam2 + lam2 ** -2 - 3) + 1e-6
            hi[i] = 1e6
        elif material == "ogden" and n.startswith("alpha"):
            lo[i], hi[i] = 0.05, 50.0
        else:  # a modulus: positive (a tiny floor keeps the material valid)
            lo[i] = 1e-9 * abs(default[i])
    return lo, hi


def split_fix(fix: dict | None, names: list[str], what: str, elsewhere=(), why: str = "") -> tuple[dict, list[str]]:
    """``--fix`` values (SI) checked against a fit's parameter ``names``: the fixed ones and the free
    names. ``what``: the fit in words; a name in ``elsewhere`` is explained by ``why``."""
    fixed = {}
    for k, v in (fix or {}).items():
        if k not in names:
            hint = why if k in elsewhere else did_you_mean(k, names)
            raise ValueError(f"--fix {k}: not a parameter of {what}{hint}; allowed: {', '.join(names)}")
        if not math.isfinite(v):
            raise ValueError(f"--fix {k}={v}: not a finite number")
        fixed[k] = float(v)
    free = [n for n in names if n not in fixed]
    if not free:
        raise ValueError("--fix: every parameter is fixed; nothing to fit")
    return fixed, free


def check_options(material: str, contact: str | None, fidelity: str | None) -> None:
    """ValueError naming the flag for an unknown material, contact or fidelity, or one not available
    (``fidelity`` None: not chosen yet)."""
    for flag, value, allowed in (("--fidelity", fidelity, FIDELITIES), ("--contact", contact, CONTACTS),
                                 ("--material", material, tuple(MATERIALS))):
        if value is not None and value not in allowed:
            raise ValueError(f"{flag} {value}{did_you_mean(value, allowed)}; allowed: {', '.join(allowed)}")
    if contact == "bonded" and fidelity == "cap":
        raise ValueError("--contact bonded: the exact membrane's law only (the spherical cap has no glued disk); "
                         "drop --fidelity cap")
    if contact == "bonded" and material not in ("nh", "gent"):
        raise ValueError(f"--contact bonded: fits --material nh or gent only (a modulus that scales the bonded tables, "
                         f"and for gent one shape parameter Jm over a grid of tables); {material}'s "
                         f"{', '.join(param_names(material))} change the shape in more directions")


def check_disk_radius(contact: str | None, disk_radius: float | None, r1: float) -> None:
    """ValueError naming ``--disk-radius-mm`` (in mm) unless it is given exactly with a bonded contact and
    lies inside the clamp, 0 < c < r1 (m)."""
    if contact != "bonded":
        if disk_radius is not None:
            raise ValueError("--disk-radius-mm: only with --contact bonded (the radius of the disk glued at the "
                             "membrane's centre)")
        return
    if disk_radius is None:
        raise ValueError(f"--contact bonded needs --disk-radius-mm: the glued disk's radius, mm, in (0, "
                         f"{U.to_mm(r1):g}) (inside the clamp radius)")
    if not (math.isfinite(disk_radius) and 0 < disk_radius < r1):
        raise ValueError(f"--disk-radius-mm {U.to_mm(disk_radius):g} is out of range (0, {U.to_mm(r1):g}) mm: the "
                         "glued disk lies inside the clamp radius (--r1-mm)")


def exact_shapes_fixed(material: str) -> bool:
    """Whether a material's law has one shape at every parameter value (its one parameter a modulus,
    ``nh``): what the exact membrane's tables, one per material shape, can fit."""
    return len(param_names(material)) == 1 and not MATERIALS[material].dimensionless


def check_exact_material(material: str, flag: str) -> None:
    """ValueError naming ``flag`` when the exact law's tables would have to fit ``material``'s
    parameters (a plate contact or a recorded run: see :func:`exact_shapes_fixed`)."""
    if not exact_shapes_fixed(material):
        names = ", ".join(param_names(material))
        raise ValueError(f"{flag}: the exact membrane fits this for --material nh only (its one modulus scales the "
                         f"exact law's tables, which hold one material shape); {material}'s {names} change the shape, "
                         "a new table at every trial value. Use --fidelity cap; the exact law fits free points of "
                         f"{material} (no force column) and a recorded run's modulus_scale (without --fit-material)")


def resolve_fidelity(fidelity: str | None, material: str, needs_tables: bool = False) -> tuple[str, str | None]:
    """The law a fit uses: ``fidelity`` as given, or for None the roles' default (the exact membrane,
    :data:`hbma_ctrl.models.defaults.DEFAULT_MEMBRANE`) where it can fit the asked parameters, else the
    cap; with a note saying why when the default could not be taken. ``needs_tables``: the fit would
    move a material's shape through the exact law's tables (static points on a plate, a recorded run's
    --fit-material), which only nh's one modulus can do."""
    if fidelity is not None:
        return fidelity, None
    if DEFAULT_MEMBRANE == "exact" and needs_tables and not exact_shapes_fixed(material):
        return "cap", (f"fitted with the cap's law: on a plate or over a recorded run the exact membrane (the roles' "
                       f"default law) fits --material nh only; {material}'s parameters change its shape. Run the "
                       "roles on these numbers with membrane = \"cap\"")
    return DEFAULT_MEMBRANE, None


def fit_static(data: StaticData, material: str, r1: float, t0: float, contact: str | None = None,
               fix: dict | None = None, fidelity: str = "cap", disk_radius: float | None = None,
               cache=None, keep_beyond: bool = False) -> FitResult:
    """Least-squares fit of a material's parameters (SI) to static data; r1, t0 in m.

    ``contact`` None picks 'flat' when the data have a force column, else 'free'; 'bonded' is a disk of
    radius ``disk_radius`` (m) glued at the centre (the exact law, ``nh`` or ``gent``; ``cache``: its tables'
    directory, None the exact tables' one; rows at h = 0 rest on the stop, :mod:`hbma_ctrl.app.tuning.fit_bonded`). ``fix`` holds flattened parameters at SI values.
    ``fidelity``: the membrane law, 'cap' or 'exact' (the tables for ``nh``; the exact solver's free curve,
    refined from the cap's fit, for free points of the other materials; :func:`check_exact_material`).
    ``keep_beyond`` (bonded only): rows beyond the tables at the optimum keep the straight-line continuation
    they were fitted with and are counted in a note, instead of the first being refused.
    ValueError for unavailable options or too few points.
    """
    check_options(material, contact, fidelity)
    check_disk_radius(contact, disk_radius, r1)
    if keep_beyond and contact != "bonded":
        raise ValueError("--keep-beyond-reach: only with --contact bonded")
    notes: list = []
    if contact is None:
        contact = "flat" if data.F is not None else "free"
    # a shape-changing material's exact fit: free points only, through the solver itself
    solver_free = fidelity == "exact" and not exact_shapes_fixed(material) and contact != "bonded"
    if solver_free and contact != "free":
        check_exact_material(material, f"--fidelity exact with --contact {contact}")
    if contact in ("flat", "bonded") and data.F is None:
        raise ValueError(f"data: missing column 'F_n' or 'load_g': --contact {contact} needs the load of each point")
    if contact == "free" and data.F is not None and np.any(data.F > 0):
        row = int(np.argmax(data.F > 0)) + 1
        raise ValueError(f"data: column '{data.force_column}', row {row}: a load with --contact free (free "
                         "inflation carries none); use --contact flat")
    names = param_names(material)
    fixed, free = split_fix(fix, names, f"material '{material}'")
    n = data.h.size
    if n < len(free):
        raise ValueError(f"data: {n} points for {len(free)} free parameters of '{material}' ({', '.join(free)}); "
                         "add points or --fix some")
    span = float(data.p.max() - data.p.min())
    if not span > 0:
        raise ValueError("data: column 'p_kpa' has one value in every row; nothing to fit")
    bonded = contact == "bonded"
    # the model gives the defaults and bounds; the law the pressures
    model = _Model(material, r1, t0, data, contact, "cap" if solver_free or bonded else fidelity)
    lo, hi = _bounds(material, names, model.default, data, r1)
    if bonded and material == "gent":
        from hbma_ctrl.app.tuning.fit_bonded import JM_MIN

        # the bonded tables' grid in 1 / Jm ends at JM_MIN
        lo[names.index("Jm")] = max(lo[names.index("Jm")], JM_MIN)
    for k, v in fixed.items():
        i = names.index(k)
        if not lo[i] <= v <= hi[i]:
            raise ValueError(f"--fix {k}={v:g}: outside the physical range [{lo[i]:g}, {hi[i]:g}] for this data")
    # the law after the options are checked: a bonded fit's first use builds its tables (minutes)
    if bonded:
        from hbma_ctrl.app.tuning.fit_bonded import BondedLaw

        law = BondedLaw(r1, t0, disk_radius, data.h, data.F, cache, material, data.p)
    else:
        law = _ExactFree(material, r1, t0, data) if solver_free else model
    ifree = [names.index(k) for k in free]
    coords = Coordinates.scaled(model.default[ifree])

    def full(z: np.ndarray) -> np.ndarray:
        v = model.default.copy()
        for k, val in fixed.items():
            v[names.index(k)] = val
        v[ifree] = coords.values(z)
        return v

    def resid(z: np.ndarray) -> np.ndarray:
        return finite_residuals((law.pressure(full(z)) - data.p) / span)

    zlo, zhi = coords.coordinates(lo[ifree]), coords.coordinates(hi[ifree])
    dimless = set(MATERIALS[material].dimensionless)
    is_modulus = np.array([names[i].rstrip("0123456789") not in dimless for i in ifree])
    sign = np.where(model.default[ifree] < 0, -1.0, 1.0)
    if solver_free:
        # one solve of the free curve costs 0.1-0.3 s: one start, the cap's optimum (the two laws
        # differ by 5-15 % in pressure, well inside the cap fit's basin)
        cap = fit_static(data, material, r1, t0, contact, fix, "cap")
        starts = [np.clip(coords.coordinates([cap.params[k] for k in free]), zlo, zhi)]
        nfev = _EXACT_NFEV
    else:
        starts = []
        for f in _START_FACTORS:
            # moduli scaled by f, exponents and locking limits at their defaults; then inside the
            # bounds with a margin (Gent's Jm floor from the data may lie above its default)
            z0 = sign * np.where(is_modulus, f, 1.0)
            z0 = np.maximum(z0, np.where(np.isfinite(zlo), 1.5 * zlo + 1e-6, -np.inf))
            starts.append(np.minimum(z0, np.where(np.isfinite(zhi), 0.9 * zhi, np.inf)))
        nfev = 200
    z = solve(resid, starts, (zlo, zhi), method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
              max_nfev=nfev)
    if solver_free:
        top = law.reach(full(z))
        beyond = np.flatnonzero(data.h > top)
        if beyond.size:
            i = int(beyond[0])
            raise ValueError(f"data: column 'h_mm', row {i + 1}: {U.to_mm(data.h[i]):g} mm is beyond the fitted "
                             f"membrane's reach in free inflation ({U.to_mm(top):.4g} mm, pole stretch "
                             "4 or 98 % of the locking one); use --fidelity cap")
    elif keep_beyond:
        notes = law.beyond_note(full(z))
    else:
        law.check_reach(full(z))
    est = estimate(resid, z, (zlo, zhi))
    values = full(z)
    params = {k: float(values[i]) for i, k in enumerate(names)}
    ci, correlation, weak = summary(est, coords, values[ifree], free, "this data",
                                    "fix one with --fix or add points over a wider height range")
    ci.update({k: [params[k], params[k]] for k in fixed})
    pm = law.pressure(values)
    return FitResult(material=material, params=params, ci95={k: ci[k] for k in names},
                     nrmsd=nrmsd(pm, data.p), n_points=n, unidentifiable=weak,
                     correlation=correlation, contact=contact, r1=r1, t0=t0, fixed=fixed, h=data.h.copy(),
                     p_data=data.p.copy(), p_model=pm, fidelity=fidelity, disk_radius=disk_radius, notes=notes)
