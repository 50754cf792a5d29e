"""Paper-style figures (PNG, matplotlib without pyplot, so no global state and no display needed).

- :func:`fig6` equilibrium pressure and load surfaces over (h1, h2), NH and MR side by side
  (t0 = 3 mm, r1 = 7.5 mm), evaluated on the casadi model (``physics.pressure``, ``geometry``).
- :func:`fig7` five unloaded inflations, r1 = 12.5 mm, t0 = 3 mm: height and pressure vs time.
- :func:`fig9` r1 = 12.5 mm, t0 = 2 mm, 200 g: height, pressure and force vs time.
- :func:`plot_run` any log: height, pressure, force and inputs vs time, with event markers.

Axes are in edge units (mm, kPa, N, g, %), labelled in the package's style
(:mod:`hbma_ctrl.app.figstyle`); each figure is written as the PNG it is asked for and a PDF beside it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import casadi as ca
import numpy as np
from matplotlib.figure import Figure
from matplotlib.tri import Triangulation

from hbma_ctrl.app.figstyle import LABELS, legend, save, saved_once
from hbma_ctrl.core import physics as ph
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import Material, make_material
from hbma_ctrl.sim.batch import FIGURE_CASES, FIGURE_TRIALS, PROTOCOL_DEFAULTS, protocol_trials, simulate_trials
from hbma_ctrl.sim.trial import Log, SimSettings, Trial

__all__ = ["fig6", "fig7", "fig9", "plot_run", "protocol_figures", "streamed_protocol_figures", "paper_figures",
           "equilibrium_grid", "FIG7_TRIALS", "FIG9_TRIALS"]

FIG7_CASE, FIG9_CASE = FIGURE_CASES["fig7"], FIGURE_CASES["fig9"]
FIG7_TRIALS, FIG9_TRIALS = FIGURE_TRIALS["fig7"], FIGURE_TRIALS["fig9"]


def equilibrium_grid(material: Material, r1: float, t0: float, h1: np.ndarray, h2: np.ndarray,
                     V0: float = 3e-6) -> dict[str, np.ndarray]:
    """Equilibrium pressure (Pa), force (N), stretch and volume (m^3) at points (h1, h2) (m), SI.

    Uses the model's casadi expressions; requires 0 <= h2 <= h1 elementwise.
    """
    h1 = np.atleast_1d(np.asarray(h1, float))
    h2 = np.atleast_1d(np.asarray(h2, float))
    if np.any(h2 < 0) or np.any(h2 > h1 + 1e-15):
        raise ValueError("equilibrium: need 0 <= h2 <= h1")
    s1, s2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    P = {"r1": r1, "t0": t0, "V0": V0, "material": material}
    g = ph.geometry(s1, s2, P)
    p = ph.pressure(s1, s2, P)
    f = ca.Function("eq", [s1, s2], [p, ca.pi * g["a2"] * p, g["lam"], g["V"], g["a2"]])
    fm = f.map(h1.size)
    p, F, lam, V, a2 = (np.asarray(v).ravel() for v in fm(h1[None, :], h2[None, :]))
    return {"p": p, "F": F, "lam": lam, "V": V, "a2": a2}


def fig6(path: Path | str, t0_mm: float = 3.0, r1_mm: float = 7.5, h1_max_mm: float | None = None,
         n: int = 60, p_max_kpa: float = 80.0) -> Path:
    """Fig. 6: equilibrium pressure (kPa) and load (g = F/g) over (h1, h2), h2 <= h1, NH and MR.

    Points above ``p_max_kpa`` (the flat-limit corner h2 -> h1, where p grows without bound) are
    left out so the working range stays readable. The figure shows no input of a run: it is drawn
    once per machine for the same surfaces and copied after (:func:`hbma_ctrl.app.figstyle.saved_once`).
    """
    r1, t0 = U.mm(r1_mm), U.mm(t0_mm)
    h1_max = U.mm(h1_max_mm) if h1_max_mm else 2.0 * r1
    a = np.linspace(0.0, 1.0, n)
    H1, S = np.meshgrid(a * h1_max, a)
    H1, H2 = H1.ravel(), (S * H1).ravel()  # h2 = s h1, s in [0, 1]: the triangle h2 <= h1
    surfaces = {name: equilibrium_grid(make_material(name), r1, t0, H1, H2) for name in ("nh", "mr")}
    title = (f"Fig. 6: equilibrium surfaces, t0 = {t0_mm:g} mm, r1 = {r1_mm:g} mm "
             f"(h2 <= h1, shown where p <= {p_max_kpa:g} kPa)")

    def draw(stem: Path) -> None:
        fig = Figure(figsize=(11, 8.5), dpi=110)
        for col, (name, res) in enumerate(surfaces.items()):
            tri = Triangulation(U.to_mm(H1), U.to_mm(H2))
            # near the flat limit (h2 -> h1, large h1) the pressure grows without bound: show p <= p_max
            too_high = U.to_kpa(res["p"]) > p_max_kpa
            tri.set_mask(too_high[tri.triangles].any(axis=1))
            for row, (z, label, cmap) in enumerate(((U.to_kpa(res["p"]), "p (kPa)", "viridis"),
                                                    (U.to_grams(res["F"] / U.G_STD), "load F/g (g)", "plasma"))):
                ax = fig.add_subplot(2, 2, 1 + col + 2 * row, projection="3d")
                zmax = float(np.max(z[~too_high]))
                # rasterized: in the PDF each surface is one image at the PNG's resolution, not
                # 7,000 vector triangles (which took most of the figure's time and file size)
                ax.plot_trisurf(tri, z, cmap=cmap, linewidth=0.1, antialiased=True, vmin=0.0, vmax=zmax,
                                rasterized=True)
                ax.set_zlim(0.0, zmax)
                ax.set_xlabel("h1 (mm)")
                ax.set_ylabel("h2 (mm)")
                ax.set_zlabel(label)
                ax.set_title(f"{_MATERIAL_WORDS[name]}: {'pressure' if row == 0 else 'load'}")
                ax.view_init(elev=28, azim=-115)
        fig.suptitle(title)
        # fixed margins (what a tight layout gives this page): a tight layout draws the four 3D
        # surfaces once more just to measure them, a third of the figure's time
        fig.subplots_adjust(left=0.01, right=0.99, bottom=0.03, top=0.92, wspace=-0.1, hspace=0.13)
        save(fig, stem)

    shown = [title, H1, H2] + [res[k] for res in surfaces.values() for k in ("p", "F")]
    files = saved_once(Path(path).with_suffix(""), draw, *shown)
    return next(f for f in files if f.suffix == Path(path).suffix) if Path(path).suffix else files[0]


#: the materials by the names a reader knows them by
_MATERIAL_WORDS = {"nh": "neo-Hookean", "mr": "Mooney-Rivlin"}


def _save(fig: Figure, path: Path | str) -> Path:
    """``fig`` as ``path`` (PNG) and a PDF beside it (:func:`hbma_ctrl.app.figstyle.save`); returns ``path``."""
    files = save(fig, Path(path).with_suffix(""))
    return next(f for f in files if f.suffix == Path(path).suffix) if Path(path).suffix else files[0]


def _time_panels(path, logs: list[Log], labels: list[str], panels, title: str) -> Path:
    height = 2.6 * len(panels)
    fig = Figure(figsize=(8, height), dpi=110)
    # fixed margins in inches (what a tight layout gives these panels): a tight layout draws the
    # figure once more just to measure it, a third of its time
    fig.subplots_adjust(left=0.085, right=0.98, bottom=0.58 / height, top=1.0 - 0.52 / height, hspace=0.12)
    axes = fig.subplots(len(panels), 1, sharex=True)
    axes = np.atleast_1d(axes)
    for ax, (key, to_edge, ylabel) in zip(axes, panels):
        for log, lab in zip(logs, labels):
            ax.plot(log["t"], to_edge(log[key]), label=lab, lw=1.4)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="center right", title="pump speed", title_fontsize=8)
    axes[-1].set_xlabel(LABELS["t"])
    fig.suptitle(title)
    return _save(fig, path)


def fig7(path: Path | str, logs: list[Log]) -> Path:
    """Fig. 7: height and pressure vs time of unloaded inflations, one line per speed."""
    return _time_panels(path, logs, [_speed_label(log) for log in logs],
                        [("h", U.to_mm, LABELS["h"]), ("p", U.to_kpa, LABELS["p"])],
                        f"Fig. 7: unloaded inflations, t0 = {FIG7_CASE[0]:g} mm, r1 = {FIG7_CASE[1]:g} mm")


def fig9(path: Path | str, logs: list[Log]) -> Path:
    """Fig. 9: height, pressure and force vs time under a 200 g load, one line per speed."""
    return _time_panels(path, logs, [_speed_label(log) for log in logs],
                        [("h", U.to_mm, LABELS["h"]), ("p", U.to_kpa, LABELS["p"]), ("F", np.asarray, LABELS["F"])],
                        f"Fig. 9: t0 = {FIG9_CASE[0]:g} mm, r1 = {FIG9_CASE[1]:g} mm, {FIG9_CASE[2]:g} g load "
                        f"({logs[0].fidelity if logs else ''})")


def _speed_label(log: Log) -> str:
    return f"{U.to_pct(float(np.max(log['speed']))):.0f} %"


def plot_run(log: Log, path: Path | str, title: str | None = None, sensor_range: float | None = None) -> Path:
    """Height, pressure, force and inputs vs time for one log, with its events marked; ``path`` (PNG) and
    a PDF beside it."""
    fig = Figure(figsize=(9, 9.5), layout="constrained")
    axes = fig.subplots(4, 1, sharex=True)
    t = log["t"]
    axes[0].plot(t, U.to_mm(log["h"]), label="h (platform or membrane top)")
    if np.any(log["h2"] > 0):
        axes[0].plot(t, U.to_mm(log["h1"]), "--", lw=1, label="h1 (membrane cap, under the platform)")
    axes[0].set_ylabel(LABELS["h"])
    axes[1].plot(t, U.to_kpa(log["p"]), color="C1", label="chamber pressure")
    if sensor_range:
        axes[1].axhline(U.to_kpa(sensor_range), color="k", ls=":", lw=1, label="sensor range")
    axes[1].set_ylabel(LABELS["p"])
    axes[2].plot(t, log["F"], color="C2")
    axes[2].set_ylabel(LABELS["F"])
    axes[3].step(t, log["speed"] * 100, where="post", label="pump speed")
    axes[3].step(t, log["inlet"] * 100, where="post", ls="--", label="inlet duty")
    axes[3].step(t, log["outlet"] * 100, where="post", ls=":", label="outlet duty")
    axes[3].set_ylabel(LABELS["duty"])
    axes[3].set_xlabel(LABELS["t"])
    axes[3].set_ylim(-5, 105)
    seen = set()
    for te, name in log.events:
        short = name.split(":")[0]
        for ax in axes:
            ax.axvline(te, color="0.5", lw=0.8, ls="--")
        if (short, round(te, 2)) not in seen:
            axes[0].annotate(short, (te, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize=7,
                             va="top", ha="right", color="0.3")
            seen.add((short, round(te, 2)))
    for ax in axes:
        ax.grid(alpha=0.3)
        legend(ax, loc="upper right")
    fig.suptitle(title or f"{log.name} ({log.fidelity}, status {log.status})")
    return _save(fig, path)


def _figure_trials(material: Material) -> list[Trial]:
    out = []
    for case in (FIG7_CASE, FIG9_CASE):
        out += protocol_trials(material, loads_g=[case[2]], speeds_pct=PROTOCOL_DEFAULTS["speeds_pct"], t0_mm=[case[0]],
                               r1_mm=[case[1]])
    return out


def protocol_figures(out_dir: Path | str, material: Material, trials: list[Trial], logs: list[Log],
                     settings: SimSettings | None = None, fidelity: str = "auto", with_fig6: bool = True) -> list[Path]:
    """Write fig6 (unless ``with_fig6`` is False: it needs no logs), fig7 and fig9 PNGs into out_dir,
    reusing the protocol's logs (simulating what is missing)."""
    batches = iter([logs, None])
    return streamed_protocol_figures(lambda: next(batches), out_dir, material, settings, fidelity, with_fig6)


def streamed_protocol_figures(recv: Callable[[], list[Log] | None], out_dir: Path | str, material: Material,
                              settings: SimSettings | None = None, fidelity: str = "auto",
                              with_fig6: bool = True) -> list[Path]:
    """:func:`protocol_figures` with the logs arriving in batches: each ``recv()`` returns the next batch
    of logs, None after the last. fig6 is drawn first, fig7 and fig9 each as soon as its five trials have
    arrived; the trials that never arrive are simulated here."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [fig6(out / "fig6.png")] if with_fig6 else []
    todo = {"fig7": (fig7, FIG7_TRIALS), "fig9": (fig9, FIG9_TRIALS)}
    by_name: dict[str, Log] = {}
    while todo:
        batch = recv()
        if batch is None:
            need = [tr for tr in _figure_trials(material) if tr.name not in by_name]
            batch = simulate_trials(need, settings, fidelity) if need else []
        by_name.update((log.name, log) for log in batch)
        for name, (draw, names) in list(todo.items()):
            if all(n in by_name for n in names):
                paths.append(draw(out / f"{name}.png", [by_name[n] for n in names]))
                del todo[name]
    return sorted(paths)


def paper_figures(out_dir: Path | str, material: str | Material = "nh", settings: SimSettings | None = None,
                  fidelity: str = "auto") -> list[Path]:
    """fig6/fig7/fig9 PNGs without a protocol run (simulates the 10 trials figs 7 and 9 need)."""
    mat = make_material(material) if isinstance(material, str) else material
    return protocol_figures(out_dir, mat, [], [], settings, fidelity)
