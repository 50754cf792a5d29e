"""A run's signals as an MCAP log (``log.mcap``), the same topics for the daemon and the scenes: what
a run hands over each period and how the writer thread turns it into messages (edge units: mm, kPa,
duty 0-1, deg, ms). A run writes the topics it has (``groups``): the open-loop scenes have no
estimates, a real rig no truth.

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
  ``centre_mm``, ``bend_deg``, ``direction_deg``); ``/robot/pose_target`` the same from the target
  heights, ``/robot/pose_truth`` from the true heights (simulated rigs).
- ``/loop``: ``mode``, ``step_ms`` (the period's step time), ``faults`` (the latched fault kinds).
- ``/events``: ``kind``, ``cause`` and ``fields`` (the setpoint's columns of events.csv), as events.csv.

Metadata records: ``run`` (command, version, git commit, scenario path and hash, start time) and
what the run adds (the daemon: ``daemon``, its rate, speed, rig and chambers; at the end
``calibration``, the start-up calibration's result when one ran, and ``stats``, daemon_stats.json's
numbers); last ``log`` (messages, dropped). The scenario or configuration file is attached as
``config.toml``.
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

__all__ = ["SignalLog", "signal_channels", "TOPICS", "GROUPS"]

#: the daemon log's topics (see module doc)
TOPICS = ("/readings", "/estimates", "/targets", "/commands", "/truth", "/robot/pose", "/robot/pose_target",
          "/robot/pose_truth", "/loop", "/events")


#: the signal groups a run may have (each one topic; "truth" is /truth, and /robot/pose_truth for a robot)
GROUPS = ("readings", "estimates", "targets", "commands", "truth", "loop")


def signal_channels(groups, robot: bool) -> dict[str, dict]:
    """The log's channels (topic -> JSON schema) for the signal ``groups`` (of :data:`GROUPS`),
    ``/robot/pose`` for a ``robot``, and ``/events``."""
    groups = set(groups)
    truth = "truth" in groups
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
    ch = {k: v for k, v in ch.items() if k[1:] in groups}
    if truth:
        ch["/truth"] = json_schema("Truth", "the simulated rig's true state per chamber",
                                   {"h_mm": number_map("true height, mm"), "p_kpa": number_map("true pressure, kPa")},
                                   ["h_mm", "p_kpa"])
    if robot and groups & {"estimates", "targets", "truth"}:
        layer = {"type": "object", "properties": {
            "layer": {"type": "string"}, "centre_mm": {"type": ["number", "null"]},
            "bend_deg": {"type": ["number", "null"]}, "direction_deg": {"type": ["number", "null"]}}}
        if "estimates" in groups:
            ch["/robot/pose"] = json_schema("Robot pose", "the pose of each layer from the estimated heights",
                                            {"layers": {"type": "array", "items": layer}}, ["layers"])
        if "targets" in groups:
            ch["/robot/pose_target"] = json_schema("Target robot pose", "the pose of each layer from the target heights",
                                                   {"layers": {"type": "array", "items": layer}}, ["layers"])
        if truth:
            ch["/robot/pose_truth"] = json_schema("True robot pose", "the pose of each layer from the true heights",
                                                  {"layers": {"type": "array", "items": layer}}, ["layers"])
    if "loop" in groups:
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


class SignalLog:
    """The run's side of ``log.mcap``: :meth:`period` and :meth:`event` only queue what they are given
    (copies of the period's arrays); the writer thread builds the messages (module doc).

    path : the file to write.
    names : the chambers' names.
    groups : the signal groups the run has (of :data:`GROUPS`).
    design : the robot's :class:`hbma_ctrl.robot.design.RobotDesign` (the poses are computed from the
        heights on the writer thread), None for a chamber.
    metadata, attachments : as :class:`hbma_ctrl.app.logs.writer.McapLog`'s.
    queue_size : items the queue holds (one per period, one per event).
    """

    def __init__(self, path: Path | str, names, groups=GROUPS, design=None, metadata: dict | None = None,
                 attachments: dict | None = None, queue_size: int = 65536):
        self.names = list(names)
        self.groups = set(groups)
        self.design = design
        self.letters = list(LETTERS[:design.n_layers]) if design is not None else []
        self._kpa, self._mm = float(U.to_kpa(1.0)), float(U.to_mm(1.0))
        self.log = McapLog(path, signal_channels(self.groups, design is not None), metadata=metadata,
                           attachments=attachments, expanders={"period": self._period_messages},
                           queue_size=queue_size)

    # --- the run's thread -------------------------------------------------------------------------
    def period(self, t: float, *, p=None, p_est=None, h=None, h_std=None, target=None, u=None,
               truth: tuple | None = None, mode: str = "", step_s: float = math.nan, faults: str = "",
               block: bool = False) -> bool:
        """Queue one period at run time ``t`` (s): SI arrays per chamber (``p`` measured, ``p_est``, ``h``,
        ``h_std`` estimated, ``target`` heights, ``u`` the command (3, n), ``truth`` (t s, h, p)); a group
        left None or not in :attr:`groups` is not written. ``block``: wait for room in the queue (a
        scene writing its whole run) instead of dropping. False when dropped."""
        arr = lambda x: None if x is None else np.array(x, dtype=float)  # noqa: E731 - copies: the caller reuses its arrays
        tr = None if truth is None else (float(truth[0]), arr(truth[1]).ravel(), arr(truth[2]).ravel())
        return self.log.put(t, "period", (mode, arr(p), arr(p_est), arr(h), arr(h_std), arr(target), arr(u),
                                          float(step_s), faults, tr), block=block)

    def event(self, t: float, kind: str, cause: str, fields: dict | None = None, block: bool = False) -> bool:
        """Queue one event (``fields``: text by column, as events.csv's setpoint columns)."""
        return self.log.put(t, "/events", {"kind": kind, "cause": cause,
                                           "fields": {k: str(v) for k, v in (fields or {}).items()}}, block=block)

    # --- the writer thread ------------------------------------------------------------------------
    def _period_messages(self, t: float, item) -> list:
        mode, p, pe, h, hs, tg, u, step_s, faults, tr = item
        nm, kpa, mm, g = self.names, self._kpa, self._mm, self.groups
        out = []
        if p is not None and "readings" in g:
            out.append(("/readings", {"p_kpa": _by_name(nm, p, kpa)}))
        est = h is not None and "estimates" in g
        if est:
            nan = np.full(len(nm), np.nan)
            out.append(("/estimates", {"h_mm": _by_name(nm, h, mm), "h_std_mm": _by_name(nm, nan if hs is None else hs, mm),
                                       "p_kpa": _by_name(nm, nan if pe is None else pe, kpa)}))
        if tg is not None and "targets" in g:
            out.append(("/targets", {"h_mm": _by_name(nm, tg, mm)}))
        if u is not None and "commands" in g:
            out.append(("/commands", {"speed": _by_name(nm, u[0], 1.0), "inlet": _by_name(nm, u[1], 1.0),
                                      "outlet": _by_name(nm, u[2], 1.0)}))
        if "loop" in g:
            out.append(("/loop", {"mode": mode, "step_ms": finite(step_s * 1e3), "faults": faults}))
        tr = tr if "truth" in g else None
        if tr is not None:
            out.append(("/truth", {"t_s": tr[0], "h_mm": _by_name(nm, tr[1], mm), "p_kpa": _by_name(nm, tr[2], kpa)}))
        if self.design is not None:
            if est:
                out.append(("/robot/pose", {"layers": self._poses(h)}))
            if tg is not None and "targets" in g:
                out.append(("/robot/pose_target", {"layers": self._poses(tg)}))
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
        """Finish the file with the ``stats`` and ``calibration`` metadata (written as JSON texts); returns
        the log's counts (:meth:`hbma_ctrl.app.logs.writer.McapLog.stats`)."""
        meta = {}
        if calibration:
            meta["calibration"] = {k: json.dumps(v) if not isinstance(v, str) else v for k, v in calibration.items()}
        if stats:
            meta["stats"] = {k: json.dumps(v, default=str) for k, v in stats.items()}
        return self.log.close(meta)
