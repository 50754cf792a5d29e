"""Robot plots: layer shapes over time, runs, the workspace (matplotlib without pyplot), in the
package's figure style (:mod:`hbma_ctrl.app.figstyle`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.app.figstyle import DPI, LABELS, figure, legend, plain_y, save
from hbma_ctrl.core import units as U
from hbma_ctrl.robot.design import LETTERS, RobotDesign
from hbma_ctrl.robot.kinematics import forward_kinematics
from hbma_ctrl.robot.plant import RobotRun


def _outline(design: RobotDesign, pose, axis: int) -> list:
    """The bodies' sections in the plane of world ``axis`` (0: x-z, 1: y-z) and the chambers' segments,
    mm: [(kind, (xs, zs))] with kind "body" or "chamber"."""
    L, R = design.layer_thickness, design.outer_diameter / 2
    xy = design.chamber_xy()
    quad = np.array([[-R, 0, 0, 1], [R, 0, 0, 1], [R, 0, L, 1], [-R, 0, L, 1], [-R, 0, 0, 1]])
    if axis == 1:
        quad = quad[:, [1, 0, 2, 3]]
    out = []
    for Fk in pose.frames:
        q = U.to_mm((Fk @ quad.T).T)
        out.append(("body", (q[:, axis], q[:, 2])))
    for k in range(design.n_layers):
        base = (pose.frames[k] @ np.column_stack([xy, np.full(3, L), np.ones(3)]).T).T[:, :3]
        for i in range(3):
            seg = U.to_mm(np.vstack([base[i], pose.contacts[k, i]]))
            out.append(("chamber", (seg[:, axis], seg[:, 2])))
    return out


def plot_shapes(design: RobotDesign, heights_list: list, path: Path | str, labels: list | None = None,
                title: str = "") -> list[Path]:
    """The robot's shape at each of ``heights_list`` (chamber heights, m), one column per snapshot: its
    side views from the front (x-z) and from the side (y-z), the chambers in red; -> PNG and PDF
    (``path`` with its suffix replaced). Returns the files."""
    n = len(heights_list)
    fig = figure(max(2.3 * n, 6.0), 6.4)
    axes = fig.subplots(2, n, sharey=True, squeeze=False)
    extent = 0.0
    for j, hs in enumerate(heights_list):
        pose = forward_kinematics(design, np.maximum(np.asarray(hs, float).reshape(-1, 3), 0.0))
        for row, axis in enumerate((0, 1)):
            ax = axes[row, j]
            for kind, (a, z) in _outline(design, pose, axis):
                if kind == "body":
                    ax.plot(a, z, color="0.25", lw=1.0)
                else:
                    ax.plot(a, z, color="tab:red", lw=1.6)
                extent = max(extent, float(np.abs(a).max()))
            ax.set_aspect("equal")
            ax.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel(LABELS["z"])
            ax.set_xlabel(LABELS["y"] if axis == 1 else LABELS["x"])
        axes[0, j].set_title(labels[j] if labels else f"shape {j + 1}", fontsize=9)
    for ax in axes.ravel():
        ax.set_xlim(-1.1 * extent, 1.1 * extent)
    fig.suptitle((title or "robot shape") + "\nfront view (x-z, top row) and side view (y-z, bottom row); "
                 "grey: layer bodies, red: chambers (membrane centre to contact)", fontsize=10)
    return save(fig, Path(path).with_suffix(""))


def plot_run(design: RobotDesign, run: RobotRun, path: Path | str) -> list[Path]:
    """Chamber heights and pressures (one panel per layer, its three chambers named) and the layers'
    bend over time -> PNG and PDF (``path`` with its suffix replaced). Returns the files."""
    names = design.names
    N = design.n_layers
    fig = figure(11.0, 2.0 * (2 * N + 1) + 0.8)
    axs = fig.subplots(2 * N + 1, 1, sharex=True)
    T = run.t.size
    h, p = run.h.reshape(T, -1), run.p.reshape(T, -1)
    for k in range(N):
        for i in range(3):
            j = 3 * k + i
            axs[k].plot(run.t, U.to_mm(h[:, j]), color=f"C{i}", label=names[j])
            axs[N + k].plot(run.t, U.to_kpa(p[:, j]), color=f"C{i}", label=names[j])
        axs[k].set_ylabel(LABELS["h"])
        axs[k].set_title(f"Layer {LETTERS[k]}: chamber heights", fontsize=9)
        axs[N + k].set_ylabel(LABELS["p"])
        axs[N + k].set_title(f"Layer {LETTERS[k]}: chamber pressures", fontsize=9)
    for k in range(N):
        top = LETTERS[k + 1] if k + 1 < N else "top"
        axs[-1].plot(run.t, np.degrees(run.bend[:, k]), color=f"C{k}", label=f"layer {LETTERS[k]} (under {top})")
    axs[-1].set_ylabel(LABELS["bend"])
    axs[-1].set_title("Bend of each layer", fontsize=9)
    axs[-1].set_xlabel(LABELS["t"])
    for ax in axs:
        ax.grid(alpha=0.3)
        plain_y(ax)
        legend(ax, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.suptitle("Open-loop robot run: heights, pressures and bends")
    return save(fig, Path(path).with_suffix(""))


def plot_workspace(ws: dict, path: Path | str, title: str = "") -> None:
    """Polar plot of the largest bend angle against bend direction, per layer -> PNG."""

    psi = np.asarray(ws["direction"] + ws["direction"][:1])
    fig = Figure(figsize=(6.5, 6.5))
    ax = fig.add_subplot(projection="polar")
    for ly in ws["layers"]:
        b = np.degrees(ly["bend_max"] + ly["bend_max"][:1])
        bp = np.degrees(ly["bend_max_pressure_control"] + ly["bend_max_pressure_control"][:1])
        ax.plot(psi, b, label=f"layer {ly['layer']}: gas-mass hold, h <= {U.to_mm(ly['h_max']):.1f} mm "
                              f"({ly['limit'][0]})")
        bc = np.degrees(ly["bend_max_no_rim_contact"] + ly["bend_max_no_rim_contact"][:1])
        ax.plot(psi, bc, ls=":", label=f"layer {ly['layer']}: gas-mass hold, rims clear")
        ax.plot(psi, bp, ls="--", label=f"layer {ly['layer']}: pressure control, h <= "
                                        f"{U.to_mm(ly['h_pressure_control']):.1f} mm")
    ax.set_title(title or f"largest bend (deg) vs direction, pressure limit {U.to_kpa(ws['pressure_limit']):g} kPa",
                 fontsize=9)
    ax.legend(fontsize=6, loc="lower center", bbox_to_anchor=(0.5, -0.25))
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
