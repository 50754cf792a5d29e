"""The per-step Functions' compiler flags (hbma_ctrl.core.codegen.HOT_OPT, HOT_FLAGS): results that do
not depend on them, and a compiler that rejects one still builds the Function."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from hbma_ctrl.core import codegen

pytestmark = pytest.mark.skipif(not codegen.has_compiler(), reason="no C compiler (cc, gcc or clang) on this machine")


@pytest.fixture(autouse=True)
def _levels_as_named(monkeypatch):
    """Each build at the level the test names, not one the environment imposes on every build."""
    monkeypatch.delenv(codegen.OPT_ENV, raising=False)


def _function() -> ca.Function:
    """Branches, roots, powers and a subfunction called twice: what the generated step code holds."""
    x = ca.SX.sym("x", 3)
    inner = ca.Function("flags_inner", [x], [ca.sqrt(ca.fabs(x[0]) + 1e-3) * x[1] ** 3 + ca.exp(-x[2] ** 2)])
    mx = ca.MX.sym("x", 3)
    my = ca.MX.sym("y")
    out = ca.if_else(my > 0, inner(mx) * my, inner(mx[::-1]) + ca.atan2(my, 1 + mx[0] ** 2))
    return ca.Function("flags_probe", [mx, my], [out, ca.power(ca.fabs(out) + 1, 1.0 / 3.0)])


def _outputs(f: ca.Function, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    return np.hstack([np.asarray(o).ravel() for o in f.map(X.shape[1])(X, Y)])


@pytest.mark.compiling
def test_hot_flags_give_the_same_outputs_as_O1_bit_for_bit(tmp_path, monkeypatch):
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path))
    fun = _function()
    slow = codegen.compiled(fun, "-O1")
    hot = codegen.compiled(fun, codegen.HOT_OPT, codegen.HOT_FLAGS)
    assert slow is not fun and hot is not fun  # both built as C
    rng = np.random.default_rng(0)
    X = rng.normal(scale=3.0, size=(3, 400))
    Y = rng.normal(size=(1, 400))
    a, b = _outputs(slow, X, Y), _outputs(hot, X, Y)
    assert np.all(np.isfinite(a))
    assert a.tobytes() == b.tobytes()


@pytest.mark.compiling
def test_a_per_step_flag_the_compiler_rejects_is_dropped_not_the_compilation(tmp_path, monkeypatch):
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path))
    bogus = "-fno-such-option-hbma-ctrl"
    monkeypatch.setattr(codegen, "HOT_FLAGS", (bogus,))
    fun = _function()
    built = codegen.compiled(fun, codegen.HOT_OPT, [bogus])
    assert built is not fun  # generated C, not casadi's virtual machine
    X = np.array([[0.5, -2.0], [1.5, 0.3], [-0.2, 4.0]])
    Y = np.array([[1.0, -1.0]])
    np.testing.assert_array_equal(_outputs(built, X, Y), _outputs(fun, X, Y))
    # an unknown flag that is not a per-step one is still a failed build
    assert codegen.compiled(fun, "-O1", ["-fno-other-unknown-option"], on_failure="none") is None


@pytest.mark.compiling
def test_a_native_library_is_keyed_by_the_processor(tmp_path, monkeypatch):
    """A build with NATIVE_FLAGS is cached per processor (two signatures, two libraries); without them the
    processor is not part of the key (one library)."""
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path))
    fun = _function()
    for sig in ("cpu A", "cpu B"):
        monkeypatch.setattr(codegen, "cpu_signature", lambda sig=sig: sig)
        codegen._MEMO.clear()
        codegen.compiled(fun, codegen.HOT_OPT, [*codegen.HOT_FLAGS, *codegen.NATIVE_FLAGS])
        codegen.compiled(fun, codegen.HOT_OPT, codegen.HOT_FLAGS)
    libs = {p.name for p in tmp_path.glob("flags_probe_*.so")}
    assert len(libs) == 3  # the native library once per processor, the portable one once
    X = np.array([[0.5, -2.0], [1.5, 0.3], [-0.2, 4.0]])
    Y = np.array([[1.0, -1.0]])
    np.testing.assert_allclose(_outputs(codegen.compiled(fun, codegen.HOT_OPT, codegen.NATIVE_FLAGS), X, Y),
                               _outputs(fun, X, Y), rtol=1e-14)


def test_cpu_signature_names_the_processor():
    """The signature carries the instruction-set extensions where Linux lists them, and is stable."""
    from pathlib import Path

    sig = codegen.cpu_signature()
    assert isinstance(sig, str) and len(sig) > 3
    if Path("/proc/cpuinfo").exists():
        text = Path("/proc/cpuinfo").read_text()
        key = "flags" if "\nflags" in text or text.startswith("flags") else "Features"
        if key in text:
            assert f"{key}=" in sig
    assert sig == codegen.cpu_signature()  # the same machine, the same key


@pytest.mark.compiling
def test_a_build_notice_is_written_only_when_the_library_is_built(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path))
    fun = _function()
    codegen._MEMO.clear()
    codegen.compiled(fun, "-O1", notice="building the probe")
    assert "building the probe" in capsys.readouterr().err
    codegen._MEMO.clear()  # a new process: the library is on disk, nothing to build
    codegen.compiled(fun, "-O1", notice="building the probe")
    assert capsys.readouterr().err == ""


@pytest.mark.compiling
def test_the_environments_level_replaces_every_builds_own_and_keys_its_library(tmp_path, monkeypatch):
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path))
    fun = _function()
    hot = codegen.compiled(fun, codegen.HOT_OPT)
    monkeypatch.setenv(codegen.OPT_ENV, "-O0")
    quick = codegen.compiled(fun, codegen.HOT_OPT)
    again = codegen.compiled(fun, "-O2")  # the same level, whatever the caller asks: the same library
    libs = sorted(p.name for p in tmp_path.glob("*.so"))
    assert len(libs) == 2 and quick is again and quick is not hot  # its own library, never the -O3 one
    X = np.random.default_rng(1).normal(size=(3, 50))
    Y = np.random.default_rng(2).normal(size=(1, 50))
    assert _outputs(quick, X, Y).tobytes() == _outputs(hot, X, Y).tobytes()


@pytest.mark.slow
@pytest.mark.compiling
def test_the_nmpcs_qp_data_at_its_shipped_level_equals_its_unoptimised_build_bit_for_bit(
        tmp_path, monkeypatch, cap_prediction_model):
    """The per-step Function the NMPC calls most, built as users get it (HOT_OPT, HOT_FLAGS) and
    unoptimised (as the test suite builds every Function, conftest.py): the same bits, so what the
    suite checks at -O0 is what users run."""
    from hbma_ctrl.controllers.mpc_settings import MPCSettings, weights_of
    from hbma_ctrl.controllers.rti_c import _RtiOsqp, qp_data_function

    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path))
    s = MPCSettings(codegen=False).validate()
    rti = _RtiOsqp(cap_prediction_model, s)
    fun = qp_data_function(rti)
    shipped = codegen.compiled(fun, codegen.HOT_OPT, codegen.HOT_FLAGS, on_failure="none")
    monkeypatch.setenv(codegen.OPT_ENV, "-O0")
    quick = codegen.compiled(fun, codegen.HOT_OPT, codegen.HOT_FLAGS, on_failure="none")
    assert shipped is not None and quick is not None and shipped is not quick
    rng = np.random.default_rng(3)
    W = 0.4 * 9.80665
    for h in (2e-3, 5e-3, 9e-3):
        x0 = float(cap_prediction_model.x_at_height(h, W))
        par = np.r_[x0, W, 1e-4, 300.0, rng.uniform(0, 1, 3), s.p_max - s.p_margin,
                    h + rng.normal(0, 1e-3, s.horizon)]
        z = rng.normal(0, 0.1, rti.nz)
        args = [par, z, 1.0, np.asarray(weights_of(s), float)]
        a = np.hstack([np.asarray(o).ravel() for o in shipped(*args)])
        b = np.hstack([np.asarray(o).ravel() for o in quick(*args)])
        assert np.isfinite(a).all() and a.tobytes() == b.tobytes()
