"""Robot targets: per-layer centre height, bend angle and direction over time -> chamber heights (SI).
"""

from __future__ import annotations

import numpy as np

from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.kinematics import inverse_kinematics


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
