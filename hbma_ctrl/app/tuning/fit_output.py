"""What ``hbma-ctrl fit`` writes: fit.json, params.toml (a scenario's tables, with where the numbers came
from and which membrane law they belong to) and residuals.png (SI in, edge units in the files).

:func:`write_fit` is the static fit's; :mod:`hbma_ctrl.app.tuning.fit_dynamic` writes a recorded run's with
the same head of the parameter file (:func:`toml_head`). :func:`write_scenario` puts the fitted values
into a scenario file (``fit --write-scenario``): every fitted parameter under its scenario key.
"""

from __future__ import annotations

import contextlib
import json
import os
import tomllib
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import tomli_w
from matplotlib.figure import Figure

from hbma_ctrl.app.scenario import parse_scenario
from hbma_ctrl.app.schema.base import ActuatorTable, PneumaticsTable
from hbma_ctrl.app.tuning.fit import FitReport, FitResult, unflatten
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import MATERIALS
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["LAW_NOTE", "toml_value", "toml_head", "params_toml", "write_fit", "scenario_tables", "write_scenario"]


def toml_value(v) -> str:
    """A TOML value of a parameter: a float, or a list of floats (a tuple field)."""
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(repr(float(x)) for x in v) + "]"
    return repr(float(v))


#: the params.toml line that says which law the numbers belong to (a modulus fitted with one law is
#: biased under the other: docs/how-to/fit.md, "Which membrane law")
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
    disk = "" if result.disk_radius is None else f", disk_radius_mm = {U.to_mm(result.disk_radius):g} (glued at the centre)"
    return "\n".join(toml_head(result, title, result.fidelity, disk)) + "\n"


def _plot(result: FitResult, path: Path) -> None:
    fig = Figure(figsize=(9, 4.2))
    ax1, ax2 = fig.subplots(1, 2)
    h = U.to_mm(result.h)
    order = np.argsort(h)
    ax1.plot(h, U.to_kpa(result.p_data), "o", ms=4, label="data")
    ax1.plot(h[order], U.to_kpa(result.p_model[order]), "x-" if result.contact == "free" else "x", ms=5,
             label=f"fit ({result.material})")
    ax1.set_xlabel("h (mm)")
    ax1.set_ylabel("p (kPa)")
    disk = "" if result.disk_radius is None else f"\ndisk of {U.to_mm(result.disk_radius):g} mm glued at the centre"
    ax1.set_title(f"{result.contact} contact, {result.fidelity} law, NRMSD {result.nrmsd:.4f}{disk}")
    ax1.legend()
    ax2.axhline(0.0, color="0.6", lw=0.8)
    ax2.plot(h, U.to_kpa(result.p_model - result.p_data), "o", ms=4)
    ax2.set_xlabel("h (mm)")
    ax2.set_ylabel("p residual, fit minus data (kPa)")
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


#: the simulated rig's factors on the nominal chamber ([rig] keys of the modulus, dead volume, pump, outlet)
_RIG_FACTORS = ("modulus_scale", "V0_scale", "flow_scale", "C_out_scale")


def scenario_tables(result: FitReport, law: str) -> dict:
    """The fitted values as scenario tables (edge units where the keys have them): [actuator] with the
    geometry fitted for, the material and its parameters (and a recorded run's dead volume), [pneumatics]
    flow_scale and C_out, and ``membrane = "cap"`` for the roles when the fit's ``law`` is the cap."""
    p = result.params
    act = {"r1_mm": U.to_mm(result.r1), "t0_mm": U.to_mm(result.t0), "material": result.material}
    if "V0" in p:
        act["V0_cm3"] = float(U.to_cm3(p["V0"]))
    act["material_params"] = unflatten(result.material, p)
    out = {"actuator": act}
    pn = {k: float(p[k]) for k in ("flow_scale", "C_out") if k in p}
    if pn:
        out["pneumatics"] = pn
    return out


def _merge(base: dict, new: dict) -> dict:
    """``base`` with ``new``'s keys put in; tables merged key by key, except a material's parameters,
    which are replaced whole (a fitted material's names, not the old one's)."""
    out = dict(base)
    for k, v in new.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and k != "material_params":
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _nominal(data: dict) -> tuple[str, dict, float, float, float]:
    """A scenario's nominal chamber from its tables: material, its SI parameters, dead volume (m^3), flow
    scale, outlet conductance (m^3/(s Pa))."""
    act = ActuatorTable.model_validate(data.get("actuator") or {}).to_actuator()
    pn = PneumaticsTable.model_validate(data.get("pneumatics") or {}).to_pneumatics(None)
    return act.material.name, act.material.as_dict(), act.V0, pn.flow_scale, pn.outlet.C


def _keep_rig(base: dict, data: dict) -> str | None:
    """Rescale the simulated rig's factors ([rig] modulus_scale, V0_scale, flow_scale, C_out_scale: on the
    nominal chamber) so that the rig stays the one it was while the nominal moves to the fitted values; the
    sentence saying so, or None when the scenario runs no simulated rig."""
    if not any(k in data for k in ("rig", "controller", "estimator", "daemon", "schedule")):
        return None
    (m0, par0, V0, f0, C0), (m1, par1, V1, f1, C1) = _nominal(base), _nominal(data)
    if m0 != m1:
        return (f"[rig] left as it was: the material changed ({m0} -> {m1}), so its modulus_scale has no "
                "counterpart; set it for the simulated rig you want")
    dimless = set(MATERIALS[m1].dimensionless)
    mod = next(k for k, v in par0.items() if k not in dimless and not isinstance(v, (tuple, list)))
    rig = dict(data.get("rig") or {})
    defaults = RigSettings()
    for key, ratio in zip(_RIG_FACTORS, (par0[mod] / par1[mod], V0 / V1, f0 / f1, C0 / C1)):
        rig[key] = float(rig.get(key, getattr(defaults, key)) * ratio)
    data["rig"] = rig
    return ("[rig] modulus_scale, V0_scale, flow_scale and C_out_scale rescaled by the old nominal over the fitted one: "
            "the simulated rig (its truth is the nominal chamber times these) stays the rig it was")


def write_scenario(path: Path | str, result: FitReport, law: str, source: str = "") -> list[str]:
    """Put the fitted values into the scenario file ``path`` (:func:`scenario_tables`): its tables as
    they are, each fitted key replaced (never a second one), or the fitted tables alone when the file
    does not exist. The [rig] of a simulated rig is rescaled to stay the same rig (:func:`_keep_rig`);
    ``membrane = "cap"`` goes into [estimator] and [controller] for a fit with the cap's law. The
    result is validated as a scenario before it is written (ValueError naming ``--write-scenario``);
    returns notes for the user. The file's comments are not kept (its values are)."""
    path = Path(path)
    base: dict = {}
    if path.exists():
        try:
            base = tomllib.loads(path.read_text(encoding="utf-8-sig"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ValueError(f"--write-scenario {path}: cannot read it as a scenario ({exc})") from None
    data = _merge(base, scenario_tables(result, law))
    notes = [n for n in [_keep_rig(base, data)] if n]
    if law == "cap":
        for role in ("estimator", "controller"):
            if role in data:
                data[role] = {**data[role], "membrane": "cap"}
    try:
        parse_scenario(data, path.resolve())
    except ValueError as exc:
        raise ValueError(f"--write-scenario {path}: the scenario with the fitted values is not valid: {exc}") from None
    head = [f"# fitted values from hbma-ctrl fit: {result.material}, {LAW_NOTE[law]}"]
    head += [f"# data: {source}"] if source else []
    head += [f"# {n}" for n in notes] + ["# (written by hbma-ctrl fit --write-scenario: comments are not kept)", ""]
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text("\n".join(head) + tomli_w.dumps(data), encoding="utf-8")
        os.replace(tmp, path)
    except OSError as exc:  # a folder no file can be written in (procfs, read-only, missing)
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise ValueError(f"--write-scenario {path}: cannot write it ({exc.strerror or exc})") from None
    return notes + ([] if base else [f"{path} holds the fitted tables alone: copy a scenario there first "
                                     "(hbma-ctrl scenarios copy NAME --to FILE) to run it with roles"])
