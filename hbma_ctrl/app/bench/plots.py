"""Pareto plots of the benchmarks (PNG, matplotlib without pyplot): cost against accuracy, one point per
setting, the non-dominated ones joined.

- :func:`sim_pareto_png` the simulator (``hbma-ctrl bench sim``): wall time of the protocol against the
  height and pressure NRMSD versus the exact membrane, one point per fidelity x integrator x step.
- :func:`pareto_png` any list of (label, group, cost, error) points;
  :func:`estimator_pareto_png` (``bench ekf`` JSON: step time vs height NRMSD per filter) and
  :func:`controller_pareto_png` (``bench mpc`` JSON: solve time vs height RMSE per controller x horizon)
  read them from those benches' results.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

__all__ = ["pareto_front", "pareto_png", "sim_pareto_png", "estimator_pareto_png", "controller_pareto_png",
           "estimator_points", "controller_points"]

_MARKERS = {"rk4": "o", "euler": "s", "radau": "^"}


def pareto_front(cost, error) -> np.ndarray:
    """Indices of the non-dominated points (no other point is both cheaper and more accurate), by cost."""
    cost, error = np.asarray(cost, dtype=float), np.asarray(error, dtype=float)
    ok = np.flatnonzero(np.isfinite(cost) & np.isfinite(error))
    front, best = [], np.inf
    for i in ok[np.lexsort((error[ok], cost[ok]))]:
        if error[i] < best:
            front.append(int(i))
            best = error[i]
    return np.array(front, dtype=int)


def _panel(ax, labels, groups, cost, error, xlabel: str, ylabel: str, markers=None, on_front=None) -> None:
    cost, error = np.asarray(cost, dtype=float), np.asarray(error, dtype=float)
    # an exact zero (a setting scored against itself) cannot sit on a log axis: drawn at the floor
    pos = error[np.isfinite(error) & (error > 0)]
    floor = pos.min() / 3 if pos.size else 1e-9
    shown = np.where(error > 0, error, floor)
    colours = {}
    for i, (lab, grp) in enumerate(zip(labels, groups)):
        if not (np.isfinite(cost[i]) and np.isfinite(error[i])):
            continue
        colours.setdefault(grp[0], f"C{len(colours)}")
        ax.scatter(cost[i], shown[i], color=colours[grp[0]], marker=(markers or {}).get(grp[1], "o"), s=36,
                   label=" ".join(g for g in grp if g), zorder=3)
        ax.annotate(lab, (cost[i], shown[i]), textcoords="offset points", xytext=(4, 3), fontsize=7)
    # points on another set of cases (e.g. the free rung's 0 g trials) are shown but not on the front
    f = pareto_front(cost, np.where(on_front if on_front is not None else True, shown, np.nan))
    if f.size > 1:
        ax.plot(cost[f], shown[f], color="0.5", lw=1, ls="--", zorder=2, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    handles, names = ax.get_legend_handles_labels()
    seen = {}
    for h, n in zip(handles, names):
        seen.setdefault(n, h)
    ax.legend(list(seen.values()), list(seen), fontsize=7)


def pareto_png(points: list[tuple], path: Path | str, xlabel: str, ylabel: str, title: str = "") -> Path:
    """One panel of (label, group, cost, error) points -> PNG at path; group is a (colour, marker) pair of names."""
    fig = Figure(figsize=(6.5, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    _panel(ax, [p[0] for p in points], [p[1] for p in points], [p[2] for p in points], [p[3] for p in points],
           xlabel, ylabel)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return Path(path)


def sim_pareto_png(rows, path: Path | str, title: str = "") -> Path:
    """``bench sim`` rows -> PNG: wall time (s) against mean height (left) and pressure (right) NRMSD versus the
    exact membrane, colour the fidelity, marker the integrator, label the step (ms; 'def' = the default)."""
    labels = [("def" if r.dt_ms is None else f"{r.dt_ms:g}") for r in rows]
    groups = [(r.fidelity + (" (0 g)" if r.fidelity == "free" else ""), r.integrator) for r in rows]
    wall = [r.wall_s for r in rows]
    fig = Figure(figsize=(12, 4.8))
    for k, (key, name) in enumerate((("height_nrmsd_vs_exact_mean", "height"),
                                     ("pressure_nrmsd_vs_exact_mean", "pressure"))):
        ax = fig.add_subplot(1, 2, k + 1)
        _panel(ax, labels, groups, wall, [getattr(r, key) for r in rows], "wall time of the protocol (s)",
               f"{name} NRMSD vs exact membrane (mean)", _MARKERS,
               on_front=np.array([r.fidelity != "free" for r in rows]))
    fig.suptitle(title + " (free: its 0 g trials only; exact: its own step error)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return Path(path)


def _load_json(path: Path | str, what: str, key: str, kind: type, bench: str) -> tuple[dict, list | dict]:
    """A bench's JSON result and its entry ``key``, a non-empty ``kind``; ValueError naming the flag
    ``what`` when the file is missing, not JSON or not a ``bench`` result."""
    import json

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{what}: no file {p}")
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{what}: {p} is not JSON ({e.msg}, line {e.lineno})") from None
    part = data.get(key) if isinstance(data, dict) else None
    if not isinstance(part, kind) or not part:
        raise ValueError(f"{what}: {path} has no '{key}' (is it a bench {bench} result?)")
    return data, part


def estimator_points(bench_ekf_json: Path | str) -> tuple[list[tuple], str]:
    """``bench ekf`` JSON (its "filters": name -> metrics) -> ((label, group, step us, height NRMSD) points,
    title); ValueError naming ``--ekf-json`` when the file is missing or not such a result."""
    data, filters = _load_json(bench_ekf_json, "--ekf-json", "filters", dict, "ekf")
    pts = []
    for name, m in filters.items():
        fam, _, sub = name.partition(" ")
        # filterpy's row starts from each trial's true load (it has no lift-off logic): say so on the plot
        label = (sub or name) + (" (told the load)" if fam == "filterpy" else "")
        pts.append((label, (fam, ""), float(m.get("step_us_median", np.nan)), float(m.get("height_nrmsd", np.nan))))
    n = data.get("settings", {}).get("n_trials", "?")
    return pts, f"estimator: {Path(bench_ekf_json).name}, {n} trials"


def controller_points(bench_mpc_json: Path | str) -> tuple[list[tuple], str]:
    """``bench mpc`` JSON (its "rows", each a controller "name N=k") -> ((label, group, solve ms, height RMSE mm)
    points, title); ValueError naming ``--mpc-json`` when the file is missing or not such a result."""
    _, rows = _load_json(bench_mpc_json, "--mpc-json", "rows", list, "mpc")
    pts = []
    for r in rows:
        fam, _, hor = str(r.get("controller", "?")).partition(" ")
        pts.append((hor or fam, (fam, ""), float(r.get("solve_ms_median", np.nan)), float(r.get("height_rmse_mm", np.nan))))
    return pts, f"controller: {Path(bench_mpc_json).name}"


def estimator_pareto_png(bench_ekf_json: Path | str, path: Path | str) -> Path:
    """Estimator Pareto PNG (median filter step in us vs height NRMSD, one point per filter) from ``bench ekf`` JSON."""
    pts, title = estimator_points(bench_ekf_json)
    return pareto_png(pts, path, "median filter step (us)", "height NRMSD (mean over trials)", title)


def controller_pareto_png(bench_mpc_json: Path | str, path: Path | str) -> Path:
    """Controller Pareto PNG (median solve in ms vs height RMSE in mm, per controller x horizon) from ``bench mpc`` JSON."""
    pts, title = controller_points(bench_mpc_json)
    return pareto_png(pts, path, "median solve time (ms)", "height RMSE (mm)", title)
