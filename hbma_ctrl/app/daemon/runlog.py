"""The daemon's run log: append-only CSV parts rotated by size, an events file, readable after a crash.

Files in the run directory (edge units, the unit in every column name):

- ``run_0001.csv``, ``run_0002.csv``, ...: one row per loop period (columns :attr:`RunLog.columns`),
  each part with its header; a part is closed once it reaches ``rotate_bytes``.
- ``events.csv``: ``t_s, wall_utc, kind, cause``, one row per event (fault, stop, setpoint, ...),
  written at once.

Rows are kept in memory and appended with one ``os.write`` of whole rows at least every
``flush_s`` seconds (and on every event): a process killed at any moment (kill -9) leaves files
that hold only whole rows, at most ``flush_s`` behind. :func:`read_run_log` reads the parts back.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import os
import time
from pathlib import Path

__all__ = ["RunLog", "read_run_log", "chamber_columns", "EVENT_COLUMNS"]

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
    """

    def __init__(self, folder: Path | str, columns: list[str], rotate_bytes: int = 50_000_000, flush_s: float = 0.5):
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
        _append(self.events_path, _csv_line(EVENT_COLUMNS))
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

    def event(self, t: float, kind: str, cause: str) -> None:
        """Write one event at once (and the rows before it, so the two files agree in time)."""
        self.flush()
        stamp = dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")
        _append(self.events_path, _csv_line([f"{t:.4f}", stamp, kind, cause]))

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
