"""The one style of every figure the package writes: axis labels as "quantity (unit)" in edge units
(:data:`LABELS`), a legend on every axis with more than one labelled line, titles in the user's words,
each figure saved as PNG (:data:`DPI` dpi) and PDF (:func:`save`). matplotlib without pyplot: no global
state, no display."""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

__all__ = ["LABELS", "DPI", "FORMATS", "figure", "legend", "save", "saved_once", "decimate", "plain_y"]

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


def saved_once(stem: Path | str, draw: Callable[[Path], object], *shown: object) -> list[Path]:
    """``draw(stem)``'s files (``stem.png``, ``stem.pdf``), drawn once per machine for the same ``shown``
    (every value and array the figure shows) and copied from the cache (``$HBMA_CTRL_CACHE/figures``)
    after; the drawing code and matplotlib's version are part of the key, so a changed figure is
    drawn again. Returns the paths."""
    from hbma_ctrl.core.codegen import cache_dir

    key = hashlib.sha256(matplotlib.__version__.encode())
    key.update(Path(__file__).read_bytes())
    key.update(Path(draw.__code__.co_filename).read_bytes())
    for value in shown:
        key.update(np.ascontiguousarray(value).tobytes() if isinstance(value, np.ndarray) else repr(value).encode())
    cached = cache_dir() / "figures" / key.hexdigest()[:32]
    stem = Path(stem)
    if not all((cached / f"figure.{ext}").is_file() for ext in FORMATS):
        try:
            cached.parent.mkdir(parents=True, exist_ok=True)
            part = Path(tempfile.mkdtemp(dir=cached.parent, suffix=".part"))
        except OSError:  # no cache to write to (a read-only home): the figure is drawn where it is asked
            draw(stem)
            return [stem.with_suffix(f".{ext}") for ext in FORMATS]
        draw(part / "figure")
        try:
            os.replace(part, cached)  # atomic: a parallel run sees the whole figure or none
        except OSError:  # another run stored it first
            shutil.rmtree(part, ignore_errors=True)
    out = []
    for ext in FORMATS:
        shutil.copyfile(cached / f"figure.{ext}", stem.with_suffix(f".{ext}"))
        out.append(stem.with_suffix(f".{ext}"))
    return out


def decimate(t: np.ndarray, *ys: np.ndarray, most: int = 20000) -> tuple:
    """(t, *ys) thinned to at most ``most`` samples by an even stride (a figure of a long run)."""
    step = max(1, int(np.ceil(len(t) / most)))
    return (t[::step], *(y[::step] for y in ys))


def plain_y(ax: Axes, least_span: float = 1.0) -> None:
    """Plain y tick labels (no offset or power above the axis) and, for a flat signal, a y range of
    ``least_span`` around it (a constant otherwise shows as noise at its last digits)."""
    lo, hi = ax.get_ylim()
    if hi - lo < 1e-6 * max(1.0, abs(lo), abs(hi)):
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - least_span / 2, mid + least_span / 2)
    ax.ticklabel_format(axis="y", style="plain", useOffset=False)
