"""Closed-loop robustness over rig noise seeds: ``hbma-ctrl bench loop``.

The closed-loop cases on the mismatched rig (modulus x1.15, flow x0.9, dead volume x1.2,
0.2 kPa noise), each through the full chain rig -> EKF -> RTI-OSQP NMPC -> rig, repeated over rig
seeds (each seed is another noise and dropout stream, not another rig):

- ``steps_0g`` / ``steps_400g``: height steps 2 -> 8 -> 5 mm (at 0, 2 and 4.5 s, 7 s), settled when
  the TRUE height stays within 0.3 mm (the section's settle band) to the end of each step;
- ``load_step_200g``: 400 g holding 5 mm, +200 g at 2 s (6 s), rejected when the true height is
  within 0.3 mm of 5 mm over the last second.

The unit tests run one seed of each (tests/test_closed_loop.py); this sweep says how often they
hold. Results: per run and a per-case summary (runs passing, worst final error, highest pressure),
written to ``bench_loop.json``.

``rig="structured"`` judges the loop on the truth that differs in structure
(:data:`hbma_ctrl.sim.rig.STRUCTURED_RIG`: the exact membrane with plate contact, 5 ms valve delay,
2 ms minimum valve opening, a pump map of another shape, a 3 ms first-order sensor lag). The EKF,
its start-up calibration and the MPC then take the exact membrane law and model the valve and sensor
timing as dead times (``valve_delay_ms``, ``sensor_delay_ms``: a rig's datasheet values, 5 and 3 ms
by default there; pass others to see what a wrong datasheet costs), and the loop sends small valve
duties as minimum-length pulses (``valve_min_on_ms``, 2 ms there).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from hbma_ctrl.app.bench import map_jobs
from hbma_ctrl.estimators.common import FACTOR_RANGE
from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.app.scenes.controller import closed_loop, loop_metrics
from hbma_ctrl.app.schema.document import parse_role
from hbma_ctrl.system.sections import ControllerSection
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.models.defaults import DEFAULT_SENSOR_DELAY, DEFAULT_VALVE_DELAY, DEFAULT_VALVE_MIN_ON
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.sim.rig import CAP_RIG, STRUCTURED_RIG, RigSettings

__all__ = ["CASES", "RIGS", "check_cases", "run_case", "run_loop_bench", "summarize_loop", "write_loop_bench",
           "loop_setup"]

#: the truths the loop is judged on: the scalar-mismatch cap rig, or the structurally different one
RIGS = ("cap", "structured")

STEPS_MM = [[0.0, 2.0], [2.0, 8.0], [4.5, 5.0]]
#: case -> (controller section, load kg, duration s)
CASES = {
    "steps_0g": ({"targets_mm": STEPS_MM}, 0.0, 7.0),
    "steps_400g": ({"targets_mm": STEPS_MM}, 0.4, 7.0),
    "load_step_200g": ({"targets_mm": [[0.0, 5.0]], "load_steps_g": [[2.0, 600.0]]}, 0.4, 6.0),
}
TAIL_S = 1.0  # the load step's rejection window: the last second


def loop_setup(rig: str = "structured", membrane: str | None = None, valve_delay_ms: float | None = None,
               sensor_delay_ms: float | None = None, valve_min_on_ms: float | None = None,
               calibration_std_floor: float | None = None, prior: str | None = None,
               prior_std: float | None = None) -> dict:
    """The bench's truth and models: the rig, the models' membrane law (default: the rig's), the
    delays the estimator and the calibration model and the valves' minimum opening the loop shapes
    its duties for (ms; default 5, 3 and 2 on the structured rig, the default, as in
    :mod:`hbma_ctrl.models.defaults`; 0 on the cap rig). Raises
    ValueError naming the flag on a bad value. ``calibration_std_floor``: the calibration prior's
    sigma floor (default: the controller's, 0.08). ``prior``: the EKF's (and so the start-up
    calibration's) prior on its flow, modulus and dead-volume factors, "b,k,c" (a fit's; default the
    nominal 1,1,1), with one sigma ``prior_std`` for each (default the filter's 0.15, 0.15, 0.2)."""
    if rig not in RIGS:
        raise ValueError(f"--rig: '{rig}' is unknown{did_you_mean(rig, RIGS)}; allowed {', '.join(RIGS)}")
    structured = rig == "structured"
    membrane = membrane or ("exact" if structured else "cap")
    if membrane not in ("cap", "exact"):
        raise ValueError(f"--membrane: '{membrane}' is unknown; allowed cap, exact")
    models = ({"valve_delay_ms": DEFAULT_VALVE_DELAY, "sensor_delay_ms": DEFAULT_SENSOR_DELAY,
               "valve_min_on_ms": DEFAULT_VALVE_MIN_ON} if structured else {})
    given = {"valve_delay_ms": valve_delay_ms, "sensor_delay_ms": sensor_delay_ms, "valve_min_on_ms": valve_min_on_ms}
    out = {"rig": rig, "membrane": membrane}
    for key, v in given.items():
        out[key] = U.to_ms(models.get(key, 0.0)) if v is None else float(v)
    out["calibration_std_floor"] = (ControllerSection.calibration_std_floor if calibration_std_floor is None
                                    else float(calibration_std_floor))
    if not 0.0 <= out["calibration_std_floor"] <= 1.0:
        raise ValueError(f"--calibration-std-floor = {out['calibration_std_floor']:g} is out of range [0, 1]")
    for key in ("valve_delay_ms", "sensor_delay_ms", "valve_min_on_ms"):
        if not 0.0 <= out[key] <= 100.0:
            raise ValueError(f"--{key.replace('_', '-')} = {out[key]:g} is out of range [0, 100] ms")
    if prior is not None:
        try:
            vals = [float(v) for v in prior.split(",")]
        except ValueError:
            raise ValueError(f"--prior = '{prior}': three numbers b,k,c (the flow, modulus and dead-volume "
                             "factors)") from None
        if len(vals) != 3 or not all(FACTOR_RANGE[0] <= v <= FACTOR_RANGE[1] for v in vals):
            raise ValueError(f"--prior = '{prior}': three factors b,k,c, each in [{FACTOR_RANGE[0]:g}, "
                             f"{FACTOR_RANGE[1]:g}]")
        out["prior"] = vals
    if prior_std is not None:
        if not (math.isfinite(prior_std) and 0.0 < prior_std <= 10.0):
            raise ValueError(f"--prior-std = {prior_std:g} is out of range (0, 10]")
        out["prior_std"] = float(prior_std)
    return out


def _prior_settings(setup: dict) -> dict:
    """EKFSettings fields of the setup's factor prior (none: the filter's defaults)."""
    kw = {}
    if "prior" in setup:
        kw.update(zip(("flow_factor_init", "modulus_init", "dead_volume_init"), setup["prior"]))
    if "prior_std" in setup:
        kw.update({k: setup["prior_std"] for k in ("flow_factor_init_std", "modulus_init_std", "dead_volume_init_std")})
    return kw


def run_case(case: str, seed: int, setup: dict | None = None) -> dict:
    """One closed loop of ``case`` on the rig with noise seed ``seed``; ``setup`` from
    :func:`loop_setup` (default: the cap rig and models). Edge units out."""

    setup = setup or loop_setup()
    raw, load, duration = CASES[case]
    act, pn = Actuator(), Pneumatics()
    sec = replace(parse_role("controller", raw), valve_min_on=U.ms(setup.get("valve_min_on_ms", 0.0)),
                  calibration_std_floor=setup.get("calibration_std_floor", ControllerSection.calibration_std_floor))
    rs = RigSettings(seed=seed, **(STRUCTURED_RIG if setup["rig"] == "structured" else CAP_RIG))
    est = EKF(act, pn, EKFSettings(sample_period=rs.sample_period, noise_std=max(rs.noise_std, 1.0),
                                   sensor_range=rs.sensor_range, membrane=setup["membrane"],
                                   valve_delay=U.ms(setup["valve_delay_ms"]),
                                   sensor_delay=U.ms(setup["sensor_delay_ms"]), **_prior_settings(setup)))
    log = closed_loop(act, pn, Platform(load=load), sec, duration, rs, estimator=est,
                      model=PredictionModel(act, pn, membrane=setup["membrane"]))
    m = loop_metrics(log, sec)
    row = {"case": case, "seed": seed, "max_pressure_kpa": m["max_pressure_kpa"],
           "pressure_limit_kpa": m["pressure_limit_kpa"], "fallbacks": m["fallbacks"],
           "solve_ms_median": m["solve_ms_median"], "calibration": m.get("calibration")}
    if case == "load_step_200g":
        # the band and the held target are the section's (settle band, last target)
        tail = log.t >= duration - TAIL_S
        err = np.abs(log.h_true[tail] - log.target[tail])
        row.update(passed=bool(np.all(err < sec.settle_band)), final_error_mm=float(U.to_mm(np.max(err))))
    else:
        errs = [s["final_error_mm"] for s in m["settle"]]
        row.update(passed=m["steps_settled"] == len(m["settle"]), steps_settled=m["steps_settled"],
                   final_errors_mm=errs, final_error_mm=float(np.max(np.abs(errs))))
    return row


def check_cases(cases: list[str]) -> list[str]:
    """The case names as given; ValueError naming ``--cases`` and the allowed names on an unknown one."""
    for c in cases:
        if c not in CASES:
            raise ValueError(f"--cases: '{c}' is unknown{did_you_mean(c, CASES)}; allowed {', '.join(CASES)}")
    return list(cases)


def _run(args) -> dict:
    return run_case(*args)


def run_loop_bench(seeds: list[int], cases: list[str] | None = None, workers: int = 2,
                   progress=None, setup: dict | None = None) -> list[dict]:
    """Every case x seed (processes in parallel) on ``setup`` (:func:`loop_setup`); rows in case,
    seed order."""
    setup = setup or loop_setup()
    cases = check_cases(cases or list(CASES))
    return map_jobs(_run, [(c, s, setup) for c in cases for s in seeds], workers, progress)


def summarize_loop(rows: list[dict]) -> dict:
    """Per case: runs passing / runs, worst final error (mm), highest pressure (kPa), fallbacks."""
    out = {}
    for case in dict.fromkeys(r["case"] for r in rows):
        sel = [r for r in rows if r["case"] == case]
        out[case] = {"passed": sum(r["passed"] for r in sel), "runs": len(sel),
                     "final_error_mm_max": max(r["final_error_mm"] for r in sel),
                     "final_error_mm_median": float(np.median([r["final_error_mm"] for r in sel])),
                     "max_pressure_kpa": max(r["max_pressure_kpa"] for r in sel),
                     "pressure_limit_kpa": sel[0]["pressure_limit_kpa"],
                     "fallbacks": sum(r["fallbacks"] for r in sel)}
    return out


def write_loop_bench(rows: list[dict], out_dir: Path | str, setup: dict | None = None) -> Path:
    """bench_loop.json (the setup, rows and summary) in out_dir (created)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = out / "bench_loop.json"
    p.write_text(json.dumps({"setup": setup or loop_setup(), "rows": rows, "summary": summarize_loop(rows),
                             "written": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=2, default=float))
    return p
