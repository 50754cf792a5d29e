"""Robot targets: per-layer centre height, bend angle and direction over time -> chamber heights (SI).
"""

from __future__ import annotations

import math

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import check_range
from hbma_ctrl.robot.design import LETTERS, RobotDesign
from hbma_ctrl.robot.kinematics import inverse_kinematics
from hbma_ctrl.robot.rig import H_TARGET_MAX


def parse_targets(raw: dict, design: RobotDesign) -> dict:
    """``[robot.targets]`` {layer letter or "all": [[t_s, height_mm, bend_deg, direction_deg], ...]}
    -> {layer index: ((t s, centre m, bend rad >= 0, direction rad), ...)} (SI, sorted by time).

    A negative bend means the opposite direction. Every layer needs rows (from "all" or its
    letter). Each pose's chamber heights (inverse kinematics) must lie in [0, 13] mm (heights down
    to -0.05 mm count as 0: rounded table numbers for a flat chamber).
    """
    if not isinstance(raw, dict) or not raw:
        raise ValueError("robot.targets must be a table {A = [[t_s, height_mm, bend_deg, direction_deg], ...], ...} "
                         "(or all = [...])")
    N = design.n_layers
    letters = list(LETTERS[:N])
    out: dict = {}
    for key, rows in raw.items():
        if key != "all" and key not in letters:
            raise ValueError(f"robot.targets.{key}: no such layer; allowed: all, {', '.join(letters)}")
        if not isinstance(rows, list) or not rows or not all(isinstance(r, list) and len(r) == 4 for r in rows):
            raise ValueError(f"robot.targets.{key} must be a list of [t_s, height_mm, bend_deg, direction_deg]")
        parsed = []
        for j, r in enumerate(rows):
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in r):
                raise ValueError(f"robot.targets.{key}[{j}] must hold 4 finite numbers")
            check_range(f"robot.targets.{key}[{j}]", "t_s", r[0], 0.0, 1e5, "s")
            check_range(f"robot.targets.{key}[{j}]", "height_mm", r[1], 0.0, U.to_mm(H_TARGET_MAX), "mm")
            check_range(f"robot.targets.{key}[{j}]", "bend_deg", r[2], -60.0, 60.0, "deg")
            th = math.radians(float(r[2]))
            ps = math.radians(float(r[3])) + (math.pi if th < 0 else 0.0)
            parsed.append((float(r[0]), U.mm(float(r[1])), abs(th), math.atan2(math.sin(ps), math.cos(ps))))
        parsed.sort(key=lambda x: x[0])
        for k in (range(N) if key == "all" else [letters.index(key)]):
            if key == "all" and k in out:
                continue
            out[k] = tuple(parsed)
    for k in range(N):
        if k not in out:
            raise ValueError(f"robot.targets: layer {letters[k]} has no rows (give robot.targets.all or "
                             f"robot.targets.{letters[k]})")
        for j, (t, c, th, ps) in enumerate(out[k]):
            h = inverse_kinematics(design.with_(n_layers=1), c, th, ps)[0]
            if h.min() < -5e-5 or h.max() > H_TARGET_MAX + 1e-9:  # 0.05 mm: rounding of the table's numbers
                raise ValueError(f"robot.targets: layer {letters[k]} at t = {t:g} s needs chamber heights "
                                 f"{np.round(U.to_mm(h), 2).tolist()} mm; each must lie in [0, "
                                 f"{U.to_mm(H_TARGET_MAX):g}] mm (raise height_mm or lower bend_deg)")
    return out


def _layer_pose(rows, t: float) -> tuple:
    cur = rows[0]
    for r in rows:
        if t + 1e-9 >= r[0]:
            cur = r
    return cur


def chamber_targets(design: RobotDesign, targets: dict, t: float, cache: dict | None = None) -> np.ndarray:
    """Target chamber heights (3N,), m, at time t (``cache``: a dict reused between calls)."""
    N = design.n_layers
    if cache is not None:
        key = tuple(sum(1 for r in targets[k] if t + 1e-9 >= r[0]) for k in range(N))
        if key not in cache:
            cache[key] = chamber_targets(design, targets, t)
        return cache[key]
    c, th, ps = np.zeros(N), np.zeros(N), np.zeros(N)
    for k in range(N):
        _, c[k], th[k], ps[k] = _layer_pose(targets[k], t)
    return np.maximum(inverse_kinematics(design, c, th, ps).ravel(), 0.0)


def change_times(targets: dict) -> np.ndarray:
    """Sorted times at which any layer's target changes, s (0 included)."""
    ts = {0.0}
    for rows in targets.values():
        ts |= {r[0] for r in rows}
    return np.array(sorted(ts))
