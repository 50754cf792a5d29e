"""``hbma-ctrl robot ...``: the continuum robot's Table II, workspace and pose plots.

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`. Each command writes its own
results directory (default ``runs/table2``, ``runs/workspace``, ``runs/pose``, ``runs/bench_robot``)
through :func:`hbma_ctrl.app.outputs.run_dir`. Edge units (mm, kPa, deg) here only;
:mod:`hbma_ctrl.robot` works in SI. Bad input raises ValueError, which the top-level CLI prints as
one ``error: ...`` line with exit code 2.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer
from rich.console import Console

# the robot's models (casadi, the exact membrane), its plots and its closed loop are imported by the
# commands when they run; the default glue-spot radius comes from the light cli_constants
from hbma_ctrl.app.cli.args import ReportDir, check_choice, check_range, numbers, show_table, whole_numbers
from hbma_ctrl.app.cli.constants import BOND_RADIUS_MM
from hbma_ctrl.app.outputs import OVERWRITE_HELP, check_out, cli_argv, run_dir
from hbma_ctrl.core import units as U

if TYPE_CHECKING:
    from hbma_ctrl.robot.design import RobotDesign

__all__ = ["register", "robot_app"]

robot_app = typer.Typer(add_completion=False, rich_markup_mode=None, no_args_is_help=True,
                        help="The hybrid soft-rigid continuum robot (docs/concepts/model.md §8): Table II, workspace, pose.")


def _wide_console() -> Console:
    """The robot's wide tables' console (150 columns, on a terminal too)."""
    return Console(highlight=False, width=150)


def _design(layers: int | None, max_stretch: float | None = None) -> RobotDesign:
    from hbma_ctrl.robot.design import RobotDesign

    # the flags' ranges here, so that the error names the flag (the design's own check names its field)
    check_range("--layers", layers, 1, 26, unit="layers")
    check_range("--max-stretch", max_stretch, 1.05, 20.0)
    kw = {"n_layers": layers, "max_stretch": max_stretch}
    return RobotDesign(**{k: v for k, v in kw.items() if v is not None}).validate()


@robot_app.command("table2")
def table2(out: Path = typer.Option(Path("runs/table2"), "--out", help="directory for table2.md and table2.json"),
           overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
           layers: int = typer.Option(2, help="chamber layers of the robot (Fig. 10: 2, A and B)"),
           stretch: float = typer.Option(None, help="stretch of an inflated chamber (default: max stretch 4.0)"),
           hold_kpa: float = typer.Option(35.0, "--hold-kpa", help="near-branch reading: hold pressure, kPa"),
           bond_radius_mm: float = typer.Option(BOND_RADIUS_MM, "--bond-radius-mm",
                                                help="bonded reading: radius of the glue spot on each membrane, mm"),
           bond_kpa: float = typer.Option(40.0, "--bond-kpa", help="bonded reading: inflated chambers' pressure, kPa "
                                                                "(40: every row has a taut exact equilibrium at 1 mm)"),
           bonded: bool = typer.Option(True, "--bonded/--no-bonded",
                                       help="add the glued-chamber reading (exact membrane; its table is built "
                                            "once, a few minutes)")) -> None:
    """The paper's Table II beside the model (one layer, 0-3 chambers inflated)."""
    from hbma_ctrl.robot.design import RobotDesign
    from hbma_ctrl.robot.reach import bonded_table2, paper_pose_check, paper_pose_markdown, robot_table2, table2_markdown

    check_range("--hold-kpa", hold_kpa, 1.0, 1000.0, unit="kPa")
    check_range("--bond-radius-mm", bond_radius_mm, 0.0, U.to_mm(RobotDesign().chamber.r1), lo_open=True, unit="mm",
                hi_open=True, note="the chamber's r1")
    check_range("--bond-kpa", bond_kpa, 0.0, 50.0, lo_open=True, unit="kPa", note="the bonded table's range")
    check_range("--stretch", stretch, 1.05, 20.0)
    d = _design(layers)
    with run_dir(out, command="robot table2", argv=cli_argv(), overwrite=overwrite) as tmp:
        rows = robot_table2(d, stretch=stretch, hold_pressure=U.kpa(hold_kpa))
        if bonded:
            rows += bonded_table2(d, U.kpa(bond_kpa), U.mm(bond_radius_mm))
        md = table2_markdown(rows)
        # can the paper's one- and two-chamber poses stand at all? (beside the table: its JSON keeps its rows)
        poses = paper_pose_check(d, U.mm(bond_radius_mm) if bonded else None)
        pmd = paper_pose_markdown(poses)
        (tmp / "table2.md").write_text(md + "\nThe paper's poses as rigid-layer statics:\n\n" + pmd)
        (tmp / "table2.json").write_text(json.dumps(rows, indent=1) + "\n")
        (tmp / "paper_poses.json").write_text(json.dumps(poses, indent=1) + "\n")
    show_table("Table II: model / paper (one layer of the robot)",
               ("reading", "inflated", "angle (deg)", "length (mm)", "extension (%)", "chamber h (mm)", "p (kPa)",
                "stretch"),
               [(r["reading"], str(r["inflated"]), f"{r['angle_deg']:.1f} / {r['paper_angle_deg']:.1f}",
                 f"{r['length_mm']:.1f} / {r['paper_length_mm']:.1f}",
                 f"{r['extension_pct']:.0f} / {r['paper_extension_pct']:.0f}", f"{r['chamber_height_mm']:.2f}",
                 f"{r['pressure_kpa']:.1f}", f"{r['stretch']:.2f}") for r in rows], _wide_console(), justify="left")
    typer.echo("\n".join(ln for ln in md.splitlines() if ln and not ln.startswith("|")))  # the notes
    typer.echo("\n".join(ln for ln in pmd.splitlines() if ln and not ln.startswith("|")))
    typer.echo(f"wrote {out / 'table2.md'}, {out / 'table2.json'} and {out / 'paper_poses.json'}")


@robot_app.command("workspace")
def workspace(out: Path = typer.Option(Path("runs/workspace"), "--out", help="directory for workspace.png/.json"),
              overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
              layers: int = typer.Option(3, help="chamber layers (Fig. 1: 3)"),
              pressure_limit_kpa: float = typer.Option(45.0, "--pressure-limit-kpa", help="chamber pressure limit"),
              max_stretch: float = typer.Option(None, "--max-stretch", help="membrane stretch limit (default 4.0)"),
              directions: int = typer.Option(72, help="number of bend directions")) -> None:
    """Reachable workspace at the pressure limit: per-layer bend angle against direction, height range."""
    from hbma_ctrl.robot import reach

    check_range("--pressure-limit-kpa", pressure_limit_kpa, 1.0, 1000.0, unit="kPa")
    check_range("--directions", directions, 8, 3600)
    d = _design(layers, max_stretch)
    with run_dir(out, command="robot workspace", argv=cli_argv(), overwrite=overwrite) as tmp:
        ws = reach.workspace(d, U.kpa(pressure_limit_kpa), n_dir=directions)
        _write_workspace(ws, d, pressure_limit_kpa, tmp)
    rows = []
    for ly in ws["layers"]:
        b, bc, bp = (np.degrees(ly[k]) for k in ("bend_max", "bend_max_no_rim_contact", "bend_max_pressure_control"))
        rows.append((ly["layer"], f"{np.mean(ly['load_n']):.3f}", f"{U.to_mm(ly['h_max']):.2f}",
                     ",".join(sorted(set(ly["limit"]))), f"{U.to_kpa(ly['p_peak']):.1f} at {U.to_mm(ly['h_peak']):.2f}",
                     f"{b.min():.1f}-{b.max():.1f}", f"{bc.min():.1f}-{bc.max():.1f}",
                     f"{U.to_mm(ly['h_pressure_control']):.2f}, {bp.min():.1f}-{bp.max():.1f}"))
    con = show_table(f"reach per layer at {pressure_limit_kpa:g} kPa (gas-mass hold vs pressure control)",
                     ("layer", "load/chamber (N)", "h max (mm)", "limited by", "peak p (kPa) at h (mm)",
                      "bend max (deg) over direction", "same, rims clear (deg)",
                      "pressure control: h max (mm), bend (deg)"), rows, _wide_console(), justify="left")
    tb = np.degrees(ws["tip_bend_max"])
    con.print(f"tip (all layers bent alike): bend up to {tb.min():.1f}-{tb.max():.1f} deg; tip height "
              f"{U.to_mm(ws['tip_height_range'][0]):.1f}-{U.to_mm(ws['tip_height_range'][1]):.1f} mm; pump stall "
              f"{U.to_kpa(ws['pump_stall']):g} kPa")
    typer.echo(f"wrote {out / 'workspace.png'} and {out / 'workspace.json'}")


def _write_workspace(ws: dict, d: RobotDesign, pressure_limit_kpa: float, out: Path) -> None:
    """workspace.png and workspace.json (edge units: deg, mm, kPa, N) into out."""
    from hbma_ctrl.app.scenes.robot_plots import plot_workspace

    tb = np.degrees(ws["tip_bend_max"])
    plot_workspace(ws, out / "workspace.png")
    edge = {"direction_deg": np.degrees(ws["direction"]).tolist(), "pressure_limit_kpa": pressure_limit_kpa,
            "pump_stall_kpa": U.to_kpa(ws["pump_stall"]), "max_stretch": ws["max_stretch"],
            "tip_bend_max_deg": tb.tolist(), "tip_height_range_mm": [U.to_mm(x) for x in ws["tip_height_range"]],
            "layers": [{"layer": ly["layer"], "load_n": ly["load_n"], "h_max_mm": U.to_mm(ly["h_max"]),
                        "height_range_mm": [0.0, U.to_mm(ly["h_max"])],
                        "length_range_mm": [U.to_mm(d.layer_thickness), U.to_mm(d.layer_thickness + ly["h_max"])],
                        "limit": ly["limit"], "p_peak_kpa": U.to_kpa(ly["p_peak"]), "h_peak_mm": U.to_mm(ly["h_peak"]),
                        "p_at_max_kpa": U.to_kpa(ly["p_at_max"]),
                        "h_pressure_control_mm": U.to_mm(ly["h_pressure_control"]),
                        "bend_max_deg": np.degrees(ly["bend_max"]).tolist(),
                        "bend_max_pressure_control_deg": np.degrees(ly["bend_max_pressure_control"]).tolist(),
                        "bend_max_no_rim_contact_deg": np.degrees(ly["bend_max_no_rim_contact"]).tolist()}
                       for ly in ws["layers"]]}
    (out / "workspace.json").write_text(json.dumps(edge, indent=1) + "\n")


@robot_app.command("pose")
def pose(out: Path = typer.Option(Path("runs/pose"), "--out", help="directory for pose.png"),
         overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
         heights_mm: list[str] = typer.Option(None, "--heights-mm",
                                              help="chamber heights A1,A2,A3,B1,... in mm (3 per layer); "
                                                   "repeat the option to draw several shapes"),
         centre_mm: float = typer.Option(None, "--centre-mm", help="IK target: centre height of every layer, mm"),
         bend_deg: float = typer.Option(0.0, "--bend-deg", help="IK target: bend of every layer, deg"),
         direction_deg: float = typer.Option(0.0, "--direction-deg", help="IK target: bend direction, deg"),
         layers: int = typer.Option(None, help="chamber layers (default: from --heights-mm, else 3)"),
         pressure_limit_kpa: float = typer.Option(45.0, "--pressure-limit-kpa", help="for the reach check")) -> None:
    """Draw the robot's shape for given chamber heights (or per-layer IK targets) -> pose.png."""
    from hbma_ctrl.app.scenes.robot_plots import plot_shapes
    from hbma_ctrl.robot.design import LETTERS
    from hbma_ctrl.robot.kinematics import forward_kinematics, inverse_kinematics
    from hbma_ctrl.robot.reach import reach_report

    sets = [np.array(numbers(text, "--heights-mm")) for text in heights_mm or []]
    if sets:
        n = {s.size for s in sets}
        if len(n) != 1 or next(iter(n)) % 3:
            raise ValueError("--heights-mm: every set needs the same number of heights, 3 per layer")
        nl = next(iter(n)) // 3
        if layers is not None and layers != nl:
            raise ValueError(f"--layers = {layers} but --heights-mm gives {nl} layers")
        layers = nl
        if centre_mm is not None:
            raise ValueError("give either --heights-mm or --centre-mm/--bend-deg/--direction-deg, not both")
    d = _design(layers if layers is not None else 3)
    if not sets:
        if centre_mm is None:
            raise ValueError("give --heights-mm (chamber heights) or --centre-mm with --bend-deg/--direction-deg")
        check_range("--centre-mm", centre_mm, 0.0, 200.0, lo_open=True, unit="mm")
        check_range("--bend-deg", bend_deg, 0.0, 90.0, unit="deg", hi_open=True)
        check_range("--direction-deg", direction_deg, -360.0, 360.0, unit="deg")
        h = inverse_kinematics(d, U.mm(centre_mm), math.radians(bend_deg), math.radians(direction_deg))
        sets = [U.to_mm(h).ravel()]
    check_range("--pressure-limit-kpa", pressure_limit_kpa, 1.0, 1000.0, unit="kPa")
    source = "--heights-mm" if heights_mm else "--centre-mm/--bend-deg (their chamber heights)"
    check_out(out, overwrite)  # before the reach work below; run_dir checks again under its lock
    con = _wide_console()
    shapes = []
    for s in sets:
        h = U.mm(s).reshape(d.n_layers, 3)
        rep = reach_report(d, h, U.kpa(pressure_limit_kpa))
        if np.any(h < 0):
            neg = [f"{nm} = {v:g} mm" for nm, v in zip(d.names, s) if v < 0]
            raise ValueError(f"{source}: chamber heights must be >= 0 mm; {', '.join(neg)}")
        p = forward_kinematics(d, h)
        shapes.append(h)
        con.print("heights (mm): " + ", ".join(f"{nm}={v:.2f}" for nm, v in zip(d.names, s)))
        for k in range(d.n_layers):
            con.print(f"  layer {LETTERS[k]}: centre {U.to_mm(p.centre[k]):.2f} mm, bend "
                      f"{math.degrees(p.bend[k]):.1f} deg toward {math.degrees(p.direction[k]):.1f} deg")
        tp = U.to_mm(p.tip_position)
        con.print(f"  tip at ({tp[0]:.1f}, {tp[1]:.1f}, {tp[2]:.1f}) mm, tilted {math.degrees(p.tip_bend):.1f} deg")
        con.print("  reach: ok" if rep["ok"] else "  reach: NOT reachable: " + "; ".join(rep["violations"]))
    with run_dir(out, command="robot pose", argv=cli_argv(), overwrite=overwrite) as tmp:
        plot_shapes(d, shapes, tmp / "pose.png", labels=[f"shape {i + 1}" for i in range(len(shapes))],
                    title="robot pose")
    typer.echo(f"wrote {out / 'pose.png'}")


def bench_robot_cmd(out: Path = typer.Option(Path("runs/bench_robot"), "--out", help="directory for bench_robot.json"),
                    layers: str = typer.Option("1,2,3,4,5,6", help="layer counts to time, comma-separated (1-6)"),
                    duration: float = typer.Option(3.0, help="closed-loop run per layer count, s (0.5-60)"),
                    topology: str = typer.Option("per_chamber", help="per_chamber | shared"),
                    horizon: int = typer.Option(15, help="NMPC stages (1-100)"),
                    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
                    report: ReportDir = None) -> None:
    """Whole-robot step time (EKF bank + load sharing + NMPC) for 1..6 layers: median and p99, ms."""
    from hbma_ctrl.app.scenes.robot_closed import bench_robot
    from hbma_ctrl.robot.design import TOPOLOGIES

    ns = whole_numbers(layers, "--layers", 1, 6)
    check_range("--duration", duration, 0.5, 60.0, unit="s")
    check_choice("--topology", topology, TOPOLOGIES)
    check_range("--horizon", horizon, 1, 100)
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "robot", cli_argv())  # --report checked before the run
    with run_dir(out, command="bench robot", argv=cli_argv(), overwrite=overwrite) as tmp:
        rows = bench_robot(ns, duration, topology, horizon)
        res = {"topology": topology, "horizon": horizon, "duration_s": duration, "rows": rows}
        (tmp / "bench_robot.json").write_text(json.dumps(res, indent=1) + "\n")
    show_table(f"robot step (EKF bank + NMPC), topology {topology}, horizon {horizon}",
               ("layers", "chambers", "QP vars", "median ms", "p99 ms", "max ms", "EKF ms", "NMPC ms", "fallbacks"),
               [(str(r["layers"]), str(r["chambers"]), str(r["qp_variables"]), f"{r['step_ms_median']:.2f}",
                 f"{r['step_ms_p99']:.2f}", f"{r['step_ms_max']:.2f}", f"{r['ekf_ms_median']:.2f}",
                 f"{r['mpc_ms_median']:.2f}", str(r["fallbacks"])) for r in rows], Console())
    typer.echo(f"wrote {out / 'bench_robot.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import robot_page

        typer.echo(f"wrote {rep.write(robot_page(res))}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add the ``robot`` sub-app (table2, workspace, pose) and ``bench robot`` to the top-level CLI."""
    app.add_typer(robot_app, name="robot")
    bench_app.command("robot")(bench_robot_cmd)
