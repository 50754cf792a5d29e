"""Tables of the exact membrane (:mod:`hbma_ctrl.models.exact`), cached on disk, for the simulator to step at
table speed (SI).

- :func:`tabulate`: free inflation over apex heights, or a (h, p) grid of plate/disk contact, as solved.
- :func:`contact_ratio_table`: the exact flat-plate contact in the spherical cap's own chart (h1, h2)
  (docs/concepts/model.md §1), stored as the ratios of the exact pressure and membrane volume to the cap's.
  Why this chart: the cap's quasi-static and platform models (:mod:`hbma_ctrl.models.fidelity`) carry
  (h1, h2) with the gas mass and solve G(h1, h2) = m R T and F(h1, h2) = W; with the same chart and
  contact radius the exact law drops into the same ODEs, lift-off, touch-down and rest logic. Each
  node (u = h1/r1, s = h2/h1) is the exact equilibrium at plate height h = h1 - h2 whose contact radius
  is the cap's ``a^2 = h2 ((h1^2 + r1^2)/h1 - h2)``: so F = p pi a^2 keeps the cap's closed form and
  goes to 0 as the plate leaves (s -> 0, where the node is the exact free inflation), and the ratios
  stay bounded where p and V themselves vanish (the flat corner s -> 1, the origin u -> 0).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

try:  # a build's lock (POSIX); elsewhere two processes may build the same table, each storing it whole
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.codegen import cache_dir
from hbma_ctrl.models.exact import ExactMembrane

__all__ = ["tabulate", "table_cache_dir", "contact_ratio_table", "cap_pv", "solve_chart", "RATIO_U", "RATIO_S"]

#: nodes of the contact ratio table: u = h1/r1 (the cap's virtual apex over r1) and s = h2/h1
RATIO_U = np.concatenate([np.linspace(0.05, 1.0, 20), np.linspace(1.1, 1.6, 6)])
# s is spaced evenly in sqrt(s) (the contact radius grows like sqrt(h2) as the plate starts to press:
# the ratios are smooth in sqrt(s), not in s)
RATIO_S = np.linspace(0.0, np.sqrt(0.97), 23) ** 2
_SOURCES = (Path(__file__), Path(__file__).with_name("exact.py"))


def table_cache_dir() -> Path:
    """Directory of cached exact-membrane tables: ``$HBMA_CTRL_CACHE/exact`` (default ~/.cache/hbma-ctrl/exact)."""
    return cache_dir() / "exact"


def _key(m: ExactMembrane, kind: str, grids: dict) -> str:
    src = b"".join(p.read_bytes() for p in _SOURCES)
    blob = json.dumps({"kind": kind, "material": type(m.material).__name__, "params": m.material.as_dict(),
                       "r1": m.r1, "t0": m.t0, "contact": m.contact_type, "c": m.c, "n": m.n_steps,
                       "grids": {k: np.asarray(v, dtype=float).tolist() for k, v in grids.items()}},
                      sort_keys=True, default=list).encode()
    return hashlib.sha256(blob + hashlib.sha256(src).digest()).hexdigest()[:20]


def _read(path: Path) -> dict | None:
    """A stored table (build_s 0), or None when there is none."""
    if not path.exists():
        return None
    with np.load(path) as z:
        out = {k: z[k] for k in z.files}
    out.update(build_s=0.0, path=path)
    return out


def _cached(path: Path, build) -> dict:
    """The table at ``path``, built by ``build()`` and stored there when missing. A build holds a lock
    beside the file (POSIX ``flock``): another process that needs the same table meanwhile (a test
    worker, a second fit) waits for it and reads it instead of solving the same minutes again."""
    out = _read(path)
    if out is not None:
        return out
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".lock"), "w") as lock:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, the process's end included
        out = _read(path)  # built by the process this one waited for
        if out is not None:
            return out
        t = time.perf_counter()
        out = build()
        dt = time.perf_counter() - t
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **out)
        tmp.replace(path)
    out.update(build_s=dt, path=path)
    return out


def tabulate(m: ExactMembrane, h, p=None, cache: Path | str | None = None) -> dict:
    """Tables of one membrane, cached on disk (npz keyed by a hash of every input and the modules' source).

    Free inflation (``p`` None): over apex heights h (m, increasing) -> p (Pa), V (m^3), lam0, U (J).
    Contact (``p`` given, Pa): over the grid h x p -> F (N), a_contact (m), V (m^3) as (len(h), len(p))
    arrays; for a flat plate, points the plate does not touch hold F = 0, a_contact = 0 and the free V.
    Returns also ``build_s`` (s, the build's wall time, 0 when read from the cache) and ``path``.
    ``cache``: a directory (default :func:`table_cache_dir`).
    """
    h = np.asarray(h, dtype=float)
    grids = {"h": h} if p is None else {"h": h, "p": np.asarray(p, dtype=float)}
    if h.ndim != 1 or h.size < 2 or not np.all(np.diff(h) > 0) or h[0] <= 0:
        raise ValueError("h: the grid must be a 1-D increasing array of heights > 0 m")
    folder = Path(cache) if cache is not None else table_cache_dir()
    path = folder / f"{'free' if p is None else m.contact_type}_{_key(m, 'table', grids)}.npz"

    def build():
        out = _free_table(m, h) if p is None else _contact_table(m, h, grids["p"])
        out["h"] = h
        return out

    return _cached(path, build)


def _free_table(m: ExactMembrane, h: np.ndarray) -> dict:
    # a dense pole-stretch sweep (vectorised), then monotone interpolation of lam0(h), then one exact
    # solve per node at its interpolated stretch polished by a secant in lam0
    lam = np.linspace(1.0 + 1e-4, m.lam_hi, 160)
    sweep = m.free_pole(lam)
    if h[-1] > sweep["h"][-1]:
        raise ValueError(f"h: the grid reaches {h[-1] * 1e3:g} mm, beyond the membrane's reach "
                         f"{sweep['h'][-1] * 1e3:.4g} mm")
    lam_h = np.interp(h, sweep["h"], lam)
    prev, h_prev = None, None
    for _ in range(8):  # vectorised secant in lam0, started from the sweep's interpolation
        got = m.free_pole(lam_h)
        if prev is None:
            slope = np.interp(lam_h, lam, np.gradient(sweep["h"], lam))
        else:
            dl = lam_h - prev
            slope = np.where(np.abs(dl) > 1e-15, (got["h"] - h_prev) / np.where(dl == 0, 1, dl), 1.0)
        prev, h_prev = lam_h, got["h"]
        step = np.where(np.abs(got["h"] - h) > 1e-13 * m.r1, (got["h"] - h) / slope, 0.0)
        lam_h = np.clip(lam_h - step, 1.0 + 1e-12, m.lam_hi)
        if np.max(np.abs(got["h"] - h)) < 1e-12 * m.r1:
            break
    got = m.free_pole(lam_h)
    return {"p": got["p"], "V": got["V"], "U": got["U"], "lam0": lam_h, "h_err": got["h"] - h}


def _contact_table(m: ExactMembrane, h: np.ndarray, p: np.ndarray) -> dict:
    shape = (h.size, p.size)
    F, a, V = np.zeros(shape), np.zeros(shape), np.full(shape, np.nan)
    for j, pj in enumerate(p):
        for i, hi in enumerate(h):
            try:
                r = m.contact(hi, pj)
            except ValueError:
                if m.contact_type == "flat":
                    continue  # the plate does not touch the membrane: no force
                raise
            F[i, j], a[i, j], V[i, j] = r["F"], r["a_contact"], r["V"]
    return {"F": F, "a_contact": a, "V": V, "p": p}


# ------------------------------------------------------------------------- contact in the cap's chart
def cap_pv(m: ExactMembrane, u, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cap's (p in Pa, membrane volume above the clamp in m^3, contact radius over r1) at u = h1/r1,
    s = h2/h1 (arrays), for the membrane's material, r1 and t0 (docs/concepts/model.md §1, §3)."""
    u, s = np.asarray(u, dtype=float), np.asarray(s, dtype=float)
    P = {"r1": m.r1, "t0": m.t0, "V0": 0.0, "material": m.material}
    h1, h2 = u * m.r1, s * u * m.r1
    p = np.array([float(ph.pressure(a, b, P)) for a, b in zip(h1.ravel(), h2.ravel())]).reshape(u.shape)
    V = np.array([float(ph.geometry(a, b, P)["V"]) for a, b in zip(h1.ravel(), h2.ravel())]).reshape(u.shape)
    alpha = np.sqrt(s * (1.0 + u * u * (1.0 - s)))
    return p, V, alpha


def _chart_residual(m: ExactMembrane, lam, P, alpha, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clamp miss rho(r1)/r1 - 1 and height miss (h - x)/r1 of a plate start (lam0, contact radius alpha r1)
    at dimensionless pressure P; NaN where the march broke down or the membrane went slack."""
    tr = m._plate_shoot(lam, alpha / lam, P)
    bad = ~np.isfinite(tr[8]) | (tr[6] <= 0) | (tr[7] <= 0.2) | (tr[9] <= 0) | (tr[10] < 0)
    r = np.vstack([tr[1] - 1.0, -tr[3] - x])
    r[:, bad] = np.nan
    return r, tr


def solve_chart(m: ExactMembrane, x, alpha, lam, P, iters: int = 40, tol: float = 1e-11):
    """Exact flat-plate equilibria with the plate at height x r1 and contact radius alpha r1 (arrays):
    damped Newton (finite-difference Jacobian, vectorised over the points) on (lam0, P) from the guesses
    lam, P (P = p r1 / (mu t0)). Returns lam0, P, V / r1^3 and a mask of the converged points."""
    x, alpha = np.asarray(x, dtype=float), np.asarray(alpha, dtype=float)
    lam, P = np.array(lam, dtype=float), np.array(P, dtype=float)
    ok = np.zeros(x.size, dtype=bool)
    for _ in range(iters):
        r, tr = _chart_residual(m, lam, P, alpha, x)
        err = np.max(np.abs(r), axis=0)
        ok = np.isfinite(err) & (err < tol)
        if ok.all():
            break
        dl, dP = 1e-7 * lam, 1e-7 * np.maximum(P, 1e-4)
        rl, _ = _chart_residual(m, lam + dl, P, alpha, x)
        rp, _ = _chart_residual(m, lam, P + dP, alpha, x)
        J11, J21 = (rl[0] - r[0]) / dl, (rl[1] - r[1]) / dl
        J12, J22 = (rp[0] - r[0]) / dP, (rp[1] - r[1]) / dP
        det = J11 * J22 - J12 * J21
        d_l = (J22 * r[0] - J12 * r[1]) / det
        d_P = (-J21 * r[0] + J11 * r[1]) / det
        # damped: the stretch stays above 1 and the pressure positive
        step = np.minimum(1.0, np.minimum(0.3 * (lam - 1.0) / np.maximum(np.abs(d_l), 1e-300),
                                          0.5 * P / np.maximum(np.abs(d_P), 1e-300)))
        move = ~ok & np.isfinite(d_l) & np.isfinite(d_P)
        lam = np.where(move, lam - step * d_l, lam)
        P = np.where(move, P - step * d_P, P)
    r, tr = _chart_residual(m, lam, P, alpha, x)
    ok = np.isfinite(r).all(axis=0) & (np.max(np.abs(r), axis=0) < 1e-9)
    return lam, P, tr[4], ok


def _ratio_table(m: ExactMembrane, u: np.ndarray, s: np.ndarray) -> dict:
    free = _free_table(m, u * m.r1)
    scale = m._pscale
    Rp, Rv, L0 = (np.full((u.size, s.size), np.nan) for _ in range(3))
    p_cap, v_cap, _ = cap_pv(m, u, np.zeros_like(u))
    Rp[:, 0], Rv[:, 0], L0[:, 0] = free["p"] / p_cap, free["V"] / v_cap, free["lam0"]
    lam, P = free["lam0"].copy(), free["p"] / scale
    prev = None
    for j in range(1, s.size):
        sj = np.full(u.size, s[j])
        p_cap, v_cap, alpha = cap_pv(m, u, sj)
        x = u * (1.0 - s[j])
        if prev is not None:  # linear extrapolation of the continuation
            w = (s[j] - s[j - 1]) / (s[j - 1] - s[j - 2])
            lam_g, P_g = lam + w * (lam - prev[0]), P * (P / prev[1]) ** w
            lam_g = np.where(lam_g > 1.0 + 1e-9, lam_g, lam)
        else:
            lam_g, P_g = lam, P
        lam_n, P_n, vn, ok = solve_chart(m, x, alpha, lam_g, P_g)
        if not ok.all():  # retry from the previous node itself
            l2, P2, v2, ok2 = solve_chart(m, x, alpha, lam, P)
            lam_n, P_n, vn = np.where(ok2, l2, lam_n), np.where(ok2, P2, P_n), np.where(ok2, v2, vn)
            ok = ok | ok2
        if not ok.all():
            bad = ", ".join(f"u {a:g}" for a in u[~ok])
            raise RuntimeError(f"exact contact table: no equilibrium at s = h2/h1 = {s[j]:g} for {bad}")
        prev = (lam, P)
        lam, P = lam_n, P_n
        Rp[:, j], Rv[:, j], L0[:, j] = P * scale / p_cap, vn * m.r1**3 / v_cap, lam
    return {"u": u, "s": s, "Rp": Rp, "Rv": Rv, "lam0": L0}


def contact_ratio_table(m: ExactMembrane, u=None, s=None, cache: Path | str | None = None) -> dict:
    """The exact flat-plate contact over the cap's chart (module docstring), cached on disk.

    u = h1/r1 (increasing, > 0) and s = h2/h1 (increasing, from 0, < 1) are the nodes (default
    :data:`RATIO_U`, :data:`RATIO_S`). Returns u, s and (len(u), len(s)) arrays: Rp = p_exact / p_cap,
    Rv = V_exact / V_cap (membrane volumes above the clamp plane) and lam0 (the stretch on the plate;
    the pole's at s = 0), plus build_s (s) and path. The ratios depend on the material's shape only:
    any r1, t0 and modulus scale give the same table.
    """
    if m.contact_type != "flat":
        raise ValueError("contact_ratio_table: only a flat plate is tabulated in the cap's chart")
    u = RATIO_U if u is None else np.asarray(u, dtype=float)
    s = RATIO_S if s is None else np.asarray(s, dtype=float)
    if u.ndim != 1 or u.size < 4 or u[0] <= 0 or not np.all(np.diff(u) > 0):
        raise ValueError("u: the grid must be a 1-D increasing array of h1/r1 > 0 with >= 4 nodes")
    if s.ndim != 1 or s.size < 4 or s[0] != 0 or s[-1] >= 1 or not np.all(np.diff(s) > 0):
        raise ValueError("s: the grid must be a 1-D increasing array of h2/h1 from 0, below 1, with >= 4 nodes")
    folder = Path(cache) if cache is not None else table_cache_dir()
    path = folder / f"ratio_{_key(m, 'ratio', {'u': u, 's': s})}.npz"
    return _cached(path, lambda: _ratio_table(m, u, s))
