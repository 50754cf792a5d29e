"""The chamber's and the robot's tick as a C library (``codegen --library``): OSQP's workspace as a
caller-owned struct, the library built for the host and for a Cortex-M7, run bare-metal on QEMU beside
the host build.

The board tests need Debian's gcc-arm-none-eabi, libnewlib-arm-none-eabi and qemu-system-arm (.ci/run
installs them) and are skipped, saying so, without them.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from checkout import ROOT
from cli_checks import one_line_error
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.core.osqp_embed import own_workspace

TRACK = str(ROOT / "scenarios" / "track_height.toml")
ROBOT = str(ROOT / "scenarios" / "robot_bending.toml")
needs_cc = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                              reason="no C compiler (cc or gcc) on PATH")
_ARM_TOOLS = ("arm-none-eabi-gcc", "arm-none-eabi-size", "qemu-system-arm", "make")
needs_arm = pytest.mark.skipif(any(shutil.which(p) is None for p in _ARM_TOOLS),
                               reason="the Cortex-M toolchain is not installed (apt-get install gcc-arm-none-eabi "
                                      "libnewlib-arm-none-eabi qemu-system-arm)")
#: what the library must not call: allocation, files, the console
_FORBIDDEN = ("malloc", "calloc", "realloc", "free", "fopen", "fwrite", "fread", "printf", "fprintf", "puts",
              "_sbrk", "exit")


def _board_report(out: Path) -> dict:
    """embedded.json of a board run, holding every key the embed tutorial documents."""
    rep = json.loads((out / "embedded.json").read_text())
    for key in ("target", "ticks", "max_abs_diff", "instructions_per_tick_median", "instructions_per_tick_max",
                "flash_bytes", "ram_bytes"):
        assert key in rep
    return rep


def _assert_no_forbidden_calls(out: Path) -> None:
    """The Cortex-M7 library's objects call no allocator and no file or console I/O."""
    undefined = subprocess.run(["arm-none-eabi-nm", "-u", str(out / "build" / "cortex-m7" / "libhbma.a")],
                               check=True, capture_output=True, text=True).stdout.split()
    assert not set(undefined) & set(_FORBIDDEN), sorted(set(undefined) & set(_FORBIDDEN))


def _cli(args):
    return CliRunner().invoke(app, args)


@pytest.mark.compiling
@needs_cc
def test_osqp_workspace_as_a_struct_solves_as_osqp_does(tmp_path):
    """OSQP's generated workspace rewritten as a struct: two structs are two independent solvers, each
    giving the QP's solution OSQP's Python interface gives (to its tolerance), and a data update in one
    leaves the other alone."""
    import osqp
    import scipy.sparse as sp

    P = sp.csc_matrix(np.array([[4.0, 1.0], [0.0, 2.0]]))
    A = sp.csc_matrix(np.array([[1.0, 1.0], [1.0, 0.0], [0.0, 1.0]]))
    q, lo, hi = np.array([1.0, 1.0]), np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.7, 0.7])
    m = osqp.OSQP()
    m.setup(P, q, A, lo, hi, verbose=False, polishing=False, eps_abs=1e-9, eps_rel=1e-9, max_iter=10000)
    ref = m.solve().x
    m.codegen(str(tmp_path / "g"), parameters="matrices", extension_name=None, force_rewrite=True, prefix="t_")
    own_workspace(tmp_path / "g", "t_")
    (tmp_path / "g" / "main.c").write_text("""
#include <stdio.h>
#include "osqp.h"
#include "t_workspace.h"
static t_mem_t a, b;
int main(void) {
  t_mem_init(&a);
  t_mem_init(&b);
  OSQPFloat q2[2] = {2.0, 2.0};
  osqp_update_data_vec(t_mem_solver(&b), q2, OSQP_NULL, OSQP_NULL);
  osqp_solve(t_mem_solver(&b));
  osqp_solve(t_mem_solver(&a));
  printf("%.12g %.12g %d\\n", a.t_sol_x[0], a.t_sol_x[1], (int)a.t_info.status_val);
  return 0;
}
""")
    g = tmp_path / "g"
    srcs = [str(p) for p in sorted((g / "src").glob("*.c"))]
    cc = shutil.which("cc") or shutil.which("gcc")
    subprocess.run([cc, "-O1", "-std=c99", "-I", str(g), "-I", str(g / "inc" / "public"), "-I",
                    str(g / "inc" / "private"), str(g / "main.c"), str(g / "t_workspace.c"), *srcs, "-o",
                    str(g / "main"), "-lm"], check=True, capture_output=True)
    out = subprocess.run([str(g / "main")], check=True, capture_output=True, text=True).stdout.split()
    assert int(out[2]) == 1  # OSQP_SOLVED
    assert np.allclose([float(out[0]), float(out[1])], ref, atol=1e-6)


@pytest.mark.slow
def test_library_options_are_checked(tmp_path):
    """--library refuses what it cannot build, naming the option and what is allowed (a robot's library in
    single precision too)."""
    out = str(tmp_path / "lib")
    one_line_error(_cli(["codegen", TRACK, "--library", "--target", "avr", "--out", out]), "--target", "cortex-m7")
    one_line_error(_cli(["codegen", TRACK, "--library", "--precision", "half", "--out", out]), "--precision",
                   "single")
    one_line_error(_cli(["codegen", TRACK, "--library", "--qp-solver", "qrqp", "--out", out]), "--qp-solver", "osqp")
    one_line_error(_cli(["codegen", TRACK, "--target", "cortex-m7", "--out", out]), "--library")
    one_line_error(_cli(["codegen", ROBOT, "--library", "--precision", "single", "--out", out]), "--precision",
                   "double")
    one_line_error(_cli(["codegen", TRACK, "--library", "--qp-solver", "daqp", "--precision", "single", "--out", out]),
                   "--qp-solver", "double")
    one_line_error(_cli(["codegen", ROBOT, "--library", "--qp-solver", "daqp", "--out", out]), "--qp-solver", "osqp")


@pytest.mark.compiling
@pytest.mark.slow
@needs_arm
def test_cortex_m7_build_equals_the_host_build_on_qemu(tmp_path, monkeypatch):
    """``codegen --library --target cortex-m7``: the board program runs bare-metal on QEMU's MPS2 AN500 on
    the scenario's recorded pressures and its commands equal the host build's to 1e-9; embedded.json
    has the instruction counts (the counter calibrated at 40 instructions per 25 MHz count under
    ``-icount shift=0``), flash and RAM; the library's objects call no allocator and no file or console
    I/O."""
    # both builds unoptimised (the Makefile's OPT): the 3.4 MB of generated C compiles several times
    # faster, and host and board still share every flag; the optimised figures (library.OPT) are the
    # tutorial's runs
    monkeypatch.setenv("OPT", "-O0")
    out = tmp_path / "m7"
    res = _cli(["codegen", TRACK, "--library", "--target", "cortex-m7", "--duration-s", "0.6", "--out", str(out)])
    assert res.exit_code == 0, res.output
    rep = _board_report(out)
    assert rep["target"] == "cortex-m7" and rep["ticks"] == 60
    assert rep["max_abs_diff"] <= 1e-9
    assert rep["instructions_per_count"] == pytest.approx(40.0, rel=1e-3)
    assert 0 < rep["instructions_per_tick_median"] <= rep["instructions_per_tick_max"]
    assert rep["flash_bytes"] > 0 and rep["ram_bytes"] > 0
    host = np.loadtxt(out / "commands_host.txt")
    assert host.shape == (60, 4) and np.all((host[:, 1:] >= 0) & (host[:, 1:] <= 1))
    _assert_no_forbidden_calls(out)


@pytest.mark.compiling
@pytest.mark.slow
@needs_arm
def test_robot_cortex_m7_build_equals_the_host_build_on_qemu(tmp_path, monkeypatch):
    """``codegen --library --target cortex-m7`` on a 3-layer [robot] scenario (9 chambers): the board's
    commands (3 x 9 valve inputs per tick) equal the host build's to 1e-9 over the recorded ticks;
    embedded.json has the chamber library's keys and the comparison with the scenario's own run; the
    library's objects call no allocator and no file or console I/O."""
    monkeypatch.setenv("OPT", "-O0")  # as the chamber's test: unoptimised, host and board alike
    out = tmp_path / "robot_m7"
    res = _cli(["codegen", ROBOT, "--library", "--target", "cortex-m7", "--duration-s", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    rep = _board_report(out)
    assert rep["target"] == "cortex-m7" and rep["ticks"] == 200
    assert rep["max_abs_diff"] <= 1e-9
    assert 0 < rep["instructions_per_tick_median"] <= rep["instructions_per_tick_max"]
    assert rep["flash_bytes"] > 0 and rep["ram_bytes"] > 0
    host = np.loadtxt(out / "commands_host.txt")
    assert host.shape == (200, 1 + 27) and np.all((host[:, 1:] >= 0) & (host[:, 1:] <= 1))
    for key in ("recorded_commands_max_abs_diff", "recorded_commands_median_abs_diff",
                "recorded_ticks_diff_above_1e-3", "recorded_height_estimate_max_abs_diff_m"):
        assert np.isfinite(rep[key])
    header = (out / "hbma.h").read_text()
    assert "#define HBMA_N_CHAMBERS 9" in header and "#define HBMA_N_LAYERS 3" in header
    _assert_no_forbidden_calls(out)


@pytest.mark.compiling
@pytest.mark.slow
@needs_cc
def test_robot_host_build_replays_the_recorded_run_to_the_qp_tolerance(tmp_path, monkeypatch):
    """The robot library's host build on the readings and poses of the scenario's own run (its NMPC the
    step Function, its QP on casadi's OSQP) sends that run's commands and estimates its heights: with
    both QPs solved to 1e-8 (the scenario's 3e-4 lets the two OSQPs' iterates, and so a valve's
    minimum-duty decision, differ), every command within 5e-3 and every estimated height within 1e-6 m
    over 100 ticks."""
    from dataclasses import replace

    import hbma_ctrl.app.scenes.robot_closed as robot_closed
    from hbma_ctrl.app.codegen.library import (build_library, library_spec, record_inputs, run_library,
                                               write_inputs, write_library)
    from hbma_ctrl.app.scenario import load_scenario

    parts = robot_closed.scene_parts

    def tight(scn, s):
        rig, model, mpc = parts(scn, s)
        return rig, model, replace(mpc, eps=1e-8)

    monkeypatch.setattr(robot_closed, "scene_parts", tight)
    monkeypatch.setenv("OPT", "-O0")
    scn = load_scenario(ROBOT)
    lib = library_spec(scn)
    assert lib.qp_setup["eps"] == 1e-8
    write_library(lib, tmp_path)
    build_library(tmp_path, "host")
    rec = record_inputs(scn, lib, 100)
    run = run_library(tmp_path, "host", write_inputs(rec, tmp_path / "inputs.bin"))
    assert np.all(run.status == 0)
    assert np.max(np.abs(run.u - rec["u"])) <= 5e-3
    assert np.max(np.abs(run.height - rec["h_est"])) <= 1e-6


_HELD_HARNESS = r"""
#include <stdio.h>
#include <string.h>
#include "hbma.h"
static hbma_workspace_t ws;
static hbma_params_t params;
/* argv[1]: inputs.bin; argv[2]: 0 lockstep (held = the last u), 1 held all closed, 2 held open everywhere */
int main(int argc, char** argv) {
  int mode = argv[2][0] - '0';
  FILE* fh = fopen(argv[1], "rb");
  double head[3], row[1 + HBMA_N_CHAMBERS + 3 * HBMA_N_LAYERS];
  if (!fh || fread(head, 8, 3, fh) != 3) return 2;
  hbma_default_params(&params);
  hbma_init(&ws, &params);
  static hbma_real p[HBMA_N_CHAMBERS], pose[HBMA_N_LAYERS][3], held[3][HBMA_N_CHAMBERS], u[3][HBMA_N_CHAMBERS];
  hbma_outputs_t out;
  for (long k = 0; k < (long)head[0]; ++k) {
    if (fread(row, 8, sizeof row / 8, fh) != sizeof row / 8) return 2;
    for (int i = 0; i < HBMA_N_CHAMBERS; ++i) p[i] = row[1 + i];
    for (int l = 0; l < HBMA_N_LAYERS; ++l)
      for (int j = 0; j < 3; ++j) pose[l][j] = row[1 + HBMA_N_CHAMBERS + 3 * l + j];
    hbma_set_target(&ws, (const hbma_real(*)[3])pose);
    if (mode == 2)
      for (int j = 0; j < 3; ++j)
        for (int i = 0; i < HBMA_N_CHAMBERS; ++i) held[j][i] = 0.37;
    hbma_tick(&ws, row[0], p, (const hbma_real(*)[HBMA_N_CHAMBERS])held, u);
    if (mode == 0) memcpy(held, u, sizeof held);
    hbma_outputs(&ws, &out);
    printf("%ld", k);
    for (int j = 0; j < 3; ++j)
      for (int i = 0; i < HBMA_N_CHAMBERS; ++i) printf(" %.17g", (double)u[j][i]);
    printf(" %ld %.17g\n", out.held_unmatched, (double)out.height_m[0]);
  }
  return 0;
}
"""


@pytest.mark.compiling
@pytest.mark.slow
@needs_cc
def test_robot_library_reads_held_as_the_robot_runtime_does(tmp_path, monkeypatch):
    """``hbma_tick``'s ``held`` (the valve inputs a rig held) read as ``RobotLoop.tick`` reads it: in
    lockstep (held = the last command) the commands are the driver's; a held with every valve closed is
    the safe command (no report left unmatched) and changes the estimate; a held matching no command
    sent (speed and inlet open everywhere) is counted unmatched at every tick."""
    from hbma_ctrl.app.codegen.library import (build_library, library_spec, record_inputs, run_library,
                                               write_inputs, write_library)
    from hbma_ctrl.app.scenario import load_scenario

    monkeypatch.setenv("OPT", "-O0")
    scn = load_scenario(ROBOT)
    lib = library_spec(scn)
    write_library(lib, tmp_path)
    build_library(tmp_path, "host")
    inputs = write_inputs(record_inputs(scn, lib, 40), tmp_path / "inputs.bin")
    driver = run_library(tmp_path, "host", inputs)
    (tmp_path / "held.c").write_text(_HELD_HARNESS)
    cc = shutil.which("cc") or shutil.which("gcc")
    subprocess.run([cc, "-O0", "-std=c99", "-I", str(tmp_path), "-I", str(tmp_path / "osqp"), "-I",
                    str(tmp_path / "osqp" / "inc" / "public"), "-I", str(tmp_path / "osqp" / "inc" / "private"),
                    str(tmp_path / "held.c"), str(tmp_path / "build" / "host" / "libhbma.a"), "-o",
                    str(tmp_path / "held"), "-lm"], check=True, capture_output=True)

    def run(mode: int) -> np.ndarray:
        out = subprocess.run([str(tmp_path / "held"), str(inputs), str(mode)], check=True, capture_output=True,
                             text=True).stdout
        return np.array([[float(v) for v in line.split()] for line in out.splitlines()])

    lockstep, closed, unmatched = run(0), run(1), run(2)
    assert np.array_equal(lockstep[:, 1:28], driver.u) and np.all(lockstep[:, 28] == 0)
    assert np.all(closed[:, 28] == 0) and not np.array_equal(closed[:, 29], lockstep[:, 29])
    assert np.array_equal(unmatched[:, 28], np.arange(1, 41))


@pytest.mark.slow
def test_robot_library_qp_parts_equal_the_robot_steps_own():
    """The robot library's QP path is the robot NMPC step Function's: its post-processing on the step's
    own QP solution gives exactly the step's outputs, and its problem data solved by OSQP's Python
    interface give the step's first decisions to the solver's tolerance."""
    import osqp
    import scipy.sparse as sp

    from hbma_ctrl.app.codegen.library import library_spec
    from hbma_ctrl.app.scenario import load_scenario

    lib = library_spec(load_scenario(ROBOT))
    assert lib.kind == "robot" and lib.n == 9 and lib.n_layers == 3
    step = next(st.fun for st in lib.loop.stages if st != "log" and st.name == "robot_rti_step")
    nmpc, n, N = lib.backend, lib.n, lib.horizon
    ins = [np.full(n, 0.05), np.ones(n), np.full(n, 0.3), np.ones(n), np.ones(n), np.ones(n), np.full((n, N), 0.006),
           np.zeros((2, n)), np.zeros((n, N + 1)), np.zeros((n, N)), np.zeros((n, N)), 1.0, np.zeros(nmpc.nv),
           np.zeros(nmpc.m_rows), 0.0]
    ref = step(*ins)
    Px, q, Ax, lo, hi, _, _, chk = [np.asarray(v, float).ravel() for v in lib.qp_data(*ins)]
    got = lib.qp_post(ref[5], 0.0, ref[6], chk, Ax, lo, hi)
    for a, b in zip(ref, got):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    pr, pc, ar, ac, nv, m = lib.qp_setup["patterns"]
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix((Px, (pr, pc)), shape=(nv, nv)), q, sp.csc_matrix((Ax, (ar, ac)), shape=(m, nv)), lo,
                 hi, verbose=False, eps_abs=1e-9, eps_rel=1e-9, polishing=False, max_iter=20000)
    r = solver.solve(raise_error=False)
    mine = lib.qp_post(r.x, r.info.obj_val, r.y, chk, Ax, lo, hi)
    assert float(mine[7]) == 0.0 and float(ref[7]) == 0.0  # both usable
    for i in (0, 1):  # the decisions sent: supply and outlet of every chamber
        assert np.allclose(np.asarray(mine[i]), np.asarray(ref[i]), atol=1e-6)


def test_robot_targets_are_the_runtimes_chamber_targets():
    """The robot library's targets Function (layer poses -> chamber heights) gives the robot runtime's
    chamber targets (:func:`hbma_ctrl.robot.targets.chamber_targets`) for bent and straight poses."""
    from hbma_ctrl.app.codegen.library import _robot_targets_function
    from hbma_ctrl.app.scenario import load_scenario
    from hbma_ctrl.robot.targets import chamber_targets

    s = load_scenario(ROBOT).role("robot")
    fun = _robot_targets_function(s.design)
    for pose in ([0.006, 0.0, 0.0], [0.007, 0.349, 0.0], [0.0075, 0.262, 1.571], [0.001, 0.6, -2.0]):
        targets = {k: ((0.0, *pose),) for k in range(s.design.n_layers)}
        want = chamber_targets(s.design, targets, 0.0)
        got = np.asarray(fun(np.tile(np.array(pose)[:, None], (1, s.design.n_layers)))).ravel()
        assert np.allclose(got, want, rtol=0, atol=1e-15)


@pytest.fixture(scope="module")
def track_library():
    """The library spec of track_height (its QP's Functions and OSQP's setup point)."""
    from hbma_ctrl.app.codegen.library import library_spec
    from hbma_ctrl.app.scenario import load_scenario

    return library_spec(load_scenario(TRACK))


@pytest.mark.compiling
@pytest.mark.slow
@needs_cc
def test_daqp_library_host_build_follows_the_python_controller(tmp_path, monkeypatch):
    """``--library --qp-solver daqp`` (track_height with a horizon of 3, which builds in seconds): the library
    with the condensed QP and DAQP's sources builds on the host, its objects call no allocator and no file or
    console I/O, every tick of the first 0.4 s solves, and its commands follow the scenario's own run (the
    Python controller, OSQP to the scenario's tolerance) within 1e-3 (they differ where a decision flips
    later in the run)."""
    from hbma_ctrl.app.codegen.library import (build_library, library_spec, record_inputs, run_library,
                                               write_inputs, write_library)
    from hbma_ctrl.app.scenario import load_scenario

    monkeypatch.setenv("OPT", "-O0")  # the Makefile's OPT: faster to build, the same commands to rounding
    toml = tmp_path / "track_h3.toml"
    text = Path(TRACK).read_text()
    assert "\nhorizon = 20\n" in text
    toml.write_text(text.replace("\nhorizon = 20\n", "\nhorizon = 3\n"))
    scn = load_scenario(toml)
    lib = library_spec(scn, "daqp")
    out = tmp_path / "daqp"
    write_library(lib, out)
    assert (out / "daqp" / "LICENSE").read_text().startswith("MIT License")
    build_library(out, "host")
    undefined = subprocess.run(["nm", "-u", str(out / "build" / "host" / "libhbma.a")], check=True,
                               capture_output=True, text=True).stdout.split()
    assert not set(undefined) & set(_FORBIDDEN), sorted(set(undefined) & set(_FORBIDDEN))
    rec = record_inputs(scn, lib, 40)
    run = run_library(out, "host", write_inputs(rec, out / "inputs.bin"))
    assert np.all(run.status == 0)
    assert np.max(np.abs(run.u - rec["u"])) <= 1e-3


@pytest.mark.slow
def test_library_qp_parts_equal_the_rti_steps_own(track_library):
    """The library's QP path equals the RTI step Function's parts: OSQP's problem data (P's upper triangle,
    [I; A], the bounds) solved by OSQP's Python interface and post-processed by the library's post
    Function gives exactly what the RTI step's own post-processing (``rti_post``) gives on that solution."""
    import osqp
    import scipy.sparse as sp

    from hbma_ctrl.app.codegen.library import _nominal_inputs

    lib = track_library
    rti = next(st.fun for st in lib.loop.stages if st != "log" and st.name == "rti_step")
    post = rti.find_function("rti_post")
    ins = _nominal_inputs(lib.backend, rti)
    Px, q, Ax, lo, hi, _, _, chk = [np.asarray(v, float).ravel() for v in lib.qp_data(*ins)]
    pr, pc, ar, ac, nz, nc = lib.qp_setup["patterns"]
    m = osqp.OSQP()
    m.setup(sp.csc_matrix((Px, (pr, pc)), shape=(nz, nz)), q, sp.csc_matrix((Ax, (ar, ac)), shape=(nz + nc, nz)),
            lo, hi, verbose=False, eps_abs=1e-6, eps_rel=1e-6, polishing=False)
    r = m.solve()
    ref = post(r.x, r.info.obj_val, r.y[nz:], r.y[:nz], chk, *ins)
    got = lib.qp_post(r.x, r.info.obj_val, r.y, chk, Ax, lo, hi)
    for a, b in zip(ref, got):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    assert float(ref[5]) == 0.0  # the nominal step solves


@pytest.mark.slow
def test_library_osqp_settings_solve_the_nmpc_qp_to_its_tolerance(track_library):
    """OSQP with the library's settings (its scaling, the termination test every 5 iterations, the NMPC's
    tolerance and iteration limit) solves the chamber NMPC's QP at the generated setup point from a cold
    start within the iteration limit: solved, every bound met to 10 times the tolerance, the cost and the
    first inputs within that of the solution OSQP gives at 1e-10 (one Ruiz pass instead of OSQP's 10
    reaches the limit here)."""
    import osqp
    import scipy.sparse as sp

    from hbma_ctrl.app.codegen.library import QP_SETTINGS

    st = track_library.qp_setup
    pr, pc, ar, ac, nz, nc = st["patterns"]
    P = sp.csc_matrix((st["Px"], (pr, pc)), shape=(nz, nz))
    A = sp.csc_matrix((st["Ax"], (ar, ac)), shape=(nz + nc, nz))

    def solve(**kw):
        m = osqp.OSQP()
        m.setup(P, st["q"], A, st["l"], st["u"], verbose=False, polishing=False, **kw)
        return m.solve()

    ref = solve(eps_abs=1e-10, eps_rel=1e-10, max_iter=200000)
    got = solve(eps_abs=st["eps"], eps_rel=st["eps"], max_iter=st["max_iter"], **QP_SETTINGS)
    assert ref.info.status == "solved" and got.info.status == "solved"
    Az = A @ got.x
    tol = 10 * st["eps"]
    assert np.all(Az >= st["l"] - tol) and np.all(Az <= st["u"] + tol)
    assert abs(got.info.obj_val - ref.info.obj_val) <= tol * max(1.0, abs(ref.info.obj_val))
    # the inputs the controller sends: the first step's three valve inputs, at the plan's places in z
    U = np.asarray(track_library.qp_post(ref.x, 0.0, ref.y, np.zeros(track_library.qp_post.nnz_in(3)), st["Ax"],
                                         st["l"], st["u"])[0]).ravel()
    V = np.asarray(track_library.qp_post(got.x, 0.0, got.y, np.zeros(track_library.qp_post.nnz_in(3)), st["Ax"],
                                         st["l"], st["u"])[0]).ravel()
    assert np.max(np.abs(U - V)) <= tol


def test_single_precision_source_calls_float_maths_and_keeps_literals_in_range():
    """The single-precision library calls libm's float functions (``powf`` for ``pow``, not the casadi
    helpers that merely contain the name), and a literal below float's range becomes its smallest normal
    value (a guard against division by zero stays a guard) and one above it its largest."""
    from hbma_ctrl.app.codegen.library import _single

    out = _single("a=pow(b,c); x=casadi_fmin(a,b); y=sqrt(1.0e-300)+1.7976931348623157e+308+2.5e-3+fabs(a1);")
    assert "powf(b,c)" in out and "casadi_fmin(a,b)" in out and "fabsf(a1)" in out
    assert "sqrtf(1.17549435e-38)" in out and "3.40282347e+38" in out and "2.5e-3" in out


def test_profiled_driver_output_gives_the_instructions_of_each_part(tmp_path, monkeypatch):
    """A profiled board run's lines (``parts`` names, then per tick the tick's count and each part's) give
    each part's instructions (counts times the calibration), and embedded.json their medians over the
    controller's ticks; a run without ``parts`` has none."""
    from hbma_ctrl.app.codegen.library import _parse, embedded_report

    head = "calibration 50000 2000000\nworkspace 1000 bytes\nparts other ekf_step osqp_solve\n"
    ticks = ["0 0 0 0 0 5 0.001 100 1 30 69", "1 0 0 0 0 5 0.001 20 1 19 0",
             "2 0 0 0 0 5 0.001 300 1 29 270", "3 0 0 0 0 5 0.001 20 0 20 0"]
    run = _parse(head + "\n".join(ticks) + "\n")
    assert run.per_count == 40.0
    assert np.array_equal(run.parts["osqp_solve"], [2760.0, 0.0, 10800.0, 0.0])
    assert np.array_equal(run.parts["ekf_step"], [1200.0, 760.0, 1160.0, 800.0])
    elf = tmp_path / "x.elf"
    monkeypatch.setattr("hbma_ctrl.app.codegen.library._size", lambda _elf: (1, 1))  # no board program
    rep = embedded_report("cortex-m7", run, run, elf, every=2)
    assert rep["instructions_controller_tick_median_by_part"]["osqp_solve"] == 6780.0
    plain = _parse(head.replace("parts other ekf_step osqp_solve\n", "") + "0 0 0 0 0 5 0.001 100\n")
    assert plain.parts is None


@pytest.mark.slow
def test_library_and_rti_step_accept_an_osqp_solution_within_osqps_own_tolerance(track_library):
    """OSQP at the NMPC's tolerance with the small step size its embedded solver adapts to (rho 0.03, the
    termination test every 5 iterations) reports the nominal QP solved with its bounds violated by more than
    1e-3 but within OSQP's primal test, eps (1 + |Az|): the RTI step's post-processing and the library's
    both accept it (status 0) with the same commands; a violation beyond that test is rejected by both."""
    import osqp
    import scipy.sparse as sp

    from hbma_ctrl.app.codegen.library import _nominal_inputs
    from hbma_ctrl.controllers.rti_step import RES_CAP

    lib = track_library
    rti = next(st.fun for st in lib.loop.stages if st != "log" and st.name == "rti_step")
    ins = _nominal_inputs(lib.backend, rti)
    Px, q, Ax, lo, hi, _, _, chk = [np.asarray(v, float).ravel() for v in lib.qp_data(*ins)]
    st = lib.qp_setup
    pr, pc, ar, ac, nz, nc = st["patterns"]
    A = sp.csc_matrix((Ax, (ar, ac)), shape=(nz + nc, nz))
    m = osqp.OSQP()
    m.setup(sp.csc_matrix((Px, (pr, pc)), shape=(nz, nz)), q, A, lo, hi, verbose=False, polishing=False,
            eps_abs=st["eps"], eps_rel=st["eps"], max_iter=st["max_iter"], rho=0.03, adaptive_rho=0,
            check_termination=5)
    r = m.solve()
    assert r.info.status == "solved"
    Az = A @ r.x
    violation = max(np.max(lo - Az), np.max(Az - hi))
    assert 1e-3 < violation <= st["eps"] * (1.0 + np.max(np.abs(Az))) < RES_CAP
    ref = rti.find_function("rti_post")(r.x, r.info.obj_val, r.y[nz:], r.y[:nz], chk, *ins)
    got = lib.qp_post(r.x, r.info.obj_val, r.y, chk, Ax, lo, hi)
    assert float(ref[5]) == 0.0 and float(got[5]) == 0.0
    assert float(got[6]) == pytest.approx(violation, rel=1e-9)
    assert np.array_equal(np.asarray(ref[0]), np.asarray(got[0]))
    # a valve input 0.02 below its bound: beyond OSQP's test (and the cap)
    bounded = np.nonzero((lo[:nz] == 0.0) & (hi[:nz] == 1.0))[0]
    z = r.x.copy()
    z[bounded[0]] = -0.02
    assert float(lib.qp_post(z, r.info.obj_val, r.y, chk, Ax, lo, hi)[5]) == 2.0
    assert float(rti.find_function("rti_post")(z, r.info.obj_val, r.y[nz:], r.y[:nz], chk, *ins)[5]) == 2.0


@pytest.mark.compiling
@pytest.mark.slow
@needs_cc
def test_osqp_library_replays_track_height_without_a_failed_step(tmp_path, monkeypatch):
    """track_height with a horizon of 2 (which builds in seconds) on the host over its first 3.6 s: every
    tick's controller step is usable. The embedded OSQP keeps the step size it adapted and ends a solve on its
    relative primal test, and from 3.38 s on its solutions violate the valves' bounds by 1e-3 to 2e-3: an
    absolute acceptance of 1e-3 rejects 12 of these ticks."""
    from hbma_ctrl.app.codegen.library import (build_library, library_spec, record_inputs, run_library,
                                               write_inputs, write_library)
    from hbma_ctrl.app.scenario import load_scenario

    monkeypatch.setenv("OPT", "-O0")  # the Makefile's OPT: faster to build, host and board alike
    toml = tmp_path / "track_h2.toml"
    text = Path(TRACK).read_text()
    assert "\nhorizon = 20\n" in text
    toml.write_text(text.replace("\nhorizon = 20\n", "\nhorizon = 2\n"))
    scn = load_scenario(toml)
    lib = library_spec(scn)
    out = tmp_path / "osqp"
    write_library(lib, out)
    build_library(out, "host")
    run = run_library(out, "host", write_inputs(record_inputs(scn, lib, 360), out / "inputs.bin"))
    assert run.status.shape == (360,)
    assert np.all(run.status == 0)
