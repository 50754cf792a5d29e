"""The daemon's MCAP log (``log.mcap`` beside the CSV run log): what the loop hands over each period
and how the writer thread turns it into messages (edge units: mm, kPa, duty 0-1, deg, ms).

Topics (one channel each, JSON with a JSON schema; every message has ``t_s``, the rig time since the
run's start, s; chamber maps are keyed by the chamber's name):

- ``/readings``: ``p_kpa`` the measured pressure per chamber.
- ``/estimates``: ``h_mm``, ``h_std_mm``, ``p_kpa`` the estimator's height, its standard deviation and
  pressure per chamber.
- ``/targets``: ``h_mm`` the target height per chamber (null outside control).
- ``/commands``: ``speed``, ``inlet``, ``outlet`` the command written per chamber (pump speed, inlet and
  outlet valve duty, 0-1).
- ``/truth`` (simulated rigs): ``h_mm``, ``p_kpa`` the simulated rig's true height and pressure per
  chamber, at its own time ``t_s``.
- ``/robot/pose`` (robots): ``layers``, the pose of each layer from the estimated heights (``layer``,
  ``centre_mm``, ``bend_deg``, ``direction_deg``); ``/robot/pose_truth`` the same from the true heights
  (simulated rigs).
- ``/loop``: ``mode``, ``step_ms`` (the period's step time), ``faults`` (the latched fault kinds).
- ``/events``: ``kind``, ``cause`` and ``fields`` (the setpoint's columns of events.csv), as events.csv.

Metadata records: ``run`` (command, version, git commit, scenario path and hash, start time),
``daemon`` (rate, speed, rig, chambers, layers); at the end ``calibration`` (the start-up calibration's
result, when one ran), ``stats`` (daemon_stats.json's numbers) and ``log`` (messages, dropped). The
configuration file is attached as ``config.toml``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from hbma_ctrl.app.logs.writer import McapLog, finite, json_schema, number_map
from hbma_ctrl.core import units as U
from hbma_ctrl.robot.design import LETTERS
from hbma_ctrl.robot.kinematics import layer_plane

__all__ = ["DaemonRecord", "daemon_channels", "TOPICS"]

#: the daemon log's topics (see module doc)
TOPICS = ("/readings", "/estimates", "/targets", "/commands", "/truth", "/robot/pose", "/robot/pose_truth", "/loop",
          "/events")


def daemon_channels(truth: bool, robot: bool) -> dict[str, dict]:
    """The daemon log's channels (topic -> JSON schema); ``/truth`` only with ``truth``, ``/robot/pose``
    only for a ``robot``."""
    ch = {
        "/readings": json_schema("Readings", "the rig's measured pressure per chamber",
                                 {"p_kpa": number_map("measured pressure, kPa")}, ["p_kpa"]),
        "/estimates": json_schema("Estimates", "the estimator's state per chamber",
                                  {"h_mm": number_map("estimated height, mm"),
                                   "h_std_mm": number_map("standard deviation of the height, mm"),
                                   "p_kpa": number_map("estimated pressure, kPa")}, ["h_mm", "p_kpa"]),
        "/targets": json_schema("Targets", "the target height per chamber (null outside control)",
                                {"h_mm": number_map("target height, mm")}, ["h_mm"]),
        "/commands": json_schema("Commands", "the command written to the rig per chamber",
                                 {"speed": number_map("pump speed, 0-1"), "inlet": number_map("inlet valve duty, 0-1"),
                                  "outlet": number_map("outlet valve duty, 0-1")}, ["speed", "inlet", "outlet"]),
    }
    if truth:
        ch["/truth"] = json_schema("Truth", "the simulated rig's true state per chamber",
                                   {"h_mm": number_map("true height, mm"), "p_kpa": number_map("true pressure, kPa")},
                                   ["h_mm", "p_kpa"])
    if robot:
        layer = {"type": "object", "properties": {
            "layer": {"type": "string"}, "centre_mm": {"type": ["number", "null"]},
            "bend_deg": {"type": ["number", "null"]}, "direction_deg": {"type": ["number", "null"]}}}
        ch["/robot/pose"] = json_schema("Robot pose", "the pose of each layer from the estimated heights",
                                        {"layers": {"type": "array", "items": layer}}, ["layers"])
        if truth:
            ch["/robot/pose_truth"] = json_schema("True robot pose", "the pose of each layer from the true heights",
                                                  {"layers": {"type": "array", "items": layer}}, ["layers"])
    ch["/loop"] = json_schema("Loop", "the loop's mode, step time and latched faults",
                              {"mode": {"type": "string"}, "step_ms": {"type": ["number", "null"]},
                               "faults": {"type": "string", "description": "latched fault kinds, ';'-separated"}},
                              ["mode"])
    ch["/events"] = json_schema("Events", "faults, stops, setpoints and notices, as events.csv",
                                {"kind": {"type": "string"}, "cause": {"type": "string"},
                                 "fields": {"type": "object", "additionalProperties": {"type": "string"}}},
                                ["kind", "cause"])
    return ch


def _by_name(names, values, scale: float) -> dict:
    return {nm: finite(values[i] * scale) for i, nm in enumerate(names)}


class DaemonRecord:
    """The loop's side of ``log.mcap``: :meth:`step` and :meth:`event` only queue what they are given
    (copies of the period's arrays); the writer thread builds the messages (module doc).

    path : the file to write.
    names : the chambers' names.
    design : the robot's :class:`hbma_ctrl.robot.design.RobotDesign` (the poses are computed from the
        heights on the writer thread), None for a chamber.
    truth : a callable giving the simulated rig's true state (``h``, ``p`` m, Pa and ``t`` s), None
        without one.
    metadata, attachments : as :class:`hbma_ctrl.app.logs.writer.McapLog`'s.
    queue_size : items the queue holds (two per period, one per event).
    """

    def __init__(self, path: Path | str, names, design=None, truth=None, metadata: dict | None = None,
                 attachments: dict | None = None, queue_size: int = 65536):
        self.names = list(names)
        self.design = design
        self.letters = list(LETTERS[:design.n_layers]) if design is not None else []
        self.truth = truth
        self._kpa, self._mm = float(U.to_kpa(1.0)), float(U.to_mm(1.0))
        self.log = McapLog(path, daemon_channels(truth is not None, bool(self.letters)), metadata=metadata,
                           attachments=attachments, expanders={"step": self._step_messages},
                           queue_size=queue_size)

    # --- the loop's thread ------------------------------------------------------------------------
    def step(self, t: float, mode: str, p, p_est, h, h_std, target, u, step_s: float, faults: str) -> None:
        """Queue one period (SI arrays per chamber, ``u`` (3, n))."""
        tr = None
        if self.truth is not None:
            d = self.truth()
            tr = (float(d.get("t", t)), np.array(d["h"], dtype=float).ravel(), np.array(d["p"], dtype=float).ravel())
        self.log.put(t, "step", (mode, np.array(p, float), np.array(p_est, float), np.array(h, float),
                                 np.array(h_std, float), np.array(target, float), np.array(u, float),
                                 float(step_s), faults, tr))

    def event(self, t: float, kind: str, cause: str, fields: dict | None = None) -> None:
        """Queue one event."""
        self.log.put(t, "/events", {"kind": kind, "cause": cause, "fields": {k: str(v) for k, v in (fields or {}).items()}})

    # --- the writer thread ------------------------------------------------------------------------
    def _step_messages(self, t: float, item) -> list:
        mode, p, pe, h, hs, tg, u, step_s, faults, tr = item
        nm, kpa, mm = self.names, self._kpa, self._mm
        out = [("/readings", {"p_kpa": _by_name(nm, p, kpa)}),
               ("/estimates", {"h_mm": _by_name(nm, h, mm), "h_std_mm": _by_name(nm, hs, mm),
                               "p_kpa": _by_name(nm, pe, kpa)}),
               ("/targets", {"h_mm": _by_name(nm, tg, mm)}),
               ("/commands", {"speed": _by_name(nm, u[0], 1.0), "inlet": _by_name(nm, u[1], 1.0),
                              "outlet": _by_name(nm, u[2], 1.0)}),
               ("/loop", {"mode": mode, "step_ms": finite(step_s * 1e3), "faults": faults})]
        if tr is not None:
            out.append(("/truth", {"t_s": tr[0], "h_mm": _by_name(nm, tr[1], mm), "p_kpa": _by_name(nm, tr[2], kpa)}))
        if self.design is not None:
            out.append(("/robot/pose", {"layers": self._poses(h)}))
            if tr is not None:
                out.append(("/robot/pose_truth", {"t_s": tr[0], "layers": self._poses(tr[1])}))
        return out

    def _poses(self, h: np.ndarray) -> list:
        """Each layer's pose from the chamber heights ``h`` (m; [] while any is unknown)."""
        if not np.all(np.isfinite(h)):
            return []
        hh = np.maximum(h, 0.0).reshape(-1, 3)
        out = []
        for k, letter in enumerate(self.letters):
            c, b, d = layer_plane(self.design, hh[k])
            out.append({"layer": letter, "centre_mm": finite(c * self._mm), "bend_deg": finite(math.degrees(b)),
                        "direction_deg": finite(math.degrees(d))})
        return out

    # --- the end ----------------------------------------------------------------------------------
    def close(self, stats: dict | None = None, calibration: dict | None = None) -> dict:
        """Finish the file with the ``stats`` and ``calibration`` metadata; returns the log's counts."""
        meta = {}
        if calibration:
            meta["calibration"] = {k: json.dumps(v) if not isinstance(v, str) else v for k, v in calibration.items()}
        if stats:
            meta["stats"] = {k: json.dumps(v, default=str) for k, v in stats.items()}
        return self.log.close(meta)
