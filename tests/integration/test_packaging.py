"""The roles install under the package's own name: no generic top-level import names."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.subprocess


def _installed_only() -> dict:
    """This environment without PYTHONPATH (a caller's checkout on it would make any folder importable)."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


@pytest.mark.parametrize("name", ["controllers", "estimators"])
def test_generic_top_level_role_names_do_not_import_outside_the_checkout(name, tmp_path):
    # a fresh interpreter in an empty folder with no PYTHONPATH: only what is installed is importable
    r = subprocess.run([sys.executable, "-c", f"import {name}"], cwd=tmp_path, capture_output=True, text=True,
                       env=_installed_only())
    assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, r.stderr


def test_roles_import_under_the_package_name_outside_the_checkout(tmp_path):
    code = "import hbma_ctrl.estimators.ekf, hbma_ctrl.controllers.mpc; print(hbma_ctrl.controllers.mpc.NMPC.__name__)"
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                       env=_installed_only())
    assert r.returncode == 0 and r.stdout.strip() == "NMPC", r.stderr


def test_the_package_has_no_import_cycles():
    """No module imports, directly or through others, a module that imports it back (function-level
    imports included: grimp reads every import statement)."""
    import grimp

    g = grimp.build_graph("hbma_ctrl", cache_dir=None)
    cycles = sorted({tuple(sorted((m, imp))) for m in g.modules for imp in g.find_modules_directly_imported_by(m)
                     if g.chain_exists(importer=imp, imported=m)})
    assert not cycles, cycles


def test_a_cycle_is_found_when_there_is_one(tmp_path, monkeypatch):
    import grimp

    pkg = tmp_path / "cyc"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from cyc import b\n")
    (pkg / "b.py").write_text("import cyc.a\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    g = grimp.build_graph("cyc", cache_dir=None)
    assert g.chain_exists(importer="cyc.b", imported="cyc.a") and g.chain_exists(importer="cyc.a", imported="cyc.b")


def test_the_wheel_ships_every_scenario_file_the_firmware_sources_the_live_page_and_the_license_and_only_the_package(
        tmp_path):
    import shutil
    import zipfile
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    src = tmp_path / "src"
    # a copy without the checkout's build state (an in-tree build writes build/ and *.egg-info)
    shutil.copytree(repo, src, symlinks=True,
                    ignore=shutil.ignore_patterns(".git", "build", "*.egg-info", "runs", "out", "__pycache__",
                                                  ".pytest_cache", ".hypothesis"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                        "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True, env=_installed_only())
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("hbma_ctrl-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {f"hbma_ctrl/scenarios/{p.name}" for p in (repo / "scenarios").glob("*.toml")}
    assert shipped and shipped <= set(names), sorted(shipped - set(names))
    firmware = {f"hbma_ctrl/firmware/{p.relative_to(repo / 'firmware')}" for p in (repo / "firmware").rglob("*")
                if p.is_file() and (p.suffix in (".c", ".h") or p.name in ("Makefile", "README.md"))
                and "build" not in p.parts}
    assert "hbma_ctrl/firmware/src/fw.c" in firmware and firmware <= set(names), sorted(firmware - set(names))
    page = {"hbma_ctrl/app/daemon/static/live.html", "hbma_ctrl/app/daemon/static/live.js"}
    assert page <= set(names), sorted(page - set(names))
    assert {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")} == {"hbma_ctrl"}
    meta = next(zipfile.ZipFile(wheel).read(n).decode() for n in names if n.endswith(".dist-info/METADATA"))
    assert "License: MIT" in meta or "License-Expression: MIT" in meta, meta[:800]
    assert any(n.endswith("LICENSE") for n in names), [n for n in names if "dist-info" in n]
