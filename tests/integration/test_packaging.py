"""The roles install under the package's own name: no generic top-level import names."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.subprocess


@pytest.mark.parametrize("name", ["controllers", "estimators"])
def test_generic_top_level_role_names_do_not_import_outside_the_checkout(name, tmp_path):
    # a fresh interpreter in an empty folder: only what is installed is importable
    r = subprocess.run([sys.executable, "-c", f"import {name}"], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, r.stderr


def test_roles_import_under_the_package_name_outside_the_checkout(tmp_path):
    code = "import hbma_ctrl.estimators.ekf, hbma_ctrl.controllers.mpc; print(hbma_ctrl.controllers.mpc.NMPC.__name__)"
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == "NMPC", r.stderr
