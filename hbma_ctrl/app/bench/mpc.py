"""``hbma-ctrl bench mpc``: the speed/accuracy trade of the controllers on one closed-loop scenario.

Every row runs the same scenario (same rig, mismatch, noise seed, EKF, targets, load) with one
controller: the MPC variants (IPOPT and RTI-OSQP by default; RTI-OSQP with its QP data as one
generated-C call, ``rti_c_osqp``; the RTI step as one casadi Function,
``rti_fn_hpipm`` etc., and fatrop on request) at horizons 10/20/40, the PID, bang-bang and LQI baselines, and do-mpc
(optional extra) solving the same OCP at N = 20. For each: tracking RMSE of the true height (and of
the estimate, which separates the controller's error from the estimator's bias), the
largest true pressure, per-step solve time median/p99/max (wall clock on this machine, including
everything the step does), fallbacks, and how many steps would have overrun a real-time budget.

The MPC rows run without an enforced budget (``budget_ms``, default 1000 ms, acts only when the
scenario sets ``[controller] enforce_budget = true``), so that the accurate variant is measured as the
accuracy reference rather than degraded by fallbacks and no row depends on the machine's load; the
column ``over_rt`` counts the steps slower than the real-time budget (``rt_budget_ms``, default 15 ms),
i.e. the steps that would have fallen back in a rig daemon.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from hbma_ctrl.controllers.dompc_ref import DoMPCController
from hbma_ctrl.core.extras import dompc_available
from hbma_ctrl.controllers.mpc_settings import VARIANTS
from hbma_ctrl.app.endsignals import raise_if_signalled
from hbma_ctrl.app.scenes.controller import closed_loop, loop_metrics
from hbma_ctrl.system.roles import make_controller
from hbma_ctrl.app.schema.document import parse_role
from hbma_ctrl.system.sections import ControllerSection
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["default_section", "run_bench"]

DEFAULT_TARGETS_MM = [[0.0, 2.0], [3.0, 8.0], [6.0, 5.0]]


def default_section() -> ControllerSection:
    """The track_height example: steps 2 -> 8 -> 5 mm, RTI-OSQP N = 20 at 20 ms."""
    return parse_role("controller", {"kind": "mpc", "variant": "rti_osqp", "horizon": 20, "sample_ms": 20.0,
                          "targets_mm": DEFAULT_TARGETS_MM})


#: a row's columns taken from the loop's metrics, in the row's order (``over_rt`` is the bench's own)
_ROW_METRICS = ("height_rmse_mm", "height_rmse_estimate_mm", "max_pressure_kpa", "solve_ms_median", "solve_ms_p99",
                "solve_ms_max", "fallbacks", "solve_cpu_ms_median", "solve_cpu_ms_p99", "over_rt", "steps_settled",
                "steps_settled_estimate", "steps_total", "wall_s")


def _row(name: str, m: dict, rt_ms: float, solve_ms: list) -> dict:
    over_rt = int((np.asarray(solve_ms, float) > rt_ms).sum())
    return {"controller": name, **{k: over_rt if k == "over_rt" else m.get(k) for k in _ROW_METRICS}}


def run_bench(actuator: Actuator | None = None, pneumatics: Pneumatics | None = None,
              platform: Platform | None = None, section: ControllerSection | None = None,
              duration: float = 9.0, variants=("ipopt", "rti_osqp"), horizons=(10, 20, 40),
              baselines: bool = True, dompc: bool = True, budget_ms: float = 1000.0,
              rt_budget_ms: float = 15.0, rig_settings=None, progress=None, ipopt_c: bool = False) -> dict:
    """Run the sweep; returns {"rows": [...], "dompc": status text, "settings": {...}}.

    ``progress(name)`` is called before each row (for a CLI spinner). ``ipopt_c``: one more row,
    "ipopt_c N=20", IPOPT generated as C and built as the fatrop variant is (the shipped IPOPT runs its
    functions on casadi's virtual machine); it needs a C compiler. Raises ValueError on bad arguments
    (names the argument and its range).
    """

    actuator = actuator or Actuator()
    pneumatics = pneumatics or Pneumatics()
    platform = platform or Platform(load=0.4)
    section = section or default_section()
    rs = rig_settings or RigSettings(seed=1)
    for v in variants:
        if v not in VARIANTS:
            raise ValueError(f"bench.variants: unknown '{v}'; allowed {', '.join(VARIANTS)}")
    for n in horizons:
        if not isinstance(n, int) or not 2 <= n <= 200:
            raise ValueError(f"bench.horizons: {n!r} must be an integer in [2, 200]")
    if not 0 < budget_ms <= 1e5:
        raise ValueError(f"bench.budget_ms = {budget_ms!r} is out of range (0, 1e5] ms")
    model = PredictionModel(actuator, pneumatics, load_max=section.mpc.load_max, membrane=section.mpc.membrane)
    rows = []

    def run(name, sec, ctrl=None):
        if progress:
            progress(name)
        c = ctrl or make_controller(sec, actuator, pneumatics, model)
        raise_if_signalled()  # a signal caught inside the last row's solver
        log = closed_loop(actuator, pneumatics, platform, sec, duration, rs, controller=c)
        m = loop_metrics(log, sec)
        rows.append(_row(name, m, rt_budget_ms, log.solve_ms))
        return m

    ipopt_c_row = None
    if ipopt_c:  # built before any row runs: a machine that cannot build it loses no measured row
        from hbma_ctrl.controllers.mpc import NMPC
        from hbma_ctrl.controllers.mpc_solvers import _Ipopt

        mpc = replace(section.mpc, variant="ipopt", horizon=20, budget=U.ms(budget_ms)).validate()
        ctrl = NMPC(actuator, pneumatics, mpc, model=model)
        ctrl.backend = _Ipopt(model, mpc, generate=True)
        ipopt_c_row = (replace(section, kind="mpc", mpc=mpc), ctrl)
    for v in variants:
        for n in horizons:
            mpc = replace(section.mpc, variant=v, horizon=n, budget=U.ms(budget_ms)).validate()
            run(f"{v} N={n}", replace(section, kind="mpc", mpc=mpc))
    if ipopt_c_row is not None:
        run("ipopt_c N=20", *ipopt_c_row)
    if baselines:
        run("pid", replace(section, kind="pid"))
        run("bang_bang", replace(section, kind="bang_bang"))
        run("lqi", replace(section, kind="lqi"))
    dompc_status = "skipped"
    if dompc:

        ok, why = dompc_available()
        if ok:
            mpc = replace(section.mpc, horizon=20, budget=U.ms(budget_ms)).validate()
            sec = replace(section, kind="mpc", mpc=mpc)
            run("do-mpc N=20", sec, DoMPCController(actuator, pneumatics, mpc, model=model))
            dompc_status = f"do-mpc {why}"
        else:
            dompc_status = why
    return {"rows": rows, "dompc": dompc_status,
            "settings": {"duration_s": duration, "load_g": U.to_grams(platform.load), "budget_ms": budget_ms,
                         "rt_budget_ms": rt_budget_ms, "targets_mm": [[t, U.to_mm(h)] for t, h in section.reference.points],
                         "rig_seed": rs.seed}}


#: do-mpc's median step (ms) on this OCP, N = 20, last measured (docs/results/mpc.md)
DOMPC_LAST_MS = 53.2


def summarize(result: dict) -> dict:
    """The bench's targets (RTI at N = 20: median <= 2 ms, p99 <= 5 ms, RMSE against IPOPT N = 20 and do-mpc), checked on a result."""
    by = {r["controller"]: r for r in result["rows"]}
    out = _summarize_new(by)
    rti, ip, dm = by.get("rti_osqp N=20"), by.get("ipopt N=20"), by.get("do-mpc N=20")
    if rti:
        out["rti_median_le_2ms"] = rti["solve_ms_median"] <= 2.0
        out["rti_p99_le_5ms"] = rti["solve_ms_p99"] <= 5.0
    if rti and ip:
        out["rti_rmse_vs_ipopt"] = rti["height_rmse_mm"] / ip["height_rmse_mm"]
        out["rti_rmse_within_10pct"] = rti["height_rmse_mm"] <= 1.1 * ip["height_rmse_mm"]
    if rti and dm:
        out["dompc_over_rti_speed"] = dm["solve_ms_median"] / rti["solve_ms_median"]
        out["rti_10x_faster_than_dompc"] = out["dompc_over_rti_speed"] >= 10.0
        if rti.get("solve_cpu_ms_median") and dm.get("solve_cpu_ms_median"):
            out["dompc_over_rti_speed_cpu"] = dm["solve_cpu_ms_median"] / rti["solve_cpu_ms_median"]
    if rti and rti.get("solve_cpu_ms_median") is not None:
        out["rti_cpu_median_le_2ms"] = rti["solve_cpu_ms_median"] <= 2.0
        out["rti_cpu_p99_le_5ms"] = rti["solve_cpu_ms_p99"] <= 5.0
    return out


def _summarize_new(by: dict) -> dict:
    """The step-time and accuracy targets for every RTI and fatrop row at N = 20: median <= 0.2 ms,
    p99 <= 0.5 ms, RMSE within 1 % of IPOPT, >= 250x do-mpc (measured in this run, else
    :data:`DOMPC_LAST_MS`); fatrop >= 5x faster than IPOPT at the same RMSE (within 1 %)."""
    out = {}
    ip, dm = by.get("ipopt N=20"), by.get("do-mpc N=20")
    dm_ms, dm_src = (dm["solve_ms_median"], "measured") if dm else (DOMPC_LAST_MS, "last measured")
    for name, row in by.items():
        v = name.split(" ")[0]
        if not name.endswith("N=20") or not (v.startswith("rti_") or v == "fatrop"):
            continue
        if ip:
            out[f"{v}_rmse_vs_ipopt"] = row["height_rmse_mm"] / ip["height_rmse_mm"]
            out[f"{v}_rmse_within_1pct"] = row["height_rmse_mm"] <= 1.01 * ip["height_rmse_mm"]
        if v == "fatrop":
            if ip:
                out["ipopt_over_fatrop_speed"] = ip["solve_ms_median"] / row["solve_ms_median"]
                out["fatrop_5x_faster_than_ipopt"] = out["ipopt_over_fatrop_speed"] >= 5.0
            gen = by.get("ipopt_c N=20")
            if gen:  # the same comparison with IPOPT generated as C too
                out["ipopt_c_over_fatrop_speed"] = gen["solve_ms_median"] / row["solve_ms_median"]
                out["fatrop_5x_faster_than_ipopt_c"] = out["ipopt_c_over_fatrop_speed"] >= 5.0
            continue
        out[f"{v}_median_le_0.2ms"] = row["solve_ms_median"] <= 0.2
        out[f"{v}_p99_le_0.5ms"] = row["solve_ms_p99"] <= 0.5
        out[f"dompc_over_{v}_speed ({dm_src} do-mpc)"] = dm_ms / row["solve_ms_median"]
        out[f"{v}_250x_faster_than_dompc"] = dm_ms / row["solve_ms_median"] >= 250.0
    return out


def write_bench(result: dict, out_dir: Path) -> Path:
    """bench_mpc.json in out_dir (created)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    p = out_dir / "bench_mpc.json"
    p.write_text(json.dumps({**result, "summary": summarize(result), "written": time.strftime("%Y-%m-%dT%H:%M:%S")},
                            indent=2, default=float))
    return p
