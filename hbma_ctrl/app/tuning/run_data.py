"""A recorded run of one chamber, read from its CSV (SI inside): what ``hbma-ctrl fit`` fits to.

A recorded run is a CSV with a time column ``t_s``, the pressure reading, the commands (compressor
speed, inlet and outlet duty) and optionally the height and the load; the files the package writes
are accepted as they are (:data:`COLUMN_ALIASES`, first match wins; :mod:`hbma_ctrl.app.tuning.fit_dynamic`
lists which file has which), the daemon's run log too: one chamber's columns chosen by its name
(:data:`CHAMBER_COLUMNS`), its repeated times (a period with no new sample, the stop) read as one row. :func:`parse_run` checks it (one error naming the column, row and the
allowed range in the file's units): times increasing, readings in kPa, a vented start, isolated
dropouts skipped and longer runs of them refused. :func:`is_dynamic` tells such a file from a
static (pressure-height) data file.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.validation import did_you_mean

__all__ = ["CHAMBER_COLUMNS", "COLUMN_ALIASES", "MAX_MISSING_RUN", "chamber_names", "P_KPA_MAX", "RunData", "check_height_unit", "data_lines", "data_number", "data_rows",
           "is_dynamic", "parse_run"]

#: role -> accepted column names, first match wins (see the module docstring for which file has which)
COLUMN_ALIASES = {
    "t": ("t_s",),
    "p": ("p_meas_kpa", "p_kpa"),
    "speed": ("speed", "speed_pct"),
    "inlet": ("inlet", "inlet_duty"),
    "outlet": ("outlet", "outlet_duty"),
    "h": ("h_mm", "h_true_mm"),
    "load": ("load_g",),
}
_REQUIRED = ("t", "p", "speed", "inlet", "outlet")
#: a daemon run log's per-chamber columns (:func:`hbma_ctrl.app.daemon.runlog.chamber_columns`):
#: role -> (prefix, suffix) around the chamber's name
CHAMBER_COLUMNS = {"p": ("p_", "_kpa"), "speed": ("speed_", "_1"), "inlet": ("inlet_", "_1"),
                   "outlet": ("outlet_", "_1")}
#: longest run of missing readings (dropouts) that is skipped rather than refused
MAX_MISSING_RUN = 5
#: p_kpa above this looks like Pa
P_KPA_MAX = 1000.0
#: rows further apart than this (s, median) look like times in ms: a chamber fills in about a second
MAX_ROW_STEP = 0.5
#: heights all below this (mm) while the pressure reaches P_KPA_MOVED look like metres
H_MM_MIN = 0.5
P_KPA_MOVED = 2.0
#: a gauge reading below this (kPa) is not noise around zero
_P_KPA_MIN = -10.0
#: the run must start vented: first reading at most this (kPa)
_P_START_MAX_KPA = 3.0

@dataclass(frozen=True)
class RunData:
    """A recorded run in SI: times t (s, from 0), pressure readings p (Pa; NaN = skipped), commands
    u (n x 3: speed, inlet, outlet, 0-1), heights h (m; None = not recorded), the load (kg) and the
    column name used for each role."""

    t: np.ndarray
    p: np.ndarray
    u: np.ndarray
    h: np.ndarray | None
    load: float
    columns: dict


def data_lines(raw: bytes) -> list[str]:
    """A data CSV's lines from its bytes (UTF-8, a BOM allowed), blank and '#' lines left out;
    ValueError naming the first byte that is not UTF-8 and its line."""
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ValueError(f"data: not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line}); save the "
                         "file as UTF-8") from None
    return [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def data_rows(raw: bytes, expected: str) -> tuple[list[str], list[list[str]]]:
    """A data CSV's header (names stripped) and data rows from its bytes (:func:`data_lines`);
    ValueError for an empty file, saying which header was ``expected``."""
    lines = data_lines(raw)
    if not lines:
        raise ValueError(f"data: the file is empty; expected a header {expected}")
    rows = list(csv.reader(io.StringIO("\n".join(lines))))
    header = [c.strip() for c in rows[0]]
    twice = sorted({c for c in header if c and header.count(c) > 1})
    if twice:  # the reader would take the first and ignore the other without a word
        raise ValueError(f"data: column '{twice[0]}' appears {header.count(twice[0])} times in the header; keep one")
    return header, rows[1:]


def is_dynamic(raw: bytes) -> bool:
    """True when the CSV's header has a ``t_s`` column (a recorded run), False for static points."""
    lines = data_lines(raw)
    if not lines:
        return False
    header = [c.strip() for c in next(csv.reader(io.StringIO(lines[0])))]
    return "t_s" in header


def _value(cells: list[str], i: int, col: str, row: int, missing_ok: bool) -> float:
    """Cell ``i`` of a row as a number; NaN for a missing one where ``missing_ok``, else ValueError."""
    text = cells[i].strip() if i < len(cells) else ""
    if text == "" or text.lower() == "nan":
        if missing_ok:
            return float("nan")
        raise ValueError(f"data: column '{col}', row {row}: missing value")
    return data_number(text, col, row)


def data_number(text: str, col: str, row: int) -> float:
    """A data cell's finite number; ValueError naming the column and the 1-based data row."""
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"data: column '{col}', row {row}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"data: column '{col}', row {row}: {text!r} is not a finite number")
    return v


def check_height_unit(h_mm: np.ndarray, p_kpa: np.ndarray, col: str) -> None:
    """ValueError naming ``col`` when the heights look like metres: all below :data:`H_MM_MIN` mm while the
    pressure (kPa) reaches :data:`P_KPA_MOVED` (a membrane that held that much is millimetres high)."""
    h_top, p_top = np.nanmax(np.abs(h_mm), initial=0.0), np.nanmax(p_kpa, initial=0.0)
    if h_top < H_MM_MIN and p_top >= P_KPA_MOVED:
        raise ValueError(f"data: column '{col}': the heights are at most {h_top:g} mm while the pressure reaches "
                         f"{p_top:g} kPa; the values look like metres: convert them to mm")


def _missing_runs(v: np.ndarray, col: str) -> None:
    """Refuse a run of more than MAX_MISSING_RUN missing values (rows are 1-based)."""
    bad = np.isnan(v)
    k = 0
    for i, b in enumerate(bad):
        k = k + 1 if b else 0
        if k > MAX_MISSING_RUN:
            start = i - k + 2
            raise ValueError(f"data: column '{col}', rows {start}-{i + 1}: more than {MAX_MISSING_RUN} missing "
                             "readings in a row (only isolated dropouts are skipped); cut the run or fill the gap")


def chamber_names(header: list[str]) -> list[str]:
    """The chambers of a daemon run log's header (each with its pressure, speed, inlet and outlet
    columns, :data:`CHAMBER_COLUMNS`), in order; [] for a file of one chamber's plain columns."""
    pre, post = CHAMBER_COLUMNS["p"]
    names = [c[len(pre):-len(post)] for c in header if c.startswith(pre) and c.endswith(post) and len(c) > 6]
    return [n for n in names if all(f"{a}{n}{b}" in header for a, b in CHAMBER_COLUMNS.values())]


def _columns(header: list[str], chamber: str | None) -> tuple[dict[str, str], bool]:
    """role -> column name as written, and whether the file is a daemon run log (per-chamber columns)."""
    names = chamber_names(header)
    if names:
        if chamber is None and len(names) > 1:
            raise ValueError(f"--chamber: the run log holds {len(names)} chambers ({', '.join(names)}); choose one "
                             f"with --chamber NAME")
        name = names[0] if chamber is None else chamber
        if name not in names:
            raise ValueError(f"--chamber {chamber}: no such chamber in the run log; the chambers are "
                             f"{', '.join(names)}{did_you_mean(chamber, names)}")
        # the log's height is the filter's estimate, not a measurement: it is not fitted to
        return {"t": "t_s", **{r: f"{a}{name}{b}" for r, (a, b) in CHAMBER_COLUMNS.items()}}, True
    if chamber is not None:
        raise ValueError(f"--chamber {chamber}: the file has no per-chamber columns (a daemon run log's "
                         f"p_<name>_kpa, speed_<name>_1, ...); columns: {', '.join(header)}")
    col: dict[str, str] = {}
    for role, names in COLUMN_ALIASES.items():
        hit = next((n for n in names if n in header), None)
        if hit is not None:
            col[role] = hit
        elif role in _REQUIRED:
            hint = did_you_mean(names[0], header)
            alt = f" (or '{names[1]}')" if len(names) > 1 else ""
            raise ValueError(f"data: missing column '{names[0]}'{alt}{hint}; a recorded run needs t_s, p_kpa, "
                             f"speed, inlet, outlet (or a daemon run log); columns: {', '.join(header)}")
    return col, False


def parse_run(raw: bytes, load_kg: float | None = None, chamber: str | None = None) -> RunData:
    """A recorded run from a CSV file's bytes, in SI (see the module docstring for the columns).

    ``load_kg`` is the load for a file without a ``load_g`` column (None = 0, free inflation).
    ``chamber``: the chamber of a daemon run log to read, by name (None: its only one).
    One ValueError naming the column (as written) and the 1-based data row for bad data.
    """
    header, rows = data_rows(raw, "with t_s, p_kpa, speed, inlet, outlet")
    col, daemon_log = _columns(header, chamber)
    if "load" in col and load_kg is not None:
        raise ValueError("--load-g: the file has a 'load_g' column; give the load once")
    idx = {role: header.index(name) for role, name in col.items()}
    vals: dict[str, list] = {role: [] for role in col}
    for row, cells in enumerate(rows, start=1):
        for role, name in col.items():
            v = _value(cells, idx[role], name, row, missing_ok=role in ("p", "h"))
            if role == "p" and math.isfinite(v):
                if v > P_KPA_MAX:
                    raise ValueError(f"data: column '{name}', row {row}: {v:g} kPa is above {P_KPA_MAX:g} kPa; the "
                                     "values look like Pa: convert them to kPa")
                if v < _P_KPA_MIN:
                    raise ValueError(f"data: column '{name}', row {row}: gauge pressure {v:g} kPa is below "
                                     f"{_P_KPA_MIN:g} kPa")
            elif role in ("speed", "inlet", "outlet"):
                top = 100.0 if name.endswith("_pct") else 1.0
                if not 0.0 <= v <= top:
                    pct = (f"; '{name}' is a fraction 0-1 (a percentage belongs in a '{name}_pct' column)"
                           if name == "speed" and v <= 100 else "")
                    raise ValueError(f"data: column '{name}', row {row}: {v:g} is out of range [0, {top:g}]{pct}")
            elif role == "h" and math.isfinite(v) and v < 0:
                raise ValueError(f"data: column '{name}', row {row}: height {v:g} mm is negative")
            elif role == "load":
                if not 0.0 <= v <= 50000.0:
                    raise ValueError(f"data: column '{name}', row {row}: {v:g} g is out of range [0, 50000] g")
                if vals["load"] and v != vals["load"][0]:
                    raise ValueError(f"data: column '{name}', row {row}: the load changes ({vals['load'][0]:g} -> "
                                     f"{v:g} g); a dynamic fit takes one load per run: cut the run at the change")
            vals[role].append(v)
    if not vals["t"]:
        raise ValueError("data: no data rows below the header")
    if daemon_log:
        # the daemon logs a period the rig's clock did not move in (no new sample) and its last row
        # (the safe command at the stop) at the time of the row before: the last row of a time is the
        # command that held from it
        t_log = np.array(vals["t"])
        keep = np.flatnonzero(np.r_[t_log[1:] != t_log[:-1], True])
        vals = {role: [v[i] for i in keep] for role, v in vals.items()}
    t = np.array(vals["t"])
    step = np.diff(t)
    if np.any(step <= 0):
        i = int(np.argmax(step <= 0)) + 2
        what = "repeated" if step[i - 2] == 0 else "unsorted"
        raise ValueError(f"data: column 't_s', row {i}: time {t[i - 1]:g} s is not after the previous row's "
                         f"{t[i - 2]:g} s ({what} time); sort the rows and drop duplicates")
    if t.size > 2 and float(np.median(step)) > MAX_ROW_STEP:
        raise ValueError(f"data: column '{col['t']}': the rows are {float(np.median(step)):g} s apart (median); the "
                         "times look like milliseconds: convert them to seconds (a recorded run samples the chamber "
                         f"every {MAX_ROW_STEP:g} s or faster)")
    p_kpa = np.array(vals["p"])
    _missing_runs(p_kpa, col["p"])
    first = np.flatnonzero(np.isfinite(p_kpa))
    if first.size == 0:
        raise ValueError(f"data: column '{col['p']}': no readings")
    if p_kpa[first[0]] > _P_START_MAX_KPA:
        raise ValueError(f"data: column '{col['p']}', row {first[0] + 1}: the run starts at {p_kpa[first[0]]:g} kPa; "
                         f"the fit replays it from a vented chamber (start the log at most {_P_START_MAX_KPA:g} kPa)")
    h = None
    if "h" in col:
        h_mm = np.array(vals["h"])
        _missing_runs(h_mm, col["h"])
        check_height_unit(h_mm, p_kpa, col["h"])
        h = U.mm(h_mm)
    # commands as fractions 0-1 (a '_pct' column holds percent)
    u = np.column_stack([np.array(vals[r]) / (100.0 if col[r].endswith("_pct") else 1.0)
                         for r in ("speed", "inlet", "outlet")])
    load = U.grams(vals["load"][0]) if "load" in col else float(load_kg or 0.0)
    return RunData(t - t[0], U.kpa(p_kpa), u, h, float(load), {r: col[r] for r in col})


# ---------------------------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------------------------
