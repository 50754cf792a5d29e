"""Export a run's ``log.mcap`` as tables: one file per topic (``readings.csv``, ``estimates.csv``, ...,
``robot_pose.csv``), columns ``t_s`` then the messages' fields by dotted path (``h_mm.C1``; edge units,
the unit in each name), one row per message. CSV always; Parquet when pyarrow is installed (the package
does not require it)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from hbma_ctrl.app.logs.reader import columns, read_mcap

__all__ = ["export_log", "FORMATS"]

#: the export formats
FORMATS = ("csv", "parquet")


def _file_name(topic: str) -> str:
    return topic.strip("/").replace("/", "_") or "root"


def export_log(mcap_path: Path | str, out: Path | str, fmt: str = "csv") -> list[Path]:
    """Write each topic of the log at ``mcap_path`` into ``out`` (created) as ``fmt``; returns the files.
    ValueError for another format, or parquet without pyarrow."""
    if fmt not in FORMATS:
        raise ValueError(f"--format {fmt}: allowed {', '.join(FORMATS)}")
    if fmt == "parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise ValueError("--format parquet needs pyarrow, which is not installed (pip install pyarrow), "
                             "or use --format csv") from None
    c = read_mcap(mcap_path)
    if not any(c.messages.values()):  # an empty or truncated log: say so, not exit 0 with nothing written
        raise ValueError(f"RUN_DIR {Path(mcap_path).parent}: its log ({Path(mcap_path).name}) holds no message "
                         "to export (empty or cut short before its first)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for topic, msgs in c.messages.items():
        if not msgs:
            continue
        cols = columns(msgs)
        path = out / f"{_file_name(topic)}.{fmt}"
        if fmt == "csv":
            keys = list(cols)
            with path.open("w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(keys)
                for i in range(len(msgs)):
                    w.writerow(["" if isinstance(v, float) and math.isnan(v) else v
                                for v in (cols[k][i].item() if hasattr(cols[k][i], "item") else cols[k][i]
                                          for k in keys)])
        else:
            pq.write_table(pa.table({k: list(v) for k, v in cols.items()}), path)
        files.append(path)
    return files
