"""A run's signals for its report, from ``log.mcap`` when the run has one, else from its CSVs (the
daemon's ``run_*.csv`` and ``events.csv``, a chamber scene's ``closed_loop.csv``, a robot scene's
``robot_log.csv`` or ``robot_<controller>_log.csv``). Columns are named as in the MCAP log: per topic
(``/estimates``, ...) ``t_s`` and dotted paths (``h_mm.C1``), edge units."""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hbma_ctrl.app.logs.reader import columns, message_counts, read_mcap
from hbma_ctrl.runtime.watchdog import FAULT_KINDS

__all__ = ["RunSignals", "load_run", "is_fault"]

#: event kinds that are faults besides the safety monitor's (:data:`hbma_ctrl.runtime.watchdog.FAULT_KINDS`)
_FAULTS = frozenset({"safe", "unsafe_exit", "safe_failed", "deadline", "diverged"})


def is_fault(kind: str) -> bool:
    """True for an event kind that is a fault (a safety monitor's kind, the safe state, a failed exit)."""
    return kind in FAULT_KINDS or kind in _FAULTS


@dataclass
class RunSignals:
    """A run's signals.

    name : the run's name (its scenario's, else its folder's).
    names : the chambers' names.
    series : topic -> column name -> array (``t_s`` and dotted paths, edge units).
    events : (t s, kind, cause), in time order.
    pressure_limit_kpa : the run's pressure limit, kPa (None when the log has none).
    source : what it was read from ("log.mcap" or the CSV's name).
    truncated : the log ends before its footer (a killed run).
    """

    name: str
    names: list
    series: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    pressure_limit_kpa: float | None = None
    source: str = ""
    truncated: bool = False

    def get(self, topic: str, column: str):
        """(t s, values) of ``column`` of ``topic``, None when the run has no such signal (or only NaN)."""
        cols = self.series.get(topic)
        if not cols or column not in cols or "t_s" not in cols:
            return None
        y = cols[column]
        if y.dtype == object or not np.isfinite(y).any():
            return None
        return cols["t_s"], y

    def has(self, topic: str, stem: str) -> bool:
        """True when some chamber has a finite ``stem`` (``h_mm``) on ``topic``."""
        return any(self.get(topic, f"{stem}.{nm}") is not None for nm in self.names)

    def layers(self, topic: str = "/robot/pose") -> list[str]:
        """The robot's layer letters in ``topic``'s poses ([] for a chamber)."""
        cols = self.series.get(topic) or {}
        out = []
        for k in range(100):
            col = cols.get(f"layers.{k}.layer")
            if col is None:
                break
            letters = [v for v in col if v]
            out.append(letters[0] if letters else str(k))
        return out


#: the most messages per topic a report reads (a longer run's are thinned evenly)
MOST_MESSAGES = 50_000


def _mcap(path: Path) -> RunSignals:
    counts = message_counts(path) or {}
    stride = max(1, -(-max(counts.values(), default=0) // MOST_MESSAGES))
    c = read_mcap(path, stride=stride)
    meta = c.metadata
    scen = meta.get("run", {}).get("scenario_path") or ""
    sig = RunSignals(name=Path(scen).stem if scen else path.parent.name, names=[], source=path.name,
                     truncated=c.truncated)
    for topic, msgs in c.messages.items():
        if topic == "/events":
            sig.events = sorted((float(m["t_s"]), m.get("kind", ""), m.get("cause", "")) for m in msgs)
        elif msgs:
            sig.series[topic] = columns(msgs)
    chambers = meta.get("daemon", {}).get("chambers")
    if chambers:
        sig.names = chambers.split(",")
    else:
        seen: dict = {}
        for cols in sig.series.values():
            for k in cols:
                m = re.match(r"(?:p_kpa|h_mm|speed|inlet|outlet)\.(.+)$", k)
                if m:
                    seen.setdefault(m.group(1), None)
        sig.names = list(seen)
    for where, key in (("scene", "p_max_kpa"), ("scene", "pressure_limit_kpa"), ("stats", "pressure_limit_kpa")):
        v = meta.get(where, {}).get(key)
        if v not in (None, "", "null"):
            sig.pressure_limit_kpa = float(json.loads(v))
            break
    return sig


def _read_csv(paths) -> dict[str, np.ndarray]:
    rows: list = []
    header = None
    for p in paths:
        with open(p, newline="") as fh:
            r = csv.reader(fh)
            h = next(r)
            header = header or h
            rows += [row for row in r if len(row) == len(header)]
    out = {}
    for j, k in enumerate(header):
        vals = [row[j] for row in rows]
        try:
            out[k] = np.array([float(v) if v != "" else np.nan for v in vals])
        except ValueError:
            out[k] = np.array(vals, dtype=object)
    return out


def _regroup(raw: dict, spec: dict, names) -> dict:
    """topic -> columns from CSV columns: ``spec`` {topic: {stem: csv column pattern with {nm}}}."""
    out = {}
    for topic, stems in spec.items():
        cols = {"t_s": raw["t_s"]}
        for stem, pat in stems.items():
            for nm in names:
                if pat.format(nm=nm) in raw:
                    cols[f"{stem}.{nm}"] = raw[pat.format(nm=nm)]
        if len(cols) > 1:
            out[topic] = cols
    return out


def _daemon_csv(folder: Path) -> RunSignals:
    raw = _read_csv(sorted(folder.glob("run_*.csv")))
    names = [m.group(1) for k in raw for m in [re.match(r"p_(?!est_)(.+)_kpa$", k)] if m]
    spec = {"/readings": {"p_kpa": "p_{nm}_kpa"},
            "/estimates": {"h_mm": "h_est_{nm}_mm", "h_std_mm": "h_std_{nm}_mm", "p_kpa": "p_est_{nm}_kpa"},
            "/targets": {"h_mm": "target_{nm}_mm"},
            "/commands": {"speed": "speed_{nm}_1", "inlet": "inlet_{nm}_1", "outlet": "outlet_{nm}_1"}}
    sig = RunSignals(name=folder.name, names=names, series=_regroup(raw, spec, names), source="run_*.csv")
    sig.series["/loop"] = {"t_s": raw["t_s"], "step_ms": raw["step_ms"], "mode": raw["mode"]}
    ev = folder / "events.csv"
    if ev.is_file():
        with ev.open(newline="") as fh:
            sig.events = [(float(r["t_s"]), r["kind"], r["cause"]) for r in csv.DictReader(fh)]
    st = folder / "daemon_stats.json"
    if st.is_file():
        sig.pressure_limit_kpa = json.loads(st.read_text()).get("pressure_limit_kpa")
    return sig


def _scene_csv(folder: Path) -> RunSignals | None:
    if (folder / "closed_loop.csv").is_file():
        raw = _read_csv([folder / "closed_loop.csv"])
        ren = {"p_meas_kpa": "p", "p_est_kpa": "pe", "h_est_mm": "he", "target_mm": "tg", "h_true_mm": "ht",
               "p_true_kpa": "pt"}
        raw.update({f"{v}_C1": raw[k] for k, v in ren.items() if k in raw})
        for k in ("speed", "inlet", "outlet"):
            raw[f"{k}_C1"] = raw[k]
        spec = {"/readings": {"p_kpa": "p_{nm}"}, "/estimates": {"h_mm": "he_{nm}", "p_kpa": "pe_{nm}"},
                "/targets": {"h_mm": "tg_{nm}"}, "/truth": {"h_mm": "ht_{nm}", "p_kpa": "pt_{nm}"},
                "/commands": {"speed": "speed_{nm}", "inlet": "inlet_{nm}", "outlet": "outlet_{nm}"}}
        return RunSignals(name=folder.name, names=["C1"], series=_regroup(raw, spec, ["C1"]), source="closed_loop.csv")
    logs = sorted(folder.glob("robot_*_log.csv")) or sorted(folder.glob("robot_log.csv"))
    if logs:
        raw = _read_csv([logs[0]])
        names = [m.group(1) for k in raw for m in [re.match(r"h_(?!ref_|est_)(.+)_mm$", k)] if m]
        spec = {"/readings": {"p_kpa": "p_meas_{nm}_kpa"},
                "/estimates": {"h_mm": "h_est_{nm}_mm"}, "/targets": {"h_mm": "h_ref_{nm}_mm"},
                "/truth": {"h_mm": "h_{nm}_mm", "p_kpa": "p_{nm}_kpa"},
                "/commands": {"inlet": "supply_{nm}_1", "outlet": "outlet_{nm}_1"}}
        return RunSignals(name=folder.name, names=names, series=_regroup(raw, spec, names), source=logs[0].name)
    return None


def load_run(folder: Path | str) -> RunSignals:
    """The signals of the run in ``folder`` (module doc); FileNotFoundError when it has no log."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"RUN_DIR {folder}: no such directory")
    if (folder / "log.mcap").is_file():
        return _mcap(folder / "log.mcap")
    if list(folder.glob("run_*.csv")):
        return _daemon_csv(folder)
    sig = _scene_csv(folder)
    if sig is None:
        raise FileNotFoundError(f"RUN_DIR {folder}: no log.mcap, run_*.csv, closed_loop.csv or robot_*log.csv "
                                "(a run of 'hbma-ctrl run' or 'hbma-ctrl daemon')")
    return sig
