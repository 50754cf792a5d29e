"""Pareto plots of the benchmarks (PNG, matplotlib without pyplot): cost against accuracy, one point per
setting, the non-dominated ones joined.

- :func:`sim_pareto_png` the simulator (``hbma-ctrl bench sim``): wall time of the protocol against the
  height and pressure NRMSD versus the exact membrane, one point per fidelity x integrator x step.
- :func:`pareto_figure` panels of (label, group, cost, error) points sharing the cost axis, the
  non-dominated points ringed; :func:`save_figure` writes it as PNG (and SVG);
- :func:`pareto_png` one panel of such points;
  :func:`estimator_pareto_png` (``bench ekf`` JSON: step time vs height NRMSD per filter) and
  :func:`controller_pareto_png` (``bench mpc`` JSON: solve time vs height RMSE per controller x horizon)
  read them from those benches' results.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

__all__ = ["pareto_front", "pareto_figure", "save_figure", "pareto_png", "sim_panels", "sim_pareto_png",
           "estimator_pareto_png", "controller_pareto_png", "estimator_points", "controller_points",
           "estimator_result_points", "controller_result_points"]

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
    if f.size:
        ax.scatter(cost[f], shown[f], s=120, facecolors="none", edgecolors="k", linewidths=1, zorder=4,
                   label="non-dominated")
    # a log axis where the points span a decade or more; inside one its labels say little
    ok = np.isfinite(cost) & np.isfinite(error)
    for values, set_scale in ((cost[ok], ax.set_xscale), (shown[ok], ax.set_yscale)):
        if values.size and values.min() > 0 and values.max() / values.min() >= 10:
            set_scale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    handles, names = ax.get_legend_handles_labels()
    seen = {}
    for h, n in zip(handles, names):
        seen.setdefault(n, h)
    ax.legend(list(seen.values()), list(seen), fontsize=7)


def pareto_figure(panels: list[tuple[str, list[tuple]]], xlabel: str, title: str = "", markers=None) -> Figure:
    """Side-by-side panels sharing the cost axis ``xlabel``: each (ylabel, points), a point (label, group,
    cost, error[, on_front]) with group a (colour, marker) pair of names; a point with on_front False is
    drawn but not on the front (e.g. one scored on another set of cases)."""
    fig = Figure(figsize=(6.5 * len(panels), 4.5))
    for k, (ylabel, pts) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        _panel(ax, [p[0] for p in pts], [p[1] for p in pts], [p[2] for p in pts], [p[3] for p in pts], xlabel,
               ylabel, markers, on_front=np.array([bool(p[4]) if len(p) > 4 else True for p in pts]))
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def save_figure(fig: Figure, png: Path | str, dpi: int = 120, svg: bool = False) -> list[Path]:
    """``fig`` as PNG at ``png`` (``dpi``) and, with ``svg``, beside it as SVG (text kept as text: small);
    the files written."""
    import matplotlib

    png = Path(png)
    fig.savefig(png, dpi=dpi)
    if not svg:
        return [png]
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "hbma-ctrl"}):
        fig.savefig(png.with_suffix(".svg"), format="svg", metadata={"Date": None})
    return [png, png.with_suffix(".svg")]


def pareto_png(points: list[tuple], path: Path | str, xlabel: str, ylabel: str, title: str = "") -> Path:
    """One panel of (label, group, cost, error) points -> PNG at path; group is a (colour, marker) pair of names."""
    return save_figure(pareto_figure([(ylabel, points)], xlabel, title), path)[0]


def sim_panels(rows) -> list[tuple[str, list[tuple]]]:
    """``bench sim`` rows -> two panels (height, pressure) of (step label, (fidelity, integrator), wall s,
    mean NRMSD vs the exact membrane, on the front) points; the step label is in ms, 'def' = the default;
    the free rung (its 0 g trials only) is off the front."""
    panels = []
    for key, name in (("height_nrmsd_vs_exact_mean", "height"), ("pressure_nrmsd_vs_exact_mean", "pressure")):
        panels.append((f"{name} NRMSD vs exact membrane, mean (-)",
                       [("def" if r.dt_ms is None else f"{r.dt_ms:g}",
                         (r.fidelity + (" (0 g)" if r.fidelity == "free" else ""), r.integrator), r.wall_s,
                         getattr(r, key), r.fidelity != "free") for r in rows]))
    return panels


def sim_pareto_png(rows, path: Path | str, title: str = "") -> Path:
    """``bench sim`` rows -> PNG: wall time (s) against mean height (left) and pressure (right) NRMSD versus the
    exact membrane (:func:`sim_panels`), colour the fidelity, marker the integrator, label the step."""
    fig = pareto_figure(sim_panels(rows), "wall time of the protocol (s)",
                        title + " (free: its 0 g trials only; exact: its own step error)", _MARKERS)
    return save_figure(fig, path)[0]


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
    data, _ = _load_json(bench_ekf_json, "--ekf-json", "filters", dict, "ekf")
    n = data.get("settings", {}).get("n_trials", "?")
    return estimator_result_points(data), f"estimator: {Path(bench_ekf_json).name}, {n} trials"


def estimator_result_points(data: dict) -> list[tuple]:
    """``bench ekf`` result (its "filters": name -> metrics) -> (label, group, step us, height NRMSD) points."""
    pts = []
    for name, m in data["filters"].items():
        fam, _, sub = name.partition(" ")
        # filterpy's row starts from each trial's true load (it has no lift-off logic): say so on the plot
        label = (sub or name) + (" (told the load)" if fam == "filterpy" else "")
        pts.append((label, (fam, ""), float(m.get("step_us_median", np.nan)), float(m.get("height_nrmsd", np.nan))))
    return pts


def controller_points(bench_mpc_json: Path | str) -> tuple[list[tuple], str]:
    """``bench mpc`` JSON (its "rows", each a controller "name N=k") -> ((label, group, solve ms, height RMSE mm)
    points, title); ValueError naming ``--mpc-json`` when the file is missing or not such a result."""
    _, rows = _load_json(bench_mpc_json, "--mpc-json", "rows", list, "mpc")
    return controller_result_points(rows), f"controller: {Path(bench_mpc_json).name}"


def controller_result_points(rows: list[dict]) -> list[tuple]:
    """``bench mpc`` rows (each a controller "name N=k") -> (label, group, solve ms, height RMSE mm) points."""
    pts = []
    for r in rows:
        fam, _, hor = str(r.get("controller", "?")).partition(" ")
        pts.append((hor or fam, (fam, ""), float(r.get("solve_ms_median", np.nan)), float(r.get("height_rmse_mm", np.nan))))
    return pts


def estimator_pareto_png(bench_ekf_json: Path | str, path: Path | str) -> Path:
    """Estimator Pareto PNG (median filter step in us vs height NRMSD, one point per filter) from ``bench ekf`` JSON."""
    pts, title = estimator_points(bench_ekf_json)
    return pareto_png(pts, path, "median filter step (us)", "height NRMSD (mean over trials)", title)


def controller_pareto_png(bench_mpc_json: Path | str, path: Path | str) -> Path:
    """Controller Pareto PNG (median solve in ms vs height RMSE in mm, per controller x horizon) from ``bench mpc`` JSON."""
    pts, title = controller_points(bench_mpc_json)
    return pareto_png(pts, path, "median solve time (ms)", "height RMSE (mm)", title)
