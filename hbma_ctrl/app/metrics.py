"""Metrics and edge-unit outputs of a run: NRMSD (paper eq. 16), plant metrics, metrics.json.

Output convention (every CSV this package writes for users): edge units, with the unit in the
column name (``t_s``, ``h_mm``, ``p_kpa``, ``F_n``, ``V_cm3``, ``q_mg_per_s``, ...), see
:data:`EDGE_COLUMNS`. Inside, everything stays SI.

metrics.json holds one object per role under stable keys (:data:`ROLE_KEYS`): "scenario" (what
ran), "plant" (open loop), "estimator", "controller", "robot" (filled by their owners' scenes).
"""

from __future__ import annotations

import csv
import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import LAM_CHECK, Material
from hbma_ctrl.core.physics import pump_reach
from hbma_ctrl.sim.trial import Log

__all__ = ["EDGE_COLUMNS", "ROLE_KEYS", "nrmsd", "plant_metrics", "merge_metrics", "write_metrics",
           "write_log_csv", "edge_series", "json_safe", "physics_problems", "MASS_BALANCE_TOL",
           "PUMP_REACH_TOL"]

#: the largest mass-balance error (relative) of a result that is kept: a consistent scheme keeps
#: it near 1e-10 (rk4) or 1e-3 (euler at its default step); beyond it the step is too coarse
MASS_BALANCE_TOL = 1e-2
#: how far (relative) a chamber's pressure may rise above its pump's full-speed stall pressure: only
#: mechanical work can push it there (a load settling onto the membrane with the valves shut), a
#: small overshoot; a larger excess is a compressor map read past its end, or a model error
PUMP_REACH_TOL = 0.05


def _same(x):
    """Columns already in their edge unit (s, N, duty, stretch)."""
    return x


#: SI log column -> (edge column name, conversion to that unit)
EDGE_COLUMNS = {
    "t": ("t_s", _same),
    "speed": ("speed_pct", U.to_pct),
    "inlet": ("inlet_duty", _same),
    "outlet": ("outlet_duty", _same),
    "h1": ("h1_mm", U.to_mm),
    "h2": ("h2_mm", U.to_mm),
    "h": ("h_mm", U.to_mm),
    "p": ("p_kpa", U.to_kpa),
    "F": ("F_n", _same),
    "q": ("q_mg_per_s", U.to_mg),
    "q_in": ("q_in_mg_per_s", U.to_mg),
    "q_out": ("q_out_mg_per_s", U.to_mg),
    "lam": ("stretch", _same),
    "V": ("V_cm3", U.to_cm3),
    "m": ("m_mg", U.to_mg),
    "det": ("det_si", _same),
    "mode": ("mode", _same),
    "mass_in": ("mass_in_mg", U.to_mg),
}

ROLE_KEYS = ("scenario", "plant", "estimator", "controller", "robot")


def nrmsd(y_hat: np.ndarray, y: np.ndarray) -> float:
    """paper eq. 16: sqrt(mean((y_hat - y)^2)) / (max(y) - min(y)), y the reference.

    NaN when the reference is constant (the ratio is undefined) or the inputs are empty.
    """
    y_hat, y = np.asarray(y_hat, float), np.asarray(y, float)
    if y.size == 0 or y_hat.shape != y.shape:
        raise ValueError(f"nrmsd: need two series of the same non-zero length, got {y_hat.shape} and {y.shape}")
    span = float(y.max() - y.min())
    if not span > 0:
        return float("nan")
    return float(np.sqrt(np.mean((y_hat - y) ** 2)) / span)


def edge_series(log: Log) -> dict[str, np.ndarray]:
    """The log's columns in edge units, keyed by their edge names (unknown columns kept as is)."""
    out = {}
    for k, v in log.data.items():
        name, conv = EDGE_COLUMNS.get(k, (k, _same))
        out[name] = conv(np.asarray(v, float))
    return out


def write_log_csv(log: Log, path: Path | str) -> None:
    """Write a log as CSV in edge units (unit in each column name) plus an 'event' column."""
    cols = edge_series(log)
    t = log.data["t"]
    ev: dict[int, str] = {}
    for te, name in log.events:
        i = int(np.argmin(np.abs(t - te)))
        ev[i] = f"{ev[i]};{name}" if i in ev else name
    keys = list(cols)
    n = len(t)
    # every number formatted by one %-operation over the whole table (C-level; a per-value f-string
    # made the protocol's 150 logs a quarter of its run): the same text csv.writer wrote, CRLF rows
    row = ",".join(["%.9g"] * len(keys)) + ",\r\n"
    table = np.column_stack([np.asarray(cols[k], dtype=float).reshape(-1)[:n] for k in keys]) if keys else np.zeros((n, 0))
    lines = ((row * n) % tuple(table.ravel().tolist())).split("\r\n")[:n]
    for i, name in ev.items():
        lines[i] += _csv_field(name)
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerow(keys + ["event"])
        if n:
            fh.write("\r\n".join(lines) + "\r\n")


def _csv_field(s: str) -> str:
    """One CSV field as csv.writer quotes it (minimal quoting)."""
    return '"' + s.replace('"', '""') + '"' if any(c in s for c in ',"\r\n') else s


def _peak(log: Log, key: str) -> float:
    """The largest value of ``key`` over the whole simulation (every step when the simulator kept
    it, else the logged rows)."""
    rows = float(log[key].max())
    return max(rows, float(log.peaks[key])) if key in log.peaks else rows


def _mass_balance(log: Log) -> float | None:
    """max |m - m0 - mass_in| / max |m| over the run (None for an empty log)."""
    m = log["m"]
    if not m.size:
        return None
    return float(np.max(np.abs(m - m[0] - log["mass_in"])) / max(float(np.max(np.abs(m))), 1e-30))


def physics_problems(log: Log, material: Material, compressor_csv: Path | str | None = None) -> list[str]:
    """Why a finished run's result is not physical, one line each ([] when none): gas made or lost by
    the integrator (mass balance beyond :data:`MASS_BALANCE_TOL`), a stretch beyond the material's
    locking stretch or beyond :data:`~hbma_ctrl.core.materials.LAM_CHECK`, the range the laws are
    checked over, and (given the run's compressor map) a pressure beyond what its pump reaches at full
    speed by more than :data:`PUMP_REACH_TOL`. A diverged run already says what went wrong: nothing is
    added to it."""
    if log.status == "diverged":
        return []
    out = []
    if compressor_csv is not None and "p" in log.data and log["p"].size:
        reach, stalls = pump_reach(compressor_csv)
        p = _peak(log, "p")
        if not p <= reach * (1.0 + PUMP_REACH_TOL):
            out.append(f"the chamber pressure reached {U.to_kpa(p):.4g} kPa, above the {U.to_kpa(reach):.4g} kPa "
                       + ("the pump stalls at (full speed)" if stalls else
                          "where its compressor map ends while still delivering flow (read past as constant): "
                          "extend [pneumatics] compressor_csv to the pressure the pump stalls at"))
    bal = _mass_balance(log)
    if bal is not None and not bal <= MASS_BALANCE_TOL:
        out.append(f"the gas mass balance is off by {bal:.3g} of the chamber's mass (at most "
                   f"{MASS_BALANCE_TOL:g}): the step is too coarse for the integrator; use rk4 or a smaller [sim] dt_ms")
    lam = _peak(log, "lam") if log["lam"].size else 1.0
    lock = material.lam_max()  # a root solve for a locking material: once
    limit = min(LAM_CHECK, lock)
    if not lam <= limit:
        what = "its locking stretch" if lock <= LAM_CHECK else "the range the material laws are checked over"
        out.append(f"the membrane's stretch reached {lam:.3g}, beyond {limit:.3g} ({what})")
    return out


def plant_metrics(logs: list[Log]) -> dict:
    """Open-loop metrics of one or more logs (edge units): peaks (over every simulation step, not the
    decimated log), status, event counts, wall time.

    mass_balance_rel: max |m - m0 - mass_in| / max(m) over the run (the integrator's mass
    conservation; ~1e-12 for a consistent scheme).
    """
    if not logs:
        raise ValueError("plant_metrics: no logs")
    events = Counter(name.split(":")[0] for log in logs for _, name in log.events)
    status = Counter(log.status for log in logs)
    bal = [b for b in map(_mass_balance, logs) if b is not None]
    out = {
        "n_trials": len(logs),
        "fidelity": sorted({log.fidelity for log in logs}),
        "status": logs[0].status if len(logs) == 1 else dict(status),
        "max_height_mm": float(U.to_mm(max(_peak(log, "h") for log in logs))),
        "max_pressure_kpa": float(U.to_kpa(max(_peak(log, "p") for log in logs))),
        "max_force_n": float(max(_peak(log, "F") for log in logs)),
        "final_height_mm": float(U.to_mm(logs[0]["h"][-1])) if len(logs) == 1 else None,
        "events": dict(events),
        "wall_s": float(sum(log.wall_s for log in logs)),
        "mass_balance_rel": max(bal) if bal else None,
    }
    if len(logs) == 1:
        out["fidelity"] = logs[0].fidelity
    else:
        out.pop("final_height_mm")
    return out


def json_safe(obj):
    """JSON-safe copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def merge_metrics(*parts: dict) -> dict:
    """Merge role dicts into one metrics object; a role key given twice is merged key by key.

    Top-level keys must be role keys (:data:`ROLE_KEYS`) so that consumers can rely on them.
    """
    out: dict = {}
    for part in parts:
        if not part:
            continue
        if not isinstance(part, dict):
            raise ValueError(f"metrics: a role must return a dict, got {type(part).__name__}")
        for key, val in part.items():
            if key not in ROLE_KEYS:
                raise ValueError(f"metrics: unknown role key '{key}'; allowed: {', '.join(ROLE_KEYS)}")
            if key in out and isinstance(out[key], dict) and isinstance(val, dict):
                out[key] = {**out[key], **val}
            else:
                out[key] = val
    return {k: out[k] for k in ROLE_KEYS if k in out}


def write_metrics(metrics: dict, path: Path | str) -> None:
    """Write metrics.json (sorted role order, NaN/inf as null)."""
    Path(path).write_text(json.dumps(json_safe(metrics), indent=2) + "\n")
