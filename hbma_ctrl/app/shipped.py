"""The scenario files shipped with the package: listed, copied out, and found by name.

They are the repository's ``scenarios/`` folder, installed as package data (``hbma_ctrl/scenarios``),
so an installed package has them wherever it runs. A command given a scenario path that does not
exist, written as a shipped name (``track_height``, ``track_height.toml`` or
``scenarios/track_height.toml``), reads the shipped file (:func:`resolve`).
"""

from __future__ import annotations

import shutil
import tomllib
from importlib import resources
from pathlib import Path

from hbma_ctrl.core.validation import did_you_mean

__all__ = ["shipped_dir", "shipped", "describe", "resolve", "copy_scenario"]


def shipped_dir() -> Path:
    """The folder of the shipped scenario files."""
    return Path(str(resources.files("hbma_ctrl") / "scenarios"))


def shipped() -> dict[str, Path]:
    """Shipped scenario name (file stem) -> its file, sorted by name."""
    return {p.stem: p for p in sorted(shipped_dir().glob("*.toml"))}


def describe(path: Path) -> str:
    """One line on what a scenario file runs: the first line of its leading comment, else its kind."""
    for line in path.read_text(encoding="utf-8").splitlines():
        text = line.lstrip("# ").strip()
        if not line.startswith("#"):
            break
        if text:
            return text
    kinds = [k for k in ("controller", "robot", "estimator", "protocol", "daemon") if k in tomllib.loads(
        path.read_text(encoding="utf-8"))]
    return ", ".join(kinds)


def _name(text: str) -> str:
    """The shipped name a path-like text stands for ('scenarios/a.toml' -> 'a')."""
    p = Path(text)
    return p.stem if p.suffix == ".toml" and p.parent in (Path("."), Path("scenarios")) else text


def resolve(path: str | Path) -> Path:
    """``path`` when it exists; else the shipped file it names; else ``path`` (the reader's
    FileNotFoundError then names it)."""
    p = Path(path)
    if p.exists():
        return p
    return shipped().get(_name(str(path)), p)


def copy_scenario(name: str, dest: Path | str, overwrite: bool = False) -> Path:
    """Copy the shipped scenario ``name`` into the folder or file ``dest``; returns the file written.

    ValueError for an unknown name (with the closest one) or an existing file without ``overwrite``.
    """
    files = shipped()
    key = _name(name)
    if key not in files:
        raise ValueError(f"NAME = '{name}' is not a shipped scenario{did_you_mean(key, list(files))}; "
                         "'hbma-ctrl scenarios list' lists them")
    dest = Path(dest)
    target = dest / files[key].name if dest.is_dir() else dest
    if target.exists() and not overwrite:
        raise ValueError(f"--to: {target} already exists (give --overwrite to replace it)")
    if not target.parent.is_dir():
        raise ValueError(f"--to: the folder {target.parent} does not exist")
    try:
        shutil.copyfile(files[key], target)
    except OSError as exc:  # a place no file can be written (sysfs, procfs, a read-only folder, a full disk)
        raise ValueError(f"--to {dest}: cannot write {target} ({exc.strerror or exc})") from None
    return target
