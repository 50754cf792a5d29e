"""An MCAP log written off the caller's thread: one channel per signal group, JSON messages with a
JSON schema each, nanosecond stamps, the run's metadata and attachments in the file.

The caller (the control loop) only puts items on a bounded queue (:meth:`McapLog.put`, never
blocking: an item that finds the queue full is dropped and counted in :attr:`McapLog.dropped`). A
writer thread wakes every ``batch_s`` seconds, takes what has piled up in one batch, turns each item
into one or more messages (an *expander* registered for the item's kind does that work on the writer
thread, so the caller hands over raw arrays), encodes them as JSON and writes them with the ``mcap``
package's writer into chunks. Waking in batches, not on every item, spares the caller a thread
switch (and a wait for Python's interpreter lock) every period; the writer thread also runs at a
lower scheduling priority (``nice``) than its process, so that on a busy machine the caller's thread
gets a core first.

A chunk is closed and written to the file when it reaches ``chunk_bytes`` or at least every
``flush_s`` seconds (wall clock): a process killed at any moment (SIGKILL) leaves a file whose
chunks before the last are whole, readable by :func:`hbma_ctrl.app.logs.reader.read_mcap`.

Stamps: a message's ``log_time`` is the run's clock (``t_s`` s of the item, from the run's start)
added to the wall time the log started, ns since the Unix epoch, so the timeline of a viewer
(Foxglove, Lichtblick, PlotJuggler) is the rig's time whatever the run's speed; its
``publish_time`` is the wall time it was put on the queue, ns since the Unix epoch. Every message
also carries ``t_s`` (the run's clock, s) as its first field.
"""

from __future__ import annotations

import json
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from mcap.writer import CompressionType, Writer

__all__ = ["McapLog", "json_schema", "number_map", "finite", "SCHEMA_ENCODING", "MESSAGE_ENCODING"]

#: the schema and message encodings of every channel (MCAP's well-known JSON encodings)
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

_NUMBER = {"type": ["number", "null"]}
_STOP = object()


def finite(x) -> float | None:
    """``x`` as a float, None (JSON null) where it is NaN or infinite."""
    x = float(x)
    return x if math.isfinite(x) else None


def number_map(description: str) -> dict:
    """The JSON schema of an object of numbers (null where there is none) keyed by a name (a chamber's)."""
    return {"type": "object", "description": description, "additionalProperties": _NUMBER}


def json_schema(title: str, description: str, properties: dict, required: Iterable[str] = ()) -> dict:
    """A message's JSON schema: ``t_s`` (the run's clock, s) and ``properties`` (name -> JSON schema)."""
    props = {"t_s": {"type": "number", "description": "time since the run's start, s"}, **properties}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": props,
            "required": ["t_s", *required]}


class McapLog:
    """An MCAP log at ``path`` (see module doc), written by its own thread from :meth:`put`.

    channels : topic -> JSON schema (:func:`json_schema`); one channel each, its schema named by the
        schema's ``title``.
    metadata : name -> {key: text}, MCAP metadata records written first.
    attachments : file name -> (media type, bytes), MCAP attachments written first.
    expanders : item kind -> ``f(t_s, payload) -> [(topic, message dict), ...]``, run on the writer
        thread; an item whose kind is a topic is that topic's message.
    queue_size : items the queue holds; a :meth:`put` that finds it full drops its item.
    chunk_bytes : a chunk is closed at this size (uncompressed), bytes.
    flush_s : a chunk is closed and the file flushed at least this often, s (wall clock).
    compression : "zstd", "lz4" or "none" (per chunk).
    batch_s : the writer thread wakes this often to write what has been queued, s.
    nice : how much lower the writer thread's scheduling priority is than its process's (Linux; 0 = the same).
    """

    def __init__(self, path: Path | str, channels: dict[str, dict], *, metadata: dict | None = None,
                 attachments: dict | None = None, expanders: dict[str, Callable] | None = None,
                 queue_size: int = 65536, chunk_bytes: int = 256 * 1024, flush_s: float = 1.0,
                 compression: str = "zstd", library: str = "hbma-ctrl", batch_s: float = 0.2, nice: int = 10):
        self.path = Path(path)
        self.flush_s = float(flush_s)
        self.batch_s = min(float(batch_s), self.flush_s)
        self.nice = int(nice)
        self._closing = threading.Event()
        self.expanders = dict(expanders or {})
        self.start_ns = time.time_ns()
        #: items dropped because the queue was full
        self.dropped = 0
        #: items put on the queue
        self.queued = 0
        #: messages written, by topic
        self.written: dict[str, int] = {t: 0 for t in channels}
        #: items the writer thread could not turn into messages (the first one's error in :attr:`error`)
        self.failed = 0
        self.error: str | None = None
        self._q: queue.Queue = queue.Queue(maxsize=int(queue_size))
        self._fh = open(self.path, "wb")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self._w = Writer(self._fh, chunk_size=int(chunk_bytes), compression=comp)
        self._w.start(profile="", library=library)
        self._chan: dict[str, int] = {}
        for topic, schema in channels.items():
            sid = self._w.register_schema(name=schema.get("title", topic), encoding=SCHEMA_ENCODING,
                                          data=json.dumps(schema).encode())
            self._chan[topic] = self._w.register_channel(topic=topic, message_encoding=MESSAGE_ENCODING,
                                                         schema_id=sid)
        for name, data in (metadata or {}).items():
            self._w.add_metadata(name, {str(k): str(v) for k, v in data.items()})
        for name, (media, data) in (attachments or {}).items():
            self._w.add_attachment(create_time=self.start_ns, log_time=self.start_ns, name=name,
                                   media_type=media, data=bytes(data))
        self._w.flush()  # the header, schemas, channels and metadata are on disk before the first message
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="mcap-log", daemon=True)
        self._thread.start()

    @property
    def topics(self) -> list[str]:
        """The log's topics, in the order they were registered."""
        return list(self._chan)

    def put(self, t_s: float, kind: str, payload, block: bool = False) -> bool:
        """Queue one item at the run's clock ``t_s`` (s): a message dict for topic ``kind``, or the payload
        of the expander ``kind``. Never blocks unless ``block``; False (and :attr:`dropped` counted) when
        the queue is full."""
        try:
            self._q.put((float(t_s), time.time_ns(), kind, payload), block=block)
        except queue.Full:
            self.dropped += 1
            return False
        self.queued += 1
        return True

    # --- the writer thread ------------------------------------------------------------------------
    def _messages(self, t_s: float, kind: str, payload) -> list:
        f = self.expanders.get(kind)
        return f(t_s, payload) if f is not None else [(kind, payload)]

    def _write(self, item) -> None:
        t_s, pub_ns, kind, payload = item
        try:
            msgs = self._messages(t_s, kind, payload)
            log_ns = self.start_ns + int(round(t_s * 1e9))
            for topic, msg in msgs:
                data = json.dumps({"t_s": t_s, **msg}, allow_nan=False, separators=(",", ":")).encode()
                self._w.add_message(self._chan[topic], log_time=log_ns, data=data, publish_time=pub_ns,
                                    sequence=self.written[topic])
                self.written[topic] += 1
        except Exception as exc:  # noqa: BLE001 - a bad item must not end the log of the items after it
            self.failed += 1
            if self.error is None:
                self.error = f"{kind}: {type(exc).__name__}: {exc}"

    def _lower_priority(self) -> None:
        """The writer thread ``nice`` steps below its process (Linux schedules threads one by one)."""
        if self.nice <= 0:
            return
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + self.nice))
        except (AttributeError, OSError):  # not on this platform: the same priority as the caller
            pass

    def _run(self) -> None:
        self._lower_priority()
        last = time.monotonic()
        while True:
            self._closing.wait(self.batch_s)
            batch = []
            while True:  # everything queued so far, in one go
                try:
                    batch.append(self._q.get_nowait())
                except queue.Empty:
                    break
            stop = False
            for it in batch:
                if it is _STOP:
                    stop = True
                    continue
                self._write(it)
            if stop:
                return
            if time.monotonic() - last >= self.flush_s:
                self._w.flush()
                last = time.monotonic()

    # --- the end ----------------------------------------------------------------------------------
    def stats(self) -> dict:
        """What the log holds and lost: messages (total and by topic), items queued, dropped, failed."""
        return {"messages": sum(self.written.values()), "by_topic": dict(self.written), "queued": self.queued,
                "dropped": self.dropped, "failed": self.failed, "error": self.error}

    def close(self, metadata: dict | None = None) -> dict:
        """Write every queued item, then ``metadata`` (name -> {key: text}) and the ``log`` metadata
        record (its :meth:`stats`), and finish the file (its summary and index); returns :meth:`stats`."""
        if self._closed:
            return self.stats()
        self._closed = True
        self._q.put(_STOP)  # blocks only if the queue is full: the writer thread is emptying it
        self._closing.set()
        self._thread.join()
        st = self.stats()
        for name, data in (metadata or {}).items():
            self._w.add_metadata(name, {str(k): str(v) for k, v in data.items()})
        self._w.add_metadata("log", {"messages": str(st["messages"]), "queued": str(st["queued"]),
                                     "dropped": str(st["dropped"]), "failed": str(st["failed"]),
                                     "error": st["error"] or ""})
        self._w.finish()
        self._fh.close()
        return st

    def __enter__(self) -> "McapLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
