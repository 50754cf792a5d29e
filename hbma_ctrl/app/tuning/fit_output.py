"""What ``hbma-ctrl fit`` writes: fit.json, params.toml (a scenario's tables, with where the numbers came
from and which membrane law they belong to) and residuals.png (SI in, edge units in the files).

:func:`write_fit` is the static fit's; :mod:`hbma_ctrl.app.tuning.fit_dynamic` writes a recorded run's with
the same head of the parameter file (:func:`toml_head`).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.app.tuning.fit import FitReport, FitResult, unflatten
from hbma_ctrl.core import units as U

__all__ = ["LAW_NOTE", "toml_value", "toml_head", "params_toml", "write_fit"]


def toml_value(v) -> str:
    """A TOML value of a parameter: a float, or a list of floats (a tuple field)."""
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(repr(float(x)) for x in v) + "]"
    return repr(float(v))


#: the params.toml line that says which law the numbers belong to (a modulus fitted with one law is
#: biased under the other: README Calibrate, "The exact law")
LAW_NOTE = {"cap": "the spherical cap (use with [estimator] / [controller] / [rig] membrane = \"cap\")",
             "exact": "the exact membrane (membrane = \"exact\", the roles' default)"}


def toml_head(result: FitReport, title: str, law: str, fitted_for: str = "", actuator: tuple = ()) -> list[str]:
    """A parameter file's lines up to its ``[actuator.material_params]`` (SI): the ``title`` comment, the
    geometry it was fitted for (and ``fitted_for``), the membrane ``law``, where the numbers came from,
    ``[actuator]`` with the material and the ``actuator`` lines, and the material's parameters."""
    when = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [f"# hbma-ctrl fit{title}",
             f"# fitted for r1_mm = {U.to_mm(result.r1):g}, t0_mm = {U.to_mm(result.t0):g}{fitted_for}",
             f"# membrane law: {LAW_NOTE[law]}"]
    # where the numbers came from travels with them into any scenario that copies this file
    lines += ([f"# data: {result.source}"] if result.source else []) + [f"# written: {when}"]
    lines += ["[actuator]", f'material = "{result.material}"', *actuator, "", "[actuator.material_params]"]
    return lines + [f"{k} = {toml_value(v)}" for k, v in unflatten(result.material, result.params).items()]


def params_toml(result: FitResult) -> str:
    """A parameter file for a scenario: ``[actuator]`` material and ``[actuator.material_params]`` (SI)."""
    title = f": {result.material}, contact {result.contact}, {result.n_points} points, NRMSD {result.nrmsd:.4f}"
    return "\n".join(toml_head(result, title, result.fidelity)) + "\n"


def _plot(result: FitResult, path: Path) -> None:
    fig = Figure(figsize=(9, 4.2))
    ax1, ax2 = fig.subplots(1, 2)
    h = U.to_mm(result.h)
    order = np.argsort(h)
    ax1.plot(h, U.to_kpa(result.p_data), "o", ms=4, label="data")
    ax1.plot(h[order], U.to_kpa(result.p_model[order]), "x-" if result.contact == "free" else "x", ms=5,
             label=f"fit ({result.material})")
    ax1.set_xlabel("height h (mm)")
    ax1.set_ylabel("pressure p (kPa)")
    ax1.set_title(f"{result.contact} contact, {result.fidelity} law, NRMSD {result.nrmsd:.4f}")
    ax1.legend()
    ax2.axhline(0.0, color="0.6", lw=0.8)
    ax2.plot(h, U.to_kpa(result.p_model - result.p_data), "o", ms=4)
    ax2.set_xlabel("height h (mm)")
    ax2.set_ylabel("residual p_fit - p (kPa)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def write_fit(result: FitReport, folder: Path | str, toml: str | None = None,
              plot: Callable[[FitReport, Path], None] | None = None) -> list[Path]:
    """Write fit.json, params.toml and residuals.png into ``folder``; returns their paths. ``toml`` and
    ``plot(result, path)``: the parameter file's text and the plot (None: a static fit's)."""
    folder = Path(folder)
    paths = [folder / "fit.json", folder / "params.toml", folder / "residuals.png"]
    paths[0].write_text(json.dumps(result.as_json(), indent=1) + "\n")
    paths[1].write_text(params_toml(result) if toml is None else toml)
    (plot or _plot)(result, paths[2])
    return paths
