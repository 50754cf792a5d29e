"""Robot plots: layer shapes over time, runs, the workspace (matplotlib, Agg).
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.core import units as U
from hbma_ctrl.robot.design import LETTERS, RobotDesign
from hbma_ctrl.robot.kinematics import forward_kinematics
from hbma_ctrl.robot.plant import RobotRun


def _circle(frame: np.ndarray, z: float, r: float, n: int = 48) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, n)
    pts = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n, z), np.ones(n)])
    return (frame @ pts.T).T[:, :3]


def plot_shapes(design: RobotDesign, heights_list: list, path: Path | str, labels: list | None = None,
                title: str = "") -> None:
    """Draw robot shapes (3D view and x-z side view) for a list of chamber-height sets (m) -> PNG."""

    fig = Figure(figsize=(11, 5.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    cmap = matplotlib.colormaps["viridis"]
    L, R = design.layer_thickness, design.outer_diameter / 2
    xy = design.chamber_xy()
    extent = 0.0
    for j, hs in enumerate(heights_list):
        pose = forward_kinematics(design, hs)
        col = cmap(j / max(len(heights_list) - 1, 1))
        lab = labels[j] if labels else None
        for k, Fk in enumerate(pose.frames):
            for z in (0.0, L):
                c = U.to_mm(_circle(Fk, z, R))
                ax3.plot(c[:, 0], c[:, 1], c[:, 2], color=col, lw=0.8)
            # side view: the body's outline in its x-z section
            quad = np.array([[-R, 0, 0, 1], [R, 0, 0, 1], [R, 0, L, 1], [-R, 0, L, 1], [-R, 0, 0, 1]])
            q = U.to_mm((Fk @ quad.T).T)
            ax2.plot(q[:, 0], q[:, 2], color=col, lw=1.0, label=lab if k == 0 else None)
            extent = max(extent, float(np.abs(q[:, [0, 2]]).max()))
        for k in range(design.n_layers):
            base = (pose.frames[k] @ np.column_stack([xy, np.full(3, L), np.ones(3)]).T).T[:, :3]
            for i in range(3):
                seg = U.to_mm(np.vstack([base[i], pose.contacts[k, i]]))
                ax3.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="tab:red", lw=2.0)
                ax2.plot(seg[:, 0], seg[:, 2], color="tab:red", lw=1.5, alpha=0.7)
        tp = U.to_mm(pose.tip_position)
        ax3.scatter(*tp, color=col, s=12)
    lim = extent * 1.05
    ax3.set_xlim(-lim / 2, lim / 2)
    ax3.set_ylim(-lim / 2, lim / 2)
    ax3.set_zlim(0, lim)
    ax3.set_xlabel("x (mm)")
    ax3.set_ylabel("y (mm)")
    ax3.set_zlabel("z (mm)")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x (mm)")
    ax2.set_ylabel("z (mm)")
    ax2.set_title("side view (x-z section); red: chambers (membrane centre to contact)", fontsize=8)
    if labels:
        ax2.legend(fontsize=7, loc="upper left")
    fig.suptitle(title or "robot shape")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def plot_run(design: RobotDesign, run: RobotRun, path: Path | str) -> None:
    """Chamber heights, pressures and layer bend angles over time -> PNG."""

    names = design.names
    fig = Figure(figsize=(9, 8))
    axs = fig.subplots(3, 1, sharex=True)
    T = run.t.size
    for i, nm in enumerate(names):
        axs[0].plot(run.t, U.to_mm(run.h.reshape(T, -1)[:, i]), label=nm)
        axs[1].plot(run.t, U.to_kpa(run.p.reshape(T, -1)[:, i]), label=nm)
    for k in range(design.n_layers):
        axs[2].plot(run.t, np.degrees(run.bend[:, k]), label=f"layer {LETTERS[k]} -> {LETTERS[k + 1] if k + 1 < design.n_layers else 'top'}")
    axs[0].set_ylabel("chamber height (mm)")
    axs[1].set_ylabel("pressure (kPa)")
    axs[2].set_ylabel("bend (deg)")
    axs[2].set_xlabel("t (s)")
    for ax in axs:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


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
    fig.savefig(path, dpi=120)
