"""The results page of each bench (:class:`hbma_ctrl.app.bench.report.Page`) from the result it returns:
its title, what it measures (its own docstring), its tables (user units in the headers, ratios
measured in the same run) and, for the speed/accuracy benches, its Pareto figure.
:mod:`hbma_ctrl.app.bench.report` writes them; one function per ``hbma-ctrl bench`` subcommand.
"""

from __future__ import annotations

import statistics

from hbma_ctrl.app.bench.report import Page, Pareto, Table, docstring_paragraph, fmt, ratio

__all__ = ["sim_page", "protocol_page", "ekf_page", "loop_page", "mpc_page", "robot_page", "fit_page", "soak_page",
           "drills_page", "poses_page", "api_page", "live_page", "codegen_page"]


def sim_page(rows: list, meta: dict) -> Page:
    """``bench sim``: rows (:class:`hbma_ctrl.app.bench.sim.BenchRow`) and the ``meta`` of its bench.json."""
    from hbma_ctrl.app.bench import sim
    from hbma_ctrl.app.bench.plots import _MARKERS, sim_panels

    axis = bool(meta.get("fidelity_axis"))
    ref = next((r for r in rows if r.default), rows[0] if rows else None)
    cols = ["fidelity", "integrator", "step (ms)", "wall (s)", "wall / default", "CPU (s)", "diverged",
            "h NRMSD mean (-)", "h NRMSD max (-)", "p NRMSD mean (-)", "p NRMSD max (-)", "meets target"]
    cols += ["h NRMSD vs exact (-)", "p NRMSD vs exact (-)"] if axis else []
    table = []
    for r in rows:
        step = (f"default {r.dt_free_ms:g}/{r.dt_loaded_ms:g}" if r.dt_ms is None else f"{r.dt_ms:g}")
        row = [r.fidelity + (" (0 g)" if r.fidelity == "free" else ""), r.integrator, step + (" *" if r.default else ""),
               fmt(r.wall_s), ratio(r.wall_s, ref.wall_s), fmt(r.cpu_s), str(r.n_diverged),
               *(fmt(getattr(r, k), ".2e") for k in ("height_nrmsd_mean", "height_nrmsd_max", "pressure_nrmsd_mean",
                                                      "pressure_nrmsd_max")), fmt(r.meets_target)]
        if axis:
            row += [fmt(r.height_nrmsd_vs_exact_mean, ".2e"), fmt(r.pressure_nrmsd_vs_exact_mean, ".2e")]
        table.append(row)
    n = meta.get("n_trials", "?")
    notes = [f"{n} trials, material {meta.get('material')}, {meta.get('workers')} worker(s), median of "
             f"{meta.get('repeat')} timed run(s) per row; NRMSD against the Radau reference of the same fidelity "
             f"(rtol {sim.REF_RTOL:g}).",
             f"Target: wall <= {sim.TARGET_WALL_S:g} s and max NRMSD <= {sim.TARGET_NRMSD:g}; * marks the setting "
             "`hbma-ctrl protocol` uses (free for 0 g trials, quasi_static for loaded ones)."]
    figs = []
    if axis:
        notes.append(f"vs exact: mean NRMSD against the exact membrane (rk4 at {sim.EXACT_REF_DT * 1e3:g} ms); "
                     "free (0 g): the cap's free inflation on the 0 g trials only; exact: its own step error.")
        figs.append(Pareto("sim_pareto", f"bench sim: wall time vs accuracy, {n} trials",
                           "wall time of the protocol (s)", sim_panels(rows), _MARKERS))
    return Page("Simulator speed and accuracy (bench sim)", docstring_paragraph(sim.__doc__, slice(0, 2)),
                [Table("Integrator x step x fidelity over the protocol", cols, table)], figs, notes)


def protocol_page(res: dict) -> Page:
    """``bench protocol``: its bench.json dict."""
    from hbma_ctrl.app.bench import protocol

    rows = res["rows"]
    ref = rows["protocol"]["median_s"]
    table = [[name, fmt(r["median_s"]), fmt(r["min_s"]), fmt(r["max_s"]), ratio(r["median_s"], ref)]
             for name, r in rows.items()]
    return Page("The protocol as a user waits for it (bench protocol)",
                docstring_paragraph(protocol.__doc__, slice(0, 2)),
                [Table(f"Wall time, {res['repeat']} timed runs per row", ["run", "median (s)", "min (s)", "max (s)",
                                                                          "median / protocol"], table)],
                notes=[f"Target: the protocol in <= {res['target_wall_s']:g} s: "
                       f"{'met' if res['meets_target'] else 'not met'} here."])


def ekf_page(res: dict, run_doc: str, command_doc: str) -> Page:
    """``bench ekf``: the result of :func:`hbma_ctrl.app.cli.estimators.bench_ekf`; ``run_doc`` and
    ``command_doc``: that function's and its command's docstrings (what the page says is measured)."""
    from hbma_ctrl.app.bench.plots import estimator_result_points

    f = res["filters"]
    ref = f.get("ekf", {}).get("step_us_median")
    keys = [("step median (us)", "step_us_median", ".3g"), ("step p90 (us)", "step_us_p90", ".3g"),
            ("height NRMSD (-)", "height_nrmsd", ".3f"), ("worst height NRMSD (-)", "height_nrmsd_max", ".3f"),
            ("open loop NRMSD (-)", "height_nrmsd_open_loop", ".3f"), ("force RMSE (N)", "force_rmse_n", ".3f"),
            ("NEES (-)", "nees_mean", ".2f"), ("NIS (-)", "nis_mean", ".2f")]
    table = [[name, fmt(a.get("step_us_median"), ".3g"), fmt(a.get("step_us_p90"), ".3g"),
              ratio(a.get("step_us_median"), ref), *(fmt(a.get(k), s) for _, k, s in keys[2:])]
             for name, a in f.items()]
    s = res["settings"]
    # the docstring's "Returns {...};" names the result's keys, the rest of it says what they measure
    timings = docstring_paragraph(run_doc, 2).partition("; ")[2]
    about = (docstring_paragraph(command_doc) + " " + timings[:1].upper() + timings[1:]
             + f" The truth: the simulated rig, {s['rig']}, on {s['n_trials']} protocol trials ({s['grid']}).")
    n = s["n_trials"]
    return Page("Estimators: step time and accuracy (bench ekf)", about,
                [Table(f"Filters on the same {n} rig runs", ["filter", *(c for c, _, _ in keys[:2]), "step / ekf",
                                                              *(c for c, _, _ in keys[2:])], table)],
                [Pareto("ekf_pareto", f"bench ekf: filter step vs accuracy, {n} rig trials",
                        "median filter step (us)", [("height NRMSD, mean over trials (-)",
                                                     estimator_result_points(res))])],
                ["us: wall time per predict + update of one chamber on this machine.", *_ekf_summary(res)])


def _ekf_summary(res: dict) -> list[str]:
    """The summary's lines of an ``bench ekf`` result: the MHE's own steps and do-mpc's MHE beside it."""
    sm = res.get("summary", {})
    out = []
    if "mhe_step_us_median" in sm:
        out.append(f"MHE's own steps (after its window fills), the summary's window: median "
                   f"{fmt(sm['mhe_step_us_median'], '.3g')} us, p99 {fmt(sm['mhe_step_us_p99'], '.3g')} us.")
    if "dompc_mhe_over_mhe_speed" in sm:
        out.append(f"do-mpc's MHE on the same problem and samples ({sm['dompc_steps']} steps, the same run): median "
                   f"{fmt(sm['dompc_mhe_step_us_median'] / 1e3, '.4g')} ms per step against "
                   f"{fmt(sm['dompc_compare_mhe_step_us_median'], '.3g')} us, "
                   f"{sm['dompc_mhe_over_mhe_speed']:,.0f}x; their pressure estimates differ by "
                   f"{fmt(sm['dompc_vs_mhe_pressure_rms_pa'], '.3g')} Pa RMS.")
    elif "dompc" in sm:
        out.append(f"do-mpc's MHE: not measured ({sm['dompc']}).")
    return out


def loop_page(rows: list[dict], setup: dict) -> Page:
    """``bench loop``: its rows (one closed loop per case x seed) and setup."""
    from hbma_ctrl.app.bench import loop

    summ = loop.summarize_loop(rows)
    table = [[case, f"{v['passed']}/{v['runs']}", fmt(v["final_error_mm_median"], ".3f"),
              fmt(v["final_error_mm_max"], ".3f"),
              fmt(statistics.median(r["solve_ms_median"] for r in rows if r["case"] == case), ".3g"),
              fmt(v["max_pressure_kpa"], ".2f"), fmt(v["pressure_limit_kpa"], "g"), str(v["fallbacks"])]
             for case, v in summ.items()]
    panels = [(f"{case}: final error (mm)", [(str(r["seed"]), (case, ""), r["solve_ms_median"],
                                              r["final_error_mm"]) for r in rows if r["case"] == case])
              for case in summ]
    seeds = len({r["seed"] for r in rows})
    return Page("Closed loop over rig seeds (bench loop)", docstring_paragraph(loop.__doc__, slice(0, 3)),
                [Table(f"{setup['rig']} rig -> EKF -> RTI-OSQP -> rig, {setup['membrane']} models, delays "
                       f"{setup['valve_delay_ms']:g} + {setup['sensor_delay_ms']:g} ms, {seeds} seeds per case",
                       ["case", "passed", "final error median (mm)", "worst (mm)", "solve median (ms)",
                        "max p (kPa)", "limit (kPa)", "fallbacks"], table)],
                [Pareto("loop_pareto", "bench loop: NMPC solve time vs final error, one point per seed",
                        "median NMPC solve per step (ms)", panels)],
                ["pass: the true height within the settle band (0.3 mm) to the end of each step; solve: median wall "
                 "time of one NMPC step in the run, median over the seeds."])


def mpc_page(res: dict) -> Page:
    """``bench mpc``: the result of :func:`hbma_ctrl.app.bench.mpc.run_bench`."""
    from hbma_ctrl.app.bench import mpc
    from hbma_ctrl.app.bench.plots import controller_result_points

    rows = res["rows"]
    ref = next((r for r in rows if r["controller"] == "rti_osqp N=20"), rows[0])
    table = [[r["controller"], fmt(r["height_rmse_mm"], ".3f"), fmt(r["height_rmse_estimate_mm"], ".3f"),
              fmt(r["max_pressure_kpa"], ".2f"), fmt(r["solve_ms_median"], ".3g"), fmt(r["solve_ms_p99"], ".3g"),
              ratio(r["solve_ms_median"], ref["solve_ms_median"]), fmt(r["fallbacks"]), fmt(r["over_rt"]),
              f"{r['steps_settled']}/{r['steps_total']}"] for r in rows]
    st = res["settings"]
    return Page("Controllers: solve time and tracking (bench mpc)", docstring_paragraph(mpc.__doc__, slice(0, 2)),
                [Table(f"{st['load_g']:g} g, targets {st['targets_mm']} mm",
                       ["controller", "height RMSE (mm)", "estimate RMSE (mm)", "max p (kPa)", "solve median (ms)",
                        "solve p99 (ms)", f"solve / {ref['controller']}", "fallbacks", "over real-time budget",
                        "steps settled"], table)],
                [Pareto("mpc_pareto", "bench mpc: solve time vs tracking error", "median solve time per step (ms)",
                        [("height RMSE (mm)", controller_result_points(rows))])],
                [f"do-mpc: {res.get('dompc')}"])


def robot_page(res: dict) -> Page:
    """``bench robot``: its bench_robot.json dict."""
    from hbma_ctrl.app.scenes.robot_closed import bench_robot

    rows = res["rows"]
    ref = rows[0]["step_ms_median"] if rows else None
    table = [[str(r["layers"]), str(r["chambers"]), str(r["qp_variables"]), fmt(r["step_ms_median"], ".3g"),
              ratio(r["step_ms_median"], ref), fmt(r["step_ms_p99"], ".3g"), fmt(r["step_ms_max"], ".3g"),
              fmt(r["ekf_ms_median"], ".3g"), fmt(r["mpc_ms_median"], ".3g"), str(r["fallbacks"])] for r in rows]
    first = rows[0]["layers"] if rows else "-"
    about = docstring_paragraph(bench_robot.__doc__, cut=" Returns ")
    return Page("The whole robot's step time (bench robot)", about + " The tracking error is against the targets.",
                [Table(f"topology {res['topology']}, horizon {res['horizon']}, {res['duration_s']:g} s per layer count",
                       ["layers", "chambers", "QP variables", "step median (ms)", f"step / {first} layer(s)",
                        "step p99 (ms)", "step max (ms)", "EKF median (ms)", "NMPC median (ms)", "fallbacks"],
                       table)])


def fit_page(doc: dict) -> Page:
    """``bench fit``: its bench_fit.json dict."""
    from hbma_ctrl.app.bench import fit

    static = doc["static"]
    cells = {(r["case"], r["law"]): f"{100 * r['worst_rel_miss']:.3g} %, NRMSD {r['nrmsd']:.2g}"
             + (", undetermined" if r["unidentifiable"] else "") for r in static}
    cases = list(dict.fromkeys(r["case"] for r in static))
    keys = ("modulus_scale", "V0_cm3", "flow_scale", "C_out_1e10", "nrmsd")
    runs = [[key, *(f"{v[k][0]:.4f} - {v[k][1]:.4f}" for k in keys), f"{v['structured']}/{v['runs']}"]
            for key, v in doc["summary"].items()]
    return Page("The fit against truths it is not (bench fit)", docstring_paragraph(fit.__doc__, slice(0, 3)),
                [Table("Static points of the exact solver: the largest miss of a parameter (found / truth - 1), NRMSD",
                       ["data", "cap law", "exact law"], [[c, cells.get((c, "cap"), "-"), cells.get((c, "exact"), "-")]
                                                          for c in cases]),
                 Table(f"Pump / hold / vent runs over {doc['seeds']} rig noise seeds: the range over the seeds",
                       ["rig / law", "modulus_scale (-)", "V0 (cm^3)", "flow_scale (-)", "C_out (1e-10 SI)",
                        "NRMSD (-)", "structured residual"], runs)],
                notes=[f"Truth of the runs: {doc['truth']}."])


def soak_page(res: dict) -> Page:
    """``bench soak``: its soak.json dict."""
    from hbma_ctrl.app.bench import soak

    st = res["daemon_stats"]
    stats = [["rig time (s)", fmt(st.get("rig_time_s"), ".0f")], ["wall time (s)", fmt(st.get("wall_s"), ".0f")],
             ["setpoints accepted / sent", f"{res['setpoints_accepted']}/{res['setpoints_sent']}"],
             ["tick median (ms)", fmt(st.get("tick_ms_median"), ".3g")], ["tick p99 (ms)", fmt(st.get("tick_ms_p99"), ".3g")],
             ["ticks over the period", fmt(st.get("steps_over_period"))],
             ["of which the machine's", fmt(res.get("ticks_over_period_machine"))],
             ["max pressure (kPa)", f"{fmt(st.get('max_pressure_kpa'), '.1f')} / {fmt(st.get('pressure_limit_kpa'), 'g')}"],
             ["RSS start -> end (MB)", f"{fmt(st.get('rss_mb_start'), '.1f')} -> {fmt(st.get('rss_mb_end'), '.1f')}"],
             ["faults", str(st.get("faults") or "none")], ["replay", str(res.get("replay"))]]
    log = res.get("log")
    if log:
        msgs = sorted(set(log["messages"].values()))
        stats += [["log.mcap: periods / messages per topic", f"{log['periods_logged']} / "
                   + "-".join(str(n) for n in (msgs[:1] + msgs[-1:] if len(msgs) > 1 else msgs))],
                  ["log.mcap: dropped, size (MB)", f"{fmt(log.get('dropped'))}, {fmt(log['log_bytes'] / 1e6, '.1f')}"]]
    return Page("The daemon over a long run (bench soak)", docstring_paragraph(soak.__doc__, slice(0, 2)),
                [Table("Verdicts", ["criterion", "passed"], [[k, fmt(v)] for k, v in res["verdicts"].items()]),
                 Table(f"{res['config']}, {res['duration_s']:g} s of rig time at speed {res['speed']:g}, a setpoint "
                       f"every {res['setpoint_every_s']:g} s (seed {res['seed']})", ["quantity", "value"], stats)])


def drills_page(res: dict) -> Page:
    """``bench drills``: its drills.json dict."""
    from hbma_ctrl.app.bench import drills

    kinds = ", ".join(f"{k} {v}" for k, v in res["found_by_kind"].items()) or "none"
    totals = [[str(res["drills"]), str(res["judged"]), str(res["found"]), kinds, fmt(res["delay_s_median"], ".3g"),
               fmt(res["delay_s_max"], ".3g"), str(res["false_alarms"]), fmt(res["wall_s"], ".0f")]]
    per = [[str(r["drill"]), str(r["chamber"]), fmt(r["start_s"], ".2f"),
            "false alarm" if r["false_alarm"] else (r["found"] or "not found"), fmt(r.get("delay_s"), ".3g")]
           for r in res["per_drill"]]
    return Page("Fault drills through the daemon's loop (bench drills)", docstring_paragraph(drills.__doc__, slice(0, 3)),
                [Table(f"{res['kind']} drills on {res['config']} (seed {res['seed']}), injected in "
                       f"[{res['from_s']:g}, {res['to_s']:g}] s", ["drills", "judged", "found", "found by",
                                                                   "delay median (s)", "delay max (s)",
                                                                   "false alarms", "wall (s)"], totals),
                 Table("Each drill", ["drill", "chamber", "injected at (s)", "found", "delay (s)"], per)])


def poses_page(res: dict) -> Page:
    """``bench poses``: its poses.json dict."""
    from hbma_ctrl.app.bench import poses

    row = [[str(res["changes"]), fmt(res["target_rate_mm_s"], "g"), fmt(res["peak_kpa_max"], ".2f"),
            fmt(res["peak_kpa_p90"], ".2f"), f"{res['over_limit']} (limit {res['pressure_limit_kpa']:g} kPa)",
            f"{res['over_cap']} (cap {res['cap_kpa']:g} kPa)", str(len(res["faults"])), fmt(res["wall_s"], ".0f")]]
    return Page("Setpoint changes and the pressures they drive (bench poses)",
                docstring_paragraph(poses.__doc__, slice(0, 2)),
                [Table(f"{res['config']}, {res['duration_s']:g} s of rig time, a setpoint every {res['every_s']:g} s "
                       f"(seed {res['seed']})", ["changes", "target rate (mm/s)", "peak max (kPa)", "peak p90 (kPa)",
                                                 "over the limit", "over the cap", "faults", "wall (s)"], row)])


def api_page(res: dict) -> Page:
    """``bench api``: its api.json dict."""
    from hbma_ctrl.app.bench import api

    rows = []
    for name, r in res["runs"].items():
        d, sl = r["daemon"], r["stop_latency"]
        rows.append([name, str(r["clients"]), fmt(r["requests_per_s"], ".0f"), fmt(d["steps"]),
                     fmt(d["deadline_misses"]), fmt(d["overruns"]), fmt(d["step_ms_p99"], ".3g"),
                     f"{sl['within_period']}/{sl['n']}", fmt(sl["median_ms"], ".3g"), fmt(sl["p99_ms"], ".3g"),
                     fmt(sl["max_ms"], ".3g"), str(d["faults"] or "none")])
    period = next(iter(res["runs"].values()))["period_ms"] if res["runs"] else float("nan")
    return Page("The daemon's loop under API clients (bench api)", docstring_paragraph(api.__doc__, slice(0, 3)),
                [Table("Verdicts", ["criterion", "passed"], [[k, fmt(v)] for k, v in res["verdicts"].items()]),
                 Table(f"{res['config']}, {res['duration_s']:g} s of wall time per run, a /stop probe every "
                       f"{res['probe_every_s']:g} s, loop period {fmt(period, 'g')} ms",
                       ["run", "clients", "requests/s", "steps", "deadline misses", "overruns", "step p99 (ms)",
                        "/stop within a period", "/stop median (ms)", "/stop p99 (ms)", "/stop max (ms)", "faults"],
                       rows)])


def live_page(res: dict) -> Page:
    """``bench live``: its live.json dict."""
    from hbma_ctrl.app.bench import live

    rows = []
    for name, r in res["runs"].items():
        d = r["daemon"]
        rows.append([name.replace("_", " "), fmt(d["steps"]), fmt(d["deadline_misses"]), fmt(d["overruns"]),
                     fmt(d["step_ms_median"], ".3g"), fmt(d["step_ms_p99"], ".3g"), fmt(d["tick_ms_p99"], ".3g"),
                     fmt(d["jitter_ms_p99"], ".3g"), fmt(r.get("daemon_cpu_s"), ".3g"),
                     fmt(r.get("browser_cpu_s"), ".3g"), str(d["faults"] or "none")])
    w = res["runs"].get("with_page", {})
    period = w.get("period_ms", float("nan"))
    page_rows = [[fmt(w.get("rate_hz"), "g"), fmt(w.get("every_steps")), fmt(w.get("samples")), fmt(w.get("compared")),
                  fmt(w.get("matching_log")), fmt(w.get("lag_periods_median"), ".3g"), fmt(w.get("lag_periods_max"), ".3g"),
                  f"{w.get('within_one_decimation_period', 0)}/{w.get('compared', 0)}"]]
    notes = []
    for name, r in res["runs"].items():
        if r.get("client_error"):
            notes.append(f"{name}: the client failed: {r['client_error']}")
    if w.get("differences"):
        notes.append("Values shown that differ from the log (first ones): " + "; ".join(w["differences"][:5]))
    return Page("The daemon's loop with its live page open (bench live)", docstring_paragraph(live.__doc__, slice(0, 3)),
                [Table("Verdicts", ["criterion", "passed"], [[k, fmt(v)] for k, v in res["verdicts"].items()]),
                 Table(f"{res['config']}, {res['duration_s']:g} s per run at speed 1, loop period {fmt(period, 'g')} ms"
                       + (f", the browser {res['browser_nice']} below the daemon's priority (nice)"
                          if res.get("browser_nice") else ""),
                       ["run", "steps", "deadline misses", "overruns", "step median (ms)", "step p99 (ms)",
                        "tick p99 (ms)", "jitter p99 (ms)", "daemon CPU (s)", "browser CPU (s)", "faults"], rows),
                 Table(f"The page against the run log, one sample every {res['sample_every_s']:g} s",
                       ["updates asked (per s)", "loop periods per update", "samples", "compared with the log",
                        "equal to the log", "lag median (periods)", "lag max (periods)",
                        "within one decimation period"], page_rows)], notes=notes)


def codegen_page(res: dict, spec_name: str, opt: str) -> Page:
    """``bench codegen``: the result of :func:`hbma_ctrl.core.loopgen_c.bench` (and its scene)."""
    from hbma_ctrl.core.loopgen_c import bench

    vm = any(r.get("python_vm", {}).get("calls") for r in res["functions"].values())
    rows = []
    for name, r in list(res["functions"].items()) + [("tick (sum)", res["tick"])]:
        c, p = r["c"], r["python"]
        row = [name, str(c["calls"]), fmt(c["median_us"], ".3g"), fmt(c["p99_us"], ".3g"), fmt(p["median_us"], ".3g"),
               fmt(p["p99_us"], ".3g"), fmt(r["ratio_median"], ".2g"), fmt(r["ratio_p99"], ".2g")]
        if vm:
            row += [fmt(r["python_vm"]["median_us"], ".3g")]
        rows.append(row)
    cols = ["function", "calls", "C median (us)", "C p99 (us)", "Python median (us)", "Python p99 (us)",
            "Python / C median", "Python / C p99"] + (["VM median (us)"] if vm else [])
    w = res["wall_s"]
    notes = [f"Largest |C - Python| over the trajectory: {res['max_abs_diff_si_all']:.3g} (SI): both paths compute "
             "the same loop, so the comparison is of cost alone (no accuracy axis, no Pareto figure).",
             f"Build {w['build']:.1f} s, C run {w['c_run']:.2f} s, Python run {w['python_run']:.1f} s."]
    sc = res.get("scene")
    if sc:
        e, c = sc["ekf_step"], sc["controller_step"]
        notes.append(f"The scene's own loop ({sc.get('nmpc') or sc.get('variant')}): EKF step {e['median_us']:.1f} / "
                     f"{e['p99_us']:.1f} us, controller step {c['median_us']:.0f} / {c['p99_us']:.0f} us (median / "
                     f"p99); largest |C - scene| {sc['max_abs_diff_si_all']:.3g} (SI).")
    return Page("Generated C loop against the Python path (bench codegen)", docstring_paragraph(bench.__doc__, slice(0, 2), " Returns "),
                [Table(f"{spec_name}: C built with {opt}, us per call", cols, rows)], notes=notes)


def log_page(res: dict) -> Page:
    """``bench log``: its log.json dict."""
    from hbma_ctrl.app.bench import log

    rows = []
    for name, r in res["runs"].items():
        msgs = r.get("messages") or {}
        rows.append([name, "yes" if r["mcap"] else "no", fmt(r["steps"]), fmt(r["deadline_misses"]), fmt(r["overruns"]),
                     fmt(r["step_ms_median"], ".3g"), fmt(r["step_ms_p99"], ".3g"), fmt(r["tick_ms_p99"], ".3g"),
                     f"{min(msgs.values())}/{r['periods_logged']}" if msgs else "", fmt(r.get("dropped", "")),
                     *((fmt(r.get("handoff_us_median"), ".3g"), fmt(r.get("handoff_us_p99"), ".3g"),
                        fmt(r.get("handoff_cpu_us_median"), ".3g"), fmt(r.get("handoff_cpu_us_p99"), ".3g"))
                       if r["mcap"] else ("",) * 4),
                     str(r["faults"] or "none")])
    med = [[v, *(fmt(res["medians"][v].get(k), ".3g") for k in ("deadline_misses", "step_ms_median", "step_ms_p99",
                                                                  "tick_ms_p99"))] for v in res["medians"]]
    return Page("What the MCAP log costs the daemon's loop (bench log)", docstring_paragraph(log.__doc__, slice(0, 3)),
                [Table("Verdicts", ["criterion", "passed"], [[k, fmt(v)] for k, v in res["verdicts"].items()]),
                 Table(f"Medians over {res['repeats']} runs each", ["log", "deadline misses", "step median (ms)",
                                                                   "step p99 (ms)", "tick p99 (ms)"], med),
                 Table(f"{res['config']}, {res['duration_s']:g} s of rig time per run at speed {res['speed']:g}",
                       ["run", "MCAP", "steps", "deadline misses", "overruns", "step median (ms)", "step p99 (ms)",
                        "tick p99 (ms)", "messages per topic / periods", "dropped", "hand-off median (us)", "hand-off p99 (us)",
                        "hand-off CPU median (us)", "hand-off CPU p99 (us)", "faults"],
                       rows)])
