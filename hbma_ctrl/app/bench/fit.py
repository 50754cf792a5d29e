"""``hbma-ctrl bench fit``: what the fit's membrane law does to the numbers it finds (docs/how-to/fit.md).

Two parts, both against a truth that is not the law being fitted:

- **static**: points of the exact axisymmetric membrane's own solver
  (:class:`~hbma_ctrl.models.exact.ExactMembrane`, not the tables the exact fit evaluates), r1 12.5 mm,
  t0 3 mm: nh (modulus 15 % above nominal) in free inflation at 8 heights from 1 to 14 mm and on a
  loose flat plate at 2, 4 and 6 mm pressed 3 and 8 kPa above the free pressure there (its force the
  solver's); and the other four materials (their default parameters, mr's moduli 15 % above) in free
  inflation at 10 heights from 1 to 14 mm. Each fitted with the cap's law and the exact one
  (:func:`hbma_ctrl.app.tuning.fit.fit_static`: nh through the tables, the others through the solver).
- **runs**: a 4 s pump / hold / vent run (pump at 60 %, hold, pump at 100 %, half-open outlet, hold,
  vent; free inflation; pressure and height) of the simulated rig, modulus x1.15, pump x0.9, dead
  volume x1.2, 0.2 kPa noise, on three truths: the cap, the exact membrane, and the default rig (the
  exact membrane plus valve timing, a pump map of another shape and a sensor lag); over rig noise
  seeds 0..seeds-1, each fitted with both laws (:func:`hbma_ctrl.app.tuning.fit_dynamic.fit_dynamic`). The
  commands are replayed as acting at once on the first two rigs (they have no timing) and with the
  CLI's default dead times on the default rig.

Writes ``bench_fit.json``: every fit (found values, 95 % intervals, NRMSD, whether the residual is
structured) and the summary per (rig, law): the range over the seeds of each parameter.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hbma_ctrl.app.bench import map_jobs
from hbma_ctrl.app.metrics import json_safe
from hbma_ctrl.core import units as U

__all__ = ["STATIC_CASES", "OTHER_TRUTHS", "RUN_RIGS", "PUMP_HOLD_VENT", "LAWS", "TRUTH", "static_rows", "run_rows", "summarize_runs",
           "write_fit_bench"]

#: the laws a fit can take
LAWS = ("cap", "exact")
#: the truths of the recorded runs (docs/how-to/fit.md, "Which membrane law")
RUN_RIGS = ("cap", "exact", "default")
STATIC_CASES = ("free", "flat", "free_mr", "free_gent", "free_yeoh", "free_ogden")
#: the rig's scalar mismatches (the nominal chamber times these)
TRUTH = {"modulus_scale": 1.15, "flow_scale": 0.9, "V0_scale": 1.2}
R1, T0, V0 = U.mm(12.5), U.mm(3.0), U.cm3(3.0)
#: pump at 60 %, hold shut, pump at 100 %, half-open outlet, hold, vent (t s, speed, inlet, outlet)
PUMP_HOLD_VENT = ((0.0, 0.6, 1.0, 0.0), (1.2, 0.0, 0.0, 0.0), (1.6, 1.0, 1.0, 0.0), (2.4, 0.0, 0.0, 0.5),
                  (2.9, 0.0, 0.0, 0.0), (3.2, 0.0, 0.0, 1.0))


#: the other materials' truths (SI): their defaults, mr's moduli 15 % above them
OTHER_TRUTHS = {"mr": {"C1": 23e3, "C2": 2.3e3}, "gent": {}, "yeoh": {}, "ogden": {}}


def static_rows(progress=None) -> list[dict]:
    """The static part (module doc): per case and law, each parameter found over the truth's, the
    largest relative miss, the NRMSD, what the data cannot determine and the fit's wall time (s).
    ``progress(row)`` after each fit."""
    import time

    from hbma_ctrl.app.tuning.fit import StaticData, fit_static, param_names
    from hbma_ctrl.core.materials import make_material
    from hbma_ctrl.core.params import Actuator
    from hbma_ctrl.core.physics import ParamSpace
    from hbma_ctrl.models.exact import ExactMembrane

    E = TRUTH["modulus_scale"] * make_material("nh").E
    m = ExactMembrane(make_material("nh", E=E), R1, T0)
    h = U.mm(np.linspace(1.0, 14.0, 8))
    cases = {"free": ("nh", {"E": E}, StaticData(h, np.array([m.free(x)["p"] for x in h])))}
    pts = [(U.mm(hm), m.free(U.mm(hm))["p"] + dp) for hm in (2.0, 4.0, 6.0) for dp in (3e3, 8e3)]
    hf, pf = np.array([a for a, _ in pts]), np.array([b for _, b in pts])
    cases["flat"] = ("nh", {"E": E}, StaticData(hf, pf, np.array([m.contact(a, b)["F"] for a, b in pts]), "F_n"))
    h10 = U.mm(np.linspace(1.0, 14.0, 10))
    for name, kw in OTHER_TRUTHS.items():
        mat = make_material(name, **kw)
        space = ParamSpace.for_material(mat)
        flat = dict(zip(space.names, space.values(Actuator(material=mat)).tolist()))
        mo = ExactMembrane(mat, R1, T0)
        cases[f"free_{name}"] = (name, {k: flat[k] for k in param_names(name)},
                                 StaticData(h10, np.array([mo.free(x)["p"] for x in h10])))
    rows = []
    for case in STATIC_CASES:
        material, truth, data = cases[case]
        for law in LAWS:
            t0 = time.perf_counter()
            res = fit_static(data, material, R1, T0, fidelity=law)
            ratio = {k: res.params[k] / v for k, v in truth.items()}
            row = {"case": case, "material": material, "law": law, "n_points": res.n_points,
                   "found_over_truth": ratio, "worst_rel_miss": max(abs(r - 1) for r in ratio.values()),
                   "nrmsd": res.nrmsd, "unidentifiable": res.unidentifiable, "wall_s": time.perf_counter() - t0}
            if material == "nh":
                row["E_found_over_truth"] = ratio["E"]
            rows.append(row)
            if progress:
                progress(row)
    return rows


def _rig_settings(rig: str, seed: int):
    from hbma_ctrl.sim.rig import CAP_RIG, STRUCTURED_RIG, RigSettings

    base = {"cap": CAP_RIG, "exact": {**CAP_RIG, "membrane": "exact"}, "default": STRUCTURED_RIG}[rig]
    return RigSettings(**{**base, **TRUTH, "noise_std": 200.0, "seed": int(seed)})


def _one_run(args) -> list[dict]:
    """Both laws' fits of one rig run (a worker's task)."""
    from hbma_ctrl.app.tuning.fit_dynamic import fit_dynamic
    from hbma_ctrl.app.tuning.run_data import RunData
    from hbma_ctrl.core.materials import make_material
    from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
    from hbma_ctrl.models.defaults import DEFAULT_SENSOR_DELAY, DEFAULT_VALVE_DELAY
    from hbma_ctrl.sim.rig import simulate_rig
    from hbma_ctrl.sim.trial import InputSchedule, Trial

    rig, seed = args
    act = Actuator(r1=R1, t0=T0, V0=V0, material=make_material("nh"))
    trial = Trial(actuator=act, pneumatics=Pneumatics(), platform=Platform(), schedule=InputSchedule(PUMP_HOLD_VENT),
                  duration=4.0)
    (rec,) = simulate_rig([trial], _rig_settings(rig, seed))
    run = RunData(rec.t - rec.t[0], rec.meas.copy(), rec.u.copy(), rec.truth["h"].copy(), 0.0,
                  {"p": "p_meas_kpa", "h": "h_true_mm"})
    delays = (DEFAULT_VALVE_DELAY, DEFAULT_SENSOR_DELAY) if rig == "default" else (0.0, 0.0)
    rows = []
    for law in LAWS:
        r = fit_dynamic(run, "nh", R1, T0, V0=V0, fidelity=law, valve_delay=delays[0], sensor_delay=delays[1])
        me = r.model_error()
        rows.append({"rig": rig, "seed": int(seed), "law": law, "valve_delay_ms": U.to_ms(delays[0]),
                     "sensor_delay_ms": U.to_ms(delays[1]), "params": r.params, "ci95": r.ci95, "nrmsd": r.nrmsd,
                     "nrmsd_h": r.nrmsd_h, "structured": bool(me["structured"]),
                     "residual_rms_kpa": me["residual_rms_kpa"], "white_noise_kpa": me["white_noise_kpa"]})
    return rows


def run_rows(seeds: list[int], rigs=RUN_RIGS, workers: int = 1, progress=None) -> list[dict]:
    """The runs part (module doc) over ``seeds`` and ``rigs``; ``progress(rows)`` after each run."""
    tasks = [(rig, s) for s in seeds for rig in rigs]
    return [row for rows in map_jobs(_one_run, tasks, workers, progress) for row in rows]


def summarize_runs(rows: list[dict]) -> dict:
    """Per 'rig/law': runs, the range [min, max] over the seeds of modulus_scale, V0 (cm^3), flow_scale,
    C_out (1e-10 m^3/(s Pa)) and the pressure NRMSD, and how many residuals were structured."""
    out: dict = {}
    for key in sorted({(r["rig"], r["law"]) for r in rows}, key=lambda k: (RUN_RIGS.index(k[0]), LAWS.index(k[1]))):
        sel = [r for r in rows if (r["rig"], r["law"]) == key]

        def rng(vals):
            return [float(min(vals)), float(max(vals))]

        out[f"{key[0]}/{key[1]}"] = {
            "runs": len(sel),
            "modulus_scale": rng([r["params"]["modulus_scale"] for r in sel]),
            "V0_cm3": rng([U.to_cm3(r["params"]["V0"]) for r in sel]),
            "flow_scale": rng([r["params"]["flow_scale"] for r in sel]),
            "C_out_1e10": rng([r["params"]["C_out"] * 1e10 for r in sel]),
            "nrmsd": rng([r["nrmsd"] for r in sel]),
            "structured": int(sum(r["structured"] for r in sel)),
        }
    return out


def write_fit_bench(static: list[dict], runs: list[dict], folder: Path, seeds: int) -> Path:
    """bench_fit.json in ``folder``: the truth, the static rows, every run's fits and their summary."""
    path = Path(folder) / "bench_fit.json"
    from hbma_ctrl.core.params import Valve

    doc = {"truth": {**TRUTH, "C_out": Valve().C}, "seeds": int(seeds), "static": static, "runs": runs,
           "summary": summarize_runs(runs)}
    path.write_text(json.dumps(json_safe(doc), indent=1) + "\n")
    return path
