"""The daemon's run log: append-only CSV parts rotated by size, an events file, readable after a crash.

Files in the run directory (edge units, the unit in every column name):

- ``run_0001.csv``, ``run_0002.csv``, ...: one row per loop period (columns :attr:`RunLog.columns`),
  each part with its header; a part is closed once it reaches ``rotate_bytes``.
- ``events.csv``: ``t_s, wall_utc, kind, cause`` and the setpoint columns
  (:func:`setpoint_columns`: a target per chamber in mm, a pose per robot layer in mm and deg, filled
  on the setpoint events), one row per event (fault, stop, setpoint, ...), written at once.

Rows are kept in memory and appended with one ``os.write`` of whole rows at least every
``flush_s`` seconds (and on every event): a process killed at any moment (kill -9) leaves files
that hold only whole rows, at most ``flush_s`` behind. :func:`read_run_log` reads the parts back.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import math
import os
import time
from pathlib import Path

from hbma_ctrl.core import units as U

__all__ = ["RunLog", "read_run_log", "chamber_columns", "setpoint_columns", "setpoint_of_event", "setpoint_fields",
           "fmt_value", "EVENT_COLUMNS"]

#: columns of events.csv
EVENT_COLUMNS = ("t_s", "wall_utc", "kind", "cause")

#: per-chamber column stems and units
_STEMS = (("p", "kpa"), ("p_est", "kpa"), ("h_est", "mm"), ("h_std", "mm"), ("target", "mm"), ("speed", "1"),
          ("inlet", "1"), ("outlet", "1"))


def chamber_columns(names) -> list[str]:
    """The run log's columns: t_s, mode, per chamber its pressure, estimate, std, target, command, then faults."""
    cols = ["t_s", "mode"]
    for nm in names:
        cols += [f"{stem}_{nm}_{unit}" for stem, unit in _STEMS]
    return cols + ["step_ms", "faults"]


def setpoint_columns(names, n_layers: int = 0) -> list[str]:
    """events.csv's setpoint columns: ``target_<chamber>_mm`` per chamber, then ``centre_L<k>_mm``,
    ``bend_L<k>_deg``, ``direction_L<k>_deg`` per robot layer."""
    cols = [f"target_{nm}_mm" for nm in names]
    for k in range(n_layers):
        cols += [f"centre_L{k}_mm", f"bend_L{k}_deg", f"direction_L{k}_deg"]
    return cols


def setpoint_of_event(row: dict) -> dict:
    """A setpoint event's row of events.csv (a csv.DictReader row) as the loop applied it (SI:
    ``heights`` {chamber index: m}, ``layers`` {layer: (centre m, bend rad, direction rad)}); the
    chamber index is the target column's place among them."""
    out: dict = {}
    targets = [c for c in row if c.startswith("target_") and c.endswith("_mm")]
    heights = {i: U.mm(float(row[c])) for i, c in enumerate(targets) if row[c]}
    layers = {int(c[len("centre_L"):-len("_mm")]): c for c in row if c.startswith("centre_L") and row[c]}
    if heights:
        out["heights"] = heights
    if layers:
        out["layers"] = {k: (U.mm(float(row[c])), math.radians(float(row[f"bend_L{k}_deg"])),
                             math.radians(float(row[f"direction_L{k}_deg"]))) for k, c in sorted(layers.items())}
    return out


def _csv_line(values) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(values)
    return buf.getvalue()


def _append(path: Path, text: str) -> None:
    """Append ``text`` with os.write on an O_APPEND descriptor (no Python buffer: nothing half-kept)."""
    data = text.encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        while data:
            n = os.write(fd, data)
            data = data[n:]
    finally:
        os.close(fd)


class RunLog:
    """The run log of one daemon run in ``folder`` (see module doc).

    columns : the row columns (:func:`chamber_columns`).
    rotate_bytes : a part is closed at this size, bytes.
    flush_s : rows are written at least this often, s (wall clock).
    event_fields : events.csv's columns after :data:`EVENT_COLUMNS` (:func:`setpoint_columns`).
    """

    def __init__(self, folder: Path | str, columns: list[str], rotate_bytes: int = 50_000_000, flush_s: float = 0.5,
                 event_fields=()):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.columns = list(columns)
        self.rotate_bytes = int(rotate_bytes)
        self.flush_s = float(flush_s)
        self._header = _csv_line(self.columns)
        self._pending: list[str] = []
        self._last_flush = time.monotonic()
        self.part = 0
        self._size = 0
        self.events_path = self.folder / "events.csv"
        self.event_fields = list(event_fields)
        _append(self.events_path, _csv_line([*EVENT_COLUMNS, *self.event_fields]))
        self._new_part()

    @property
    def path(self) -> Path:
        """The part being written."""
        return self.folder / f"run_{self.part:04d}.csv"

    def _new_part(self) -> None:
        self.part += 1
        _append(self.path, self._header)
        self._size = len(self._header)

    def row(self, values) -> None:
        """Queue one row (len(columns) values); written at the next flush (at most ``flush_s`` later)."""
        if len(values) != len(self.columns):
            raise ValueError(f"run log row has {len(values)} values, expected {len(self.columns)}")
        self._pending.append(_csv_line(values))
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Append the queued rows (whole rows only), rotating to a new part at ``rotate_bytes``."""
        self._last_flush = time.monotonic()
        if not self._pending:
            return
        chunk: list[str] = []
        size = self._size
        for line in self._pending:
            if size >= self.rotate_bytes and size > len(self._header):
                _append(self.path, "".join(chunk))
                chunk = []
                self._new_part()
                size = self._size
            chunk.append(line)
            size += len(line)
        if chunk:
            _append(self.path, "".join(chunk))
        self._size = size
        self._pending.clear()

    def event(self, t: float, kind: str, cause: str, fields: dict | None = None) -> None:
        """Write one event at once (and the rows before it, so the two files agree in time); ``fields``:
        values of :attr:`event_fields` by column (ValueError for a column the file does not have)."""
        fields = fields or {}
        unknown = set(fields) - set(self.event_fields)
        if unknown:
            raise ValueError(f"events.csv has no column {', '.join(sorted(unknown))}")
        self.flush()
        stamp = dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")
        _append(self.events_path, _csv_line([f"{t:.4f}", stamp, kind, cause,
                                             *(fields.get(c, "") for c in self.event_fields)]))

    def close(self) -> None:
        """Write what is queued."""
        self.flush()


def read_run_log(folder: Path | str) -> tuple[list[str], list[list[str]]]:
    """(columns, rows) of every run_*.csv part in order; a row with the wrong number of fields raises
    ValueError (a torn row: the log is not whole)."""
    parts = sorted(Path(folder).glob("run_*.csv"))
    if not parts:
        raise FileNotFoundError(f"no run_*.csv in {folder}")
    header: list[str] | None = None
    rows: list[list[str]] = []
    for part in parts:
        with part.open(newline="") as fh:
            reader = csv.reader(fh)
            h = next(reader)
            if header is None:
                header = h
            elif h != header:
                raise ValueError(f"{part.name}: header differs from the first part")
            for i, r in enumerate(reader, start=2):
                if len(r) != len(header):
                    raise ValueError(f"{part.name} line {i}: {len(r)} fields, expected {len(header)}")
                rows.append(r)
    return header, rows


def fmt_value(x: float, scale: float = 1.0, digits: int = 4) -> str:
    """``x * scale`` with ``digits`` decimals for a log's column; an empty field for None or a non-finite value."""
    return "" if x is None or not math.isfinite(x) else f"{x * scale:.{digits}f}"


def setpoint_fields(applied: dict, names) -> tuple[str, dict]:
    """A setpoint as the loop applies it (SI, :mod:`hbma_ctrl.app.daemon.state`) as an event's cause
    and its run log columns (:func:`hbma_ctrl.app.daemon.runlog.setpoint_columns`, user units)."""
    fields, words = {}, []
    for i, h in sorted((applied.get("heights") or {}).items()):
        nm = names[int(i)] if 0 <= int(i) < len(names) else str(i)
        fields[f"target_{nm}_mm"] = repr(float(U.to_mm(h)))
        words.append(f"{nm} {U.to_mm(h):.3f} mm")
    for k, (c, th, ps) in sorted((applied.get("layers") or {}).items()):
        fields.update({f"centre_L{k}_mm": repr(float(U.to_mm(c))), f"bend_L{k}_deg": repr(math.degrees(th)),
                       f"direction_L{k}_deg": repr(math.degrees(ps))})
        words.append(f"layer {k} centre {U.to_mm(c):.3f} mm, bend {math.degrees(th):.2f} deg, direction "
                     f"{math.degrees(ps):.2f} deg")
    return "; ".join(words), fields
