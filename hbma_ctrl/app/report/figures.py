"""The report's figures of a run (:class:`hbma_ctrl.app.report.load.RunSignals`), in the package's one
style (:mod:`hbma_ctrl.app.figstyle`). Each figure is written only when the run has its signals:

- ``tracking``: per chamber its height: target, estimate and truth (a simulated rig's).
- ``pressures``: per chamber its pressure: measured, estimated and true, with the pressure limit.
- ``commands``: per chamber the pump speed and the inlet and outlet valve duty.
- ``estimator_errors``: where a truth exists, the estimate's height and pressure errors per chamber (a
  panel for each quantity the log holds both of).
- ``events``: faults and other events on the time axis, with the loop's step time.
- ``robot_pose``: a robot's layers: bend, bend direction and centre height (target, estimated, true).

A robot's chambers are drawn one panel per layer (its three chambers, named in each legend).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.lines import Line2D

from hbma_ctrl.app.figstyle import LABELS, decimate, figure, legend, plain_y, save
from hbma_ctrl.app.report.load import RunSignals, is_fault, load_run

__all__ = ["report", "make_figures", "FIGURES"]

#: deg: below this bend a layer's bend direction is the noise's, not drawn
BEND_FOR_DIRECTION_DEG = 1.0
#: the report's figures, in the order they are made
FIGURES = ("tracking", "pressures", "commands", "estimator_errors", "events", "robot_pose")

def _groups(sig: RunSignals) -> list[tuple[str, list[str]]]:
    """The panels' chamber groups: a robot's layers (three chambers each), else one panel per chamber."""
    names = sig.names
    if len(names) > 1 and len(names) % 3 == 0:
        return [(f"Layer {names[3 * k][0]}" if names[3 * k][0].isalpha() else f"Chambers {', '.join(names[3 * k:3 * k + 3])}",
                 names[3 * k:3 * k + 3]) for k in range(len(names) // 3)]
    return [(f"Chamber {nm}", [nm]) for nm in names]


def _panels(n: int, title: str, height: float = 2.4):
    cols = 1 if n <= 4 else 2
    rows = math.ceil(n / cols)
    fig = figure(6.5 * cols if cols > 1 else 10.0, height * rows + 0.8)
    axes = np.atleast_1d(fig.subplots(rows, cols, sharex=True, squeeze=False)).ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.suptitle(title)
    return fig, axes[:n]


def _bottom(ax: Axes, axes) -> bool:
    """True for the lowest panel of its column (the one that carries the shared time axis's label)."""
    ss = ax.get_subplotspec()
    return not any(o.get_subplotspec().colspan == ss.colspan and o.get_subplotspec().rowspan.start > ss.rowspan.start
                   for o in axes)


def _finish_axes(axes, ylabel: str, keys=None) -> None:
    """Labels, grid and legends of a panel figure: each axis gets ``keys`` (a compact legend: its
    chambers' colours, then the signals' line styles) or its own lines' legend."""
    for ax in axes:
        ax.set_ylabel(ylabel)
        plain_y(ax)
        if _bottom(ax, axes):
            ax.set_xlabel(LABELS["t"])
        ax.grid(alpha=0.3)
        if keys is not None:
            handles = keys(ax)
            if len(handles) > 1:
                ax.legend(handles=handles, fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
        else:
            legend(ax, loc="center left", bbox_to_anchor=(1.01, 0.5))


def _keys(chambers_by_ax: dict, styles) -> Callable:
    """A compact legend per axis: one entry per chamber (its colour), one per signal (its line style),
    for the signals the axis draws; ``styles``: (words, style dict)."""
    def make(ax):
        drawn = {ln.get_label() for ln in ax.get_lines()}
        chambers = chambers_by_ax.get(ax, [])
        out = []
        if len(chambers) > 1:
            out += [Line2D([], [], color=f"C{j}", lw=2, label=nm) for j, nm in enumerate(chambers)]
        for words, st in styles:
            if any(d.endswith(words) for d in drawn):
                out.append(Line2D([], [], color="0.2" if len(chambers) > 1 else "C0",
                                  **{k: v for k, v in st.items() if k in ("ls", "lw", "alpha")}, label=words))
        out += [ln for ln in ax.get_lines() if ln.get_label() in ("pressure limit", "fault")]
        return out
    return make


def _faults(sig: RunSignals, axes) -> None:
    """The faults as red vertical lines on every panel (one legend entry)."""
    ts = [t for t, k, _ in sig.events if is_fault(k)]
    for ax in axes:
        for j, t in enumerate(ts):
            ax.axvline(t, color="tab:red", lw=0.8, ls="--", label="fault" if j == 0 else None)


def _plot(ax: Axes, sig: RunSignals, topic: str, col: str, scale: float = 1.0, **kw) -> bool:
    got = sig.get(topic, col)
    if got is None:
        return False
    t, y = decimate(*got)
    ax.plot(t, y * scale, **kw)
    return True


def _chamber_figure(sig: RunSignals, what: str, lines, ylabel: str, limit: float | None = None):
    """Panels by chamber group, titled ``what`` and the lines the log holds; ``lines``: (topic, stem,
    words, style) drawn per chamber."""
    groups = _groups(sig)
    lines = [ln for ln in lines if sig.has(ln[0], ln[1])]
    fig, axes = _panels(len(groups), f"{sig.name}: {what} ({', '.join(w for _, _, w, _ in lines)})")
    by_ax = {}
    for ax, (gname, chambers) in zip(axes, groups):
        by_ax[ax] = chambers
        for j, nm in enumerate(chambers):
            for topic, stem, words, style in lines:
                _plot(ax, sig, topic, f"{stem}.{nm}", label=f"{nm} {words}", **{"color": f"C{j}", **style})
        if limit is not None:
            ax.axhline(limit, color="tab:red", lw=1.0, ls="-.", label="pressure limit")
        ax.set_title(gname, fontsize=9)
    _faults(sig, axes)
    _finish_axes(axes, ylabel, _keys(by_ax, [(w, st) for _, _, w, st in lines]))
    return fig


def tracking(sig: RunSignals):
    """Height per chamber: target (dashed), estimate (solid), truth (thin); None without heights."""
    if not (sig.has("/estimates", "h_mm") or sig.has("/truth", "h_mm")):
        return None
    lines = [("/targets", "h_mm", "target", dict(ls="--", lw=1.2)),
             ("/estimates", "h_mm", "estimate", dict(lw=1.4)),
             ("/truth", "h_mm", "true", dict(lw=0.9, ls=":"))]
    return _chamber_figure(sig, "chamber heights", lines, LABELS["h"])


def pressures(sig: RunSignals):
    """Pressure per chamber: measured (thin), estimated, true, and the limit; None without pressures."""
    if not (sig.has("/readings", "p_kpa") or sig.has("/truth", "p_kpa")):
        return None
    lines = [("/readings", "p_kpa", "measured", dict(lw=0.6, alpha=0.5)),
             ("/estimates", "p_kpa", "estimate", dict(lw=1.4)),
             ("/truth", "p_kpa", "true", dict(lw=0.9, ls=":"))]
    return _chamber_figure(sig, "chamber pressures", lines, LABELS["p"], sig.pressure_limit_kpa)


def commands(sig: RunSignals):
    """Pump speed and valve duties per chamber (%); None without commands."""
    if not any(sig.has("/commands", k) for k in ("speed", "inlet", "outlet")):
        return None
    groups = _groups(sig)
    styles = [st for st in (("speed", "pump speed", dict(ls="-", lw=1.2)), ("inlet", "inlet duty", dict(ls="--", lw=1.0)),
                            ("outlet", "outlet duty", dict(ls=":", lw=1.2))) if sig.has("/commands", st[0])]
    # the title names what the log holds (a robot's pumps are not per chamber), as _chamber_figure's do
    fig, axes = _panels(len(groups), f"{sig.name}: commands ({', '.join(w for _, w, _ in styles)})")
    by_ax = {}
    for ax, (gname, chambers) in zip(axes, groups):
        by_ax[ax] = chambers
        for j, nm in enumerate(chambers):
            for k, words, st in styles:
                got = sig.get("/commands", f"{k}.{nm}")
                if got is not None:
                    t, y = decimate(*got)
                    ax.step(t, 100.0 * y, where="post", color=f"C{j}", label=f"{nm} {words}", **st)
        ax.set_ylim(-5, 105)
        ax.set_title(gname, fontsize=9)
    _faults(sig, axes)
    _finish_axes(axes, LABELS["duty"], _keys(by_ax, [(w, st) for _, w, st in styles]))
    return fig


def _error(sig: RunSignals, stem: str, nm: str):
    est, tru = sig.get("/estimates", f"{stem}.{nm}"), sig.get("/truth", f"{stem}.{nm}")
    if est is None or tru is None:
        return None
    # the truth may be stamped one period after the estimate (the simulated rig's state after the command)
    t = est[0]
    return t, est[1] - np.interp(t, tru[0], tru[1], left=np.nan, right=np.nan)


def estimator_errors(sig: RunSignals):
    """Estimate minus truth per chamber, height and pressure; None without both."""
    if not (sig.has("/estimates", "h_mm") and sig.has("/truth", "h_mm")):
        return None
    # a panel per quantity the log has both an estimate and a truth of (a robot's truth has no pressure)
    panels = [(stem, ylabel, title, errs) for stem, ylabel, title in
              (("h_mm", LABELS["h_err"], "height"), ("p_kpa", LABELS["p_err"], "pressure"))
              if (errs := [(j, nm, got) for j, nm in enumerate(sig.names) if (got := _error(sig, stem, nm)) is not None])]
    if not panels:
        return None
    fig = figure(10.0, 1.0 + 2.5 * len(panels))
    axes = np.atleast_1d(fig.subplots(len(panels), 1, sharex=True))
    fig.suptitle(f"{sig.name}: estimator errors (estimate minus true)")
    for ax, (stem, ylabel, title, errs) in zip(axes, panels):
        for j, nm, got in errs:
            t, e = decimate(*got)
            ax.plot(t, e, lw=0.9, color=f"C{j % 10}", ls="-" if j < 10 else "--", label=nm)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        legend(ax, loc="center left", bbox_to_anchor=(1.01, 0.5), title="chamber")
    axes[-1].set_xlabel(LABELS["t"])
    _faults(sig, list(axes))
    return fig


def events(sig: RunSignals):
    """Each event kind on its own row against time (faults in red), with the loop's step time; None when
    the run has neither."""
    step = sig.get("/loop", "step_ms")
    if not sig.events and step is None:
        return None
    kinds = list(dict.fromkeys(k for _, k, _ in sig.events))
    fig = figure(10.0, 2.0 + 0.3 * len(kinds) + (2.4 if step is not None else 0))
    axes = fig.subplots(2, 1, sharex=True, height_ratios=[max(1, len(kinds)) * 0.3 + 0.6, 2.4]) if step is not None \
        else [fig.subplots(1, 1)]
    ax = axes[0]
    for i, kind in enumerate(kinds):
        ts = [t for t, k, _ in sig.events if k == kind]
        fault = is_fault(kind)
        ax.plot(ts, [i] * len(ts), "|" if not fault else "x", ms=10, mew=1.5,
                color="tab:red" if fault else "0.3", label=None)
    ax.set_yticks(range(len(kinds)), [k.replace("_", " ") for k in kinds], fontsize=8)
    ax.set_ylim(-0.7, len(kinds) - 0.3)
    ax.set_ylabel("event")
    ax.set_title("events (faults in red)", fontsize=9)
    ax.grid(alpha=0.3, axis="x")
    if step is not None:
        t, y = decimate(*step)
        axes[1].plot(t, y, lw=0.6, color="C0")
        axes[1].set_ylabel(LABELS["step"])
        axes[1].set_title("loop step time", fontsize=9)
        axes[1].grid(alpha=0.3)
    axes[-1].set_xlabel(LABELS["t"])
    fig.suptitle(f"{sig.name}: faults and events over time")
    return fig


def robot_pose(sig: RunSignals):
    """A robot's layers over time: bend, bend direction and centre height, target (dashed), estimated
    (solid) and true (dotted); None for a chamber."""
    styles = {"/robot/pose_target": ("target", "--"), "/robot/pose": ("estimate", "-"),
              "/robot/pose_truth": ("true", ":")}
    topics = [tp for tp in styles if sig.layers(tp)]
    if not topics:
        return None
    fig = figure(10.0, 8.0)
    axes = fig.subplots(3, 1, sharex=True)
    fig.suptitle(f"{sig.name}: robot pose per layer ({', '.join(styles[tp][0] for tp in topics)})")
    for tp in topics:
        words, ls = styles[tp]
        for k, letter in enumerate(sig.layers(tp)):
            for ax, field in zip(axes, ("bend_deg", "direction_deg", "centre_mm")):
                got = sig.get(tp, f"layers.{k}.{field}")
                if got is None:
                    continue
                t, y = decimate(*got)
                if field == "direction_deg":
                    # a direction is only defined while the layer bends: hide it where the bend is near 0
                    b = sig.get(tp, f"layers.{k}.bend_deg")
                    y = np.where(decimate(*b)[1] > BEND_FOR_DIRECTION_DEG, y, np.nan) if b is not None else y
                    # no line across the wrap at +-180 deg
                    jump = np.abs(np.diff(y, prepend=y[:1])) > 180.0
                    y = np.where(jump, np.nan, y)
                ax.plot(t, y, ls=ls, lw=1.2, color=f"C{k}", label=f"layer {letter} {words}")
    layers = sig.layers(topics[0])
    keys = [Line2D([], [], color=f"C{k}", lw=2, label=f"layer {letter}") for k, letter in enumerate(layers)]
    keys += [Line2D([], [], color="0.2", ls=styles[tp][1], label=styles[tp][0]) for tp in topics]
    for ax, key in zip(axes, ("bend", "direction", "centre")):
        ax.set_ylabel(LABELS[key])
        ax.grid(alpha=0.3)
        ax.legend(handles=keys + [ln for ln in ax.get_lines() if ln.get_label() == "fault"], fontsize=8,
                  loc="center left", bbox_to_anchor=(1.01, 0.5))
    axes[1].set_ylim(-185, 185)
    axes[-1].set_xlabel(LABELS["t"])
    _faults(sig, axes)
    return fig


_MAKERS = {"tracking": tracking, "pressures": pressures, "commands": commands,
           "estimator_errors": estimator_errors, "events": events, "robot_pose": robot_pose}


def make_figures(sig: RunSignals) -> dict:
    """The figures (module doc) the run's signals give: name -> matplotlib Figure, in :data:`FIGURES` order."""
    out = {}
    for name in FIGURES:
        fig = _MAKERS[name](sig)
        if fig is not None:
            out[name] = fig
    return out


def report(run_dir: Path | str, out: Path | str) -> list[Path]:
    """Write the figures of the run in ``run_dir`` into ``out`` (created): each as PNG and PDF (module doc);
    returns the files written."""
    sig = load_run(run_dir)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    for name, fig in make_figures(sig).items():
        files += save(fig, out / name)
    if not files:
        raise ValueError(f"RUN_DIR {run_dir}: its log ({sig.source}) holds no signal to draw")
    return files
