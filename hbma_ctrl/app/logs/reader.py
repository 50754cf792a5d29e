"""Read an MCAP log back (:func:`read_mcap`), also one cut short by a killed process, and turn a
topic's JSON messages into columns (:func:`columns`)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

__all__ = ["McapContents", "read_mcap", "message_counts", "columns", "flatten"]


@dataclass
class McapContents:
    """What an MCAP log holds.

    schemas : topic -> its JSON schema (a dict).
    messages : topic -> its messages (dicts, in file order).
    log_ns, publish_ns : topic -> the messages' log and publish stamps, ns.
    metadata : name -> {key: text}.
    attachments : name -> (media type, bytes).
    truncated : the file ends before its footer (a run that was killed): everything up to its last whole
        chunk is here; ``error`` says where reading stopped.
    """

    schemas: dict = field(default_factory=dict)
    messages: dict = field(default_factory=dict)
    log_ns: dict = field(default_factory=dict)
    publish_ns: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    attachments: dict = field(default_factory=dict)
    truncated: bool = False
    error: str | None = None

    def count(self, topic: str | None = None) -> int:
        """Messages on ``topic`` (all topics when None)."""
        if topic is None:
            return sum(len(v) for v in self.messages.values())
        return len(self.messages.get(topic, ()))


def message_counts(path: Path | str) -> dict[str, int] | None:
    """Messages per topic from a whole file's summary (no message read), None for a file cut short."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception:  # noqa: BLE001 - a file without its summary: the caller reads it through
        return None
    if summary is None or summary.statistics is None:
        return None
    return {ch.topic: int(summary.statistics.channel_message_counts.get(cid, 0))
            for cid, ch in summary.channels.items()}


def read_mcap(path: Path | str, stride: int = 1) -> McapContents:
    """Every record of the MCAP log at ``path`` (JSON messages decoded; with ``stride`` > 1 only every
    stride-th message of each topic but ``/events``, for a long run's figures). A file cut short (no
    footer, a torn last chunk) is read up to the last whole record and marked ``truncated``; CRCs are
    checked."""
    out = McapContents()
    seen: dict[str, int] = {}
    channels: dict[int, str] = {}
    schemas: dict[int, dict] = {}
    ended = False
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = json.loads(rec.data) if rec.data else {}
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                    out.schemas[rec.topic] = schemas.get(rec.schema_id, {})
                    for d in (out.messages, out.log_ns, out.publish_ns):
                        d.setdefault(rec.topic, [])
                elif isinstance(rec, Message):
                    topic = channels[rec.channel_id]
                    k = seen[topic] = seen.get(topic, -1) + 1
                    if stride > 1 and topic != "/events" and k % stride:
                        continue
                    out.messages[topic].append(json.loads(rec.data))
                    out.log_ns[topic].append(rec.log_time)
                    out.publish_ns[topic].append(rec.publish_time)
                elif isinstance(rec, Metadata):
                    out.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    out.attachments[rec.name] = (rec.media_type, bytes(rec.data))
            ended = True
        except Exception as exc:  # noqa: BLE001 - any record cut by a kill ends the reading, not the result
            out.error = f"{type(exc).__name__}: {exc}"
    if not ended:
        out.truncated = True
    else:
        # a whole file ends with its footer and magic; a stream that just stops is cut short too
        with open(path, "rb") as fh:
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(0, size - 8))
            if fh.read() != b"\x89MCAP0\r\n" or size < 16:
                out.truncated = True
    return out


def flatten(msg: dict, prefix: str = "") -> dict:
    """A JSON message's numbers and texts by dotted path (``estimates`` ``{"h_mm": {"C1": 2.0}}`` ->
    ``{"h_mm.C1": 2.0}``); lists are indexed (``layers.0.bend_deg``)."""
    out: dict = {}
    items = msg.items() if isinstance(msg, dict) else enumerate(msg)
    for k, v in items:
        key = f"{prefix}{k}"
        if isinstance(v, (dict, list)):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def columns(messages: list[dict]) -> dict[str, np.ndarray]:
    """A topic's messages as columns by dotted path (:func:`flatten`): float arrays (NaN for null or
    missing) for numeric fields, object arrays for text."""
    flat = [flatten(m) for m in messages]
    keys: dict = {}
    for f in flat:
        for k in f:
            keys.setdefault(k, None)
    out: dict[str, np.ndarray] = {}
    for k in keys:
        vals = [f.get(k) for f in flat]
        if all(v is None or isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
            out[k] = np.array([np.nan if v is None else float(v) for v in vals])
        else:
            out[k] = np.array(["" if v is None else v for v in vals], dtype=object)
    return out
