"""What the chamber pressure alone can tell, per regime: observability along real trajectories.

The estimators' state is ``x = [m, W, b, k, c]`` (gas mass kg, load N, pump-flow factor, modulus
factor, dead-volume factor; :mod:`hbma_ctrl.estimators.ekf`). Along rig trajectories (the mismatched rig of
:mod:`hbma_ctrl.sim.rig`, open loop) the EKF's linearisation (A = dx+/dx of the discrete model, H =
dp/dx) gives, at every sample,

- the rank and condition number of the frozen observability matrix ``control.obsv(A, H)``
  (python-control; columns scaled by the state scales ``OBS_SCALE`` so the numbers compare),
- the *window* rank over the next second: the time-varying matrix ``[H_k; H_k+1 A_k; ...]``
  whitened by the sensor noise (rows / 200 Pa) and scaled by ``OBS_SCALE``; its singular values
  >= 1 count the state directions that one second of readings pins down to better than
  ``OBS_SCALE`` (0.1 mg of gas, 0.1 N, 5 % of flow, 5 % of modulus, 5 % of dead volume).

Regimes (from the rig's truth and the command): ``resting`` (membrane flat under the load),
``free`` (no contact), ``contact`` (dead load carried), each ``+flow`` (pump or vent active) or
``+hold`` (valves closed, pump off).

Conclusions (``hbma-ctrl observability``, default actuator r1 12.5 mm, t0 3 mm, mismatched rig;
frozen rank = ``control.obsv(A, H)``, window rank = directions resolved within 1 s):

=================  ===========  ===========  ====================================================
regime             frozen rank  window rank  what the pressure tells
=================  ===========  ===========  ====================================================
resting + flow     1-2          1-2          m and (pumping) the ratio b / c of flow to dead
                                             volume (venting: c); W and k do not enter: only
                                             ``W >= pi r1^2 p``; h = 0 exactly
resting + hold     1            1            the gas mass (the pressure level) only
free/contact+flow  2            1-3 (med 2)  m, and over a window part of (W, b, k, c); W and k
                                             act alike on p (stiffer membrane ~ heavier load)
free/contact+hold  1            1            one combination of (m, W, k): every pair on a level
                                             set of p is an equilibrium
saturated          0            0            only ``p >= range``: the model (mass integration)
                                             carries the estimate, the covariance grows
=================  ===========  ===========  ====================================================

The frozen matrix never exceeds rank 2: with random-walk parameters ``A = I + e0 a^T``, so
``H A^j = H + j (H e0) a^T`` spans at most {H, a}. Only the time variation along a trajectory
(the changing shape as gas flows) reveals more, which is what the window rank measures.

So: h and F are available live from pressure alone while gas flows and after a loaded membrane
has lifted off (the lift-off pressure, a kink in p(t), gives W = pi r1^2 p without any modulus:
the filter detects it); in a hold they are as good as the last flowing phase left them; resting,
h = 0 and the plate force pi r1^2 p are known, the load is not; a lift-off that happens above the
sensor range cannot be seen at all. Two gas masses can give the same pressure past the load
path's pressure maximum (snap-through branch): pressure alone cannot tell the branch; the filter
relies on having tracked the history.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import control
import numpy as np

from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.ekf import EKF
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.actuation import CommandTiming
from hbma_ctrl.models.chamber import NX, STATE_NAMES
from hbma_ctrl.sim.rig import RigSettings, simulate_rig
from hbma_ctrl.sim.trial import InputSchedule, Trial

__all__ = ["OBS_SCALE", "Trajectory", "default_trajectories", "analyse", "summarise", "run"]

#: state resolutions used to scale the observability matrices: m kg, W N, b -, k -, c -
OBS_SCALE = np.array([1e-7, 0.1, 0.05, 0.05, 0.05])
WINDOW_S = 1.0


@dataclass(frozen=True)
class Trajectory:
    """A named open-loop run: load (kg) and input schedule rows (t s, speed, inlet, outlet)."""

    name: str
    load: float
    rows: tuple
    duration: float


def default_trajectories() -> list[Trajectory]:
    """Free inflation, a dead load (resting, lift-off, contact), a load too heavy to lift; each with
    a pumping phase, a hold (valves closed) and a vent."""
    pump_hold_vent = ((0.0, 0.6, 1.0, 0.0), (2.5, 0.0, 0.0, 0.0), (3.5, 0.0, 0.0, 1.0))
    return [
        Trajectory("free", 0.0, pump_hold_vent, 5.0),
        Trajectory("dead_load_400g", 0.4, pump_hold_vent, 5.0),
        Trajectory("resting_3kg", 3.0, pump_hold_vent, 5.0),
    ]


def _regime(truth_h: float, truth_F: float, u: np.ndarray) -> str:
    flow = "flow" if (u[0] * u[1] > 0 or u[2] > 0) else "hold"
    if truth_h <= 1e-5:
        base = "resting"  # flat: under a load, or unpressurised
    elif truth_F > 1e-3:
        base = "contact"
    else:
        base = "free"
    return f"{base}+{flow}"


def _rank_cond(M: np.ndarray, tol: float = 1e-9) -> tuple[int, float, np.ndarray]:
    sv = np.linalg.svd(M, compute_uv=False)
    if sv.size == 0 or sv[0] == 0:
        return 0, float("inf"), sv
    rank = int(np.sum(sv > tol * sv[0]))
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    return rank, cond, sv


def analyse(traj: Trajectory, actuator: Actuator | None = None, pneumatics: Pneumatics | None = None,
            rig: RigSettings | None = None, settings: FilterSettings | None = None,
            every: int = 5) -> list[dict]:
    """Per-sample observability along one trajectory (every ``every``-th sample)."""
    act = actuator or Actuator()
    pn = pneumatics or Pneumatics()
    rs = rig or RigSettings()
    fs = settings or FilterSettings(sample_period=rs.sample_period, sensor_range=rs.sensor_range)
    trial = Trial(act, pn, Platform(load=traj.load, own_mass=0.02 if traj.load > 0 else 0.0),
                  InputSchedule(traj.rows), traj.duration, traj.name)
    (rec,) = simulate_rig([trial], rs)
    ekf = EKF(act, pn, fs)
    As, Hs = [], []
    for k in range(len(rec.t)):
        u = Command(*rec.u[k - 1]) if k > 0 else Command()
        ekf.step(float(rec.t[k]), rec.meas[k], u)
        As.append(ekf.last_A.copy())
        Hs.append(ekf.measurement_jacobian())
    S = np.diag(OBS_SCALE)
    w = 1.0 / fs.noise_std
    nwin = int(round(WINDOW_S / fs.sample_period))
    # each sample's regime is that of the command its linearisation saw: the one acting on the filter's
    # model over the period before it (step k is given the command sent at k - 1, delayed as the filter
    # delays it: a hold's first samples still see the flow of the phase before)
    tm = CommandTiming(fs.sample_period, fs.valve_delay, fs.sensor_delay)
    acting = [tm.acting(rec.u[k - 1] if k else np.zeros(3), 1 if k else 0) for k in range(len(rec.t))]
    regimes = [_regime(rec.truth["h"][k], rec.truth["F"][k], acting[k]) for k in range(len(rec.t))]
    rows = []
    for k in range(1, len(rec.t) - nwin, every):
        A, H = As[k], Hs[k]
        O = control.obsv(A, H) @ S
        rank, cond, _ = _rank_cond(O)
        # time-varying window H_{k+j} Phi(k+j, k), up to 1 s, cut where the regime changes
        n = 1
        while n < nwin and regimes[k + n] == regimes[k]:
            n += 1
        if n < 10:
            continue
        Phi = np.eye(NX)
        blocks = [Hs[k]]
        for j in range(1, n):
            Phi = As[k + j] @ Phi
            blocks.append(Hs[k + j] @ Phi)
        Ow = np.vstack(blocks) * w @ S
        sv = np.linalg.svd(Ow, compute_uv=False)
        rows.append({
            "trajectory": traj.name, "t_s": float(rec.t[k]),
            "regime": regimes[k], "window_s": n * fs.sample_period,
            "rank": rank, "cond": cond,
            "window_rank": int(np.sum(sv >= 1.0)),
            "window_sv": [float(v) for v in sv],
            "h_true_mm": float(rec.truth["h"][k] * 1e3), "p_kpa": float(rec.truth["p"][k] * 1e-3),
        })
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Per (trajectory, regime): samples, median/min/max rank, median condition, window rank."""
    out = []
    keys = sorted({(r["trajectory"], r["regime"]) for r in rows}, key=lambda k: (k[0], k[1]))
    for tr, reg in keys:
        sel = [r for r in rows if r["trajectory"] == tr and r["regime"] == reg]
        ranks = np.array([r["rank"] for r in sel])
        wr = np.array([r["window_rank"] for r in sel])
        conds = np.array([r["cond"] for r in sel])
        out.append({"trajectory": tr, "regime": reg, "samples": len(sel),
                    "rank_median": float(np.median(ranks)), "rank_min": int(ranks.min()), "rank_max": int(ranks.max()),
                    "cond_median": float(np.median(conds[np.isfinite(conds)])) if np.any(np.isfinite(conds)) else None,
                    "window_rank_median": float(np.median(wr)), "window_rank_min": int(wr.min()),
                    "window_rank_max": int(wr.max())})
    return out


def run(out_dir: Path | str, actuator: Actuator | None = None, rig: RigSettings | None = None,
        trajectories: list[Trajectory] | None = None) -> list[dict]:
    """Analyse the trajectories, write ``observability.json`` (summary + samples); return the summary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for tr in trajectories or default_trajectories():
        rows += analyse(tr, actuator, rig=rig)
    summ = summarise(rows)
    with open(out / "observability.json", "w") as fh:
        json.dump({"state": list(STATE_NAMES), "obs_scale": OBS_SCALE.tolist(), "window_s": WINDOW_S,
                   "summary": summ, "samples": rows}, fh, indent=1)
    return summ
