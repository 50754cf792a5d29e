"""The one style of every figure the package writes: axis labels as "quantity (unit)" in edge units
(:data:`LABELS`), a legend on every axis with more than one labelled line, titles in the user's words,
each figure saved as PNG (:data:`DPI` dpi) and PDF (:func:`save`). matplotlib without pyplot: no global
state, no display."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

__all__ = ["LABELS", "DPI", "FORMATS", "figure", "legend", "save", "decimate", "label_chambers"]

#: axis labels, one style everywhere: "symbol (unit)" or "what (unit)"
LABELS = {
    "t": "t (s)",
    "h": "h (mm)",
    "h_err": "h error (mm)",
    "p": "p (kPa)",
    "p_err": "p error (kPa)",
    "F": "F (N)",
    "duty": "duty (%)",
    "bend": "bend (deg)",
    "direction": "bend direction (deg)",
    "centre": "centre height (mm)",
    "step": "step time (ms)",
    "x": "x (mm)",
    "y": "y (mm)",
    "z": "z (mm)",
}

#: raster resolution of the PNGs, dots per inch
DPI = 150
#: the files each figure is saved as
FORMATS = ("png", "pdf")


def figure(width: float, height: float) -> Figure:
    """A new figure of ``width`` x ``height`` inches with constrained layout (no clipped labels)."""
    return Figure(figsize=(width, height), layout="constrained")


def legend(ax: Axes, **kw) -> None:
    """A legend on ``ax`` when it has more than one labelled line (the package's rule); ``kw`` to matplotlib."""
    handles, labels = ax.get_legend_handles_labels()
    if len(labels) > 1:
        kw.setdefault("fontsize", 8)
        ax.legend(**kw)


def save(fig: Figure, stem: Path | str) -> list[Path]:
    """Save ``fig`` as ``stem.png`` (:data:`DPI` dpi) and ``stem.pdf``; returns the paths."""
    stem = Path(stem)
    out = []
    for ext in FORMATS:
        path = stem.with_suffix(f".{ext}")
        fig.savefig(path, dpi=DPI)
        out.append(path)
    return out


def decimate(t: np.ndarray, *ys: np.ndarray, most: int = 20000) -> tuple:
    """(t, *ys) thinned to at most ``most`` samples by an even stride (a figure of a long run)."""
    step = max(1, int(np.ceil(len(t) / most)))
    return (t[::step], *(y[::step] for y in ys))


def label_chambers(ax: Axes, names, values_last) -> None:
    """Name each line at its right end (chamber names; for panels with several chambers' lines)."""
    for nm, (x, y) in zip(names, values_last):
        if np.isfinite(y):
            ax.annotate(nm, (x, y), xytext=(3, 0), textcoords="offset points", fontsize=7, va="center")
