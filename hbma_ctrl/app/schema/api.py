"""The rig daemon's API messages, one pydantic model each, in the user's units (mm, kPa, deg, ms, %).

Requests (:class:`SetpointRequest`, :class:`LayerPose`) are :class:`~hbma_ctrl.app.schema.fields.Table`
models like every scenario table: unknown keys, strings or booleans in numbers and non-finite
numbers (JSON has no NaN, but Python's json reads ``NaN`` and ``Infinity``) are refused, and each
number carries its bounds and unit so the error formatter can name the field and its range. The
bounds are the scenario file's (controller ``targets_mm``, robot ``targets``); what a rig can
actually reach is the daemon loop's business: it clips and says so in the reply.

Replies (:class:`Status`, :class:`SetpointReply`, :class:`StopReply`, :class:`Health`) are built by
the API from the loop's SI status dict (see :mod:`hbma_ctrl.app.daemon.api`); a value the loop has
no finite number for (no reading, no estimate yet) is ``null``.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from hbma_ctrl.app.schema.fields import RuleError, Table, elem_of, integer, num, shaped
from hbma_ctrl.app.schema.robot import pose_si
from hbma_ctrl.core import units as U
from hbma_ctrl.system.sections import POSE_BEND, POSE_HEIGHT, TARGET_HEIGHT

__all__ = [
    "CHAMBER_INDEX_MAX",
    "DIRECTION_MAX_DEG",
    "LAYER_INDEX_MAX",
    "LIVE_RATE_HZ",
    "ChamberStatus",
    "ErrorReply",
    "FaultEvent",
    "Faults",
    "Health",
    "LayerPose",
    "LayerStatus",
    "LiveEvent",
    "LiveQuery",
    "LoopTiming",
    "ResetReply",
    "SetpointApplied",
    "SetpointReply",
    "SetpointRequest",
    "Status",
    "StopReply",
]

#: bounds of a request the targets' declarations (TARGET_HEIGHT, POSE_HEIGHT, POSE_BEND) leave out
DIRECTION_MAX_DEG = 360.0
CHAMBER_INDEX_MAX = 255
LAYER_INDEX_MAX = 63
#: the live stream's event rate: default, lowest and highest (Hz of loop time)
LIVE_RATE_HZ = (5.0, 0.5, 50.0)

_HEIGHTS_SHAPE = '{"<chamber index>": h_mm, ...}'
_LAYERS_SHAPE = '[{"layer": i, "centre_mm": x, "bend_deg": x, "direction_deg": x}, ...]'

# JSON object keys are always strings: the index is parsed from "0", "1", ... (lax), then bounded
ChamberIndex = Annotated[int, Field(ge=0, le=CHAMBER_INDEX_MAX, description="chamber index (-, integer)",
                                    json_schema_extra={"unit": "-"})]


class LayerPose(Table):
    """One layer's pose target: centre height, bend angle and bend direction (mm, deg)."""

    layer: int = integer(..., 0, LAYER_INDEX_MAX, "layer index, 0 = the bottom layer")
    centre_mm: float = num(..., *POSE_HEIGHT.user_bounds(), POSE_HEIGHT.user_unit, POSE_HEIGHT.doc)
    bend_deg: float = num(..., *POSE_BEND.user_bounds(), POSE_BEND.user_unit, POSE_BEND.doc)
    direction_deg: float = num(..., -DIRECTION_MAX_DEG, DIRECTION_MAX_DEG, "deg",
                               "bend direction about the robot's axis")

    def to_si(self) -> tuple[float, float, float]:
        """(centre height m, bend rad >= 0, direction rad in (-pi, pi]), as [robot.targets] reads a row:
        a negative bend turns the direction by half a turn."""
        return pose_si(self.centre_mm, self.bend_deg, self.direction_deg)


class SetpointRequest(Table):
    """POST /setpoint: chamber heights and/or layer poses (at least one target)."""

    heights_mm: dict[ChamberIndex, elem_of(TARGET_HEIGHT)] = shaped(
        None, "target height per chamber (mm)", _HEIGHTS_SHAPE, default_factory=dict)
    layers: list[LayerPose] = shaped(None, "target pose per layer", _LAYERS_SHAPE, default_factory=list)

    @model_validator(mode="after")
    def _some_unique(self) -> SetpointRequest:
        if not self.heights_mm and not self.layers:
            raise RuleError("give heights_mm or layers (or both): an empty setpoint changes nothing",
                            "setpoint")
        seen: set[int] = set()
        for i, pose in enumerate(self.layers):
            if pose.layer in seen:
                raise RuleError(f"layers[{i}].layer = {pose.layer} is given twice", "setpoint")
            seen.add(pose.layer)
        return self

    def to_si(self) -> dict:
        """The request as :meth:`~hbma_ctrl.app.daemon.state.DaemonState.submit_setpoint` takes it:
        ``heights`` {index: m}, ``layers`` {index: (centre m, bend rad, direction rad)}; a part not
        given is left out."""
        out: dict = {}
        if self.heights_mm:
            out["heights"] = {i: U.mm(h) for i, h in self.heights_mm.items()}
        if self.layers:
            out["layers"] = {p.layer: p.to_si() for p in self.layers}
        return out


class LiveQuery(Table):
    """GET /stream's query string: how often to send the status, and how many times before ending."""

    rate_hz: float = num(LIVE_RATE_HZ[0], LIVE_RATE_HZ[1], LIVE_RATE_HZ[2], "Hz",
                         "events per second of loop time: the daemon sends every n-th status of its loop, "
                         "n = loop rate / rate_hz rounded (at least 1)")
    count: int | None = integer(None, 1, 10_000_000, "events to send before the stream ends; none = until the "
                                "daemon stops")


class Message(BaseModel):
    """Base of the replies: exactly the documented keys."""

    model_config = ConfigDict(extra="forbid")


def _out(unit: str, what: str) -> Annotated:
    """A reply number in ``unit``; null when the loop has no finite value."""
    return Field(None, description=f"{what} ({unit}); null when unknown", json_schema_extra={"unit": unit})


class ChamberStatus(Message):
    """One chamber: height estimate with its standard deviation, pressure read and estimated, command."""

    index: int = Field(description="chamber index (-)")
    name: str | None = Field(None, description="chamber name on the robot (A1, A2, ...); null on the rig")
    h_mm: float | None = _out("mm", "estimated membrane height")
    h_std_mm: float | None = _out("mm", "standard deviation of the height estimate")
    target_mm: float | None = _out("mm", "the target height the controller works to: the setpoint or the "
                                   "file's schedule, limited to what the chamber reaches under its load "
                                   "within its pressure limit")
    p_kpa: float | None = _out("kPa", "pressure reading (gauge)")
    p_est_kpa: float | None = _out("kPa", "estimated pressure (gauge)")
    speed_pct: float | None = _out("%", "compressor speed commanded")
    inlet_duty: float | None = _out("-", "inlet valve duty commanded, 0-1")
    outlet_duty: float | None = _out("-", "outlet valve duty commanded, 0-1")


class LayerStatus(Message):
    """One robot layer's estimated pose."""

    layer: int = Field(description="layer index, 0 = the bottom layer (-)")
    centre_mm: float | None = _out("mm", "centre height above the layer below")
    bend_deg: float | None = _out("deg", "bend angle")
    direction_deg: float | None = _out("deg", "bend direction")


class LoopTiming(Message):
    """The loop's step statistics since start (bounded statistics, not a history)."""

    rate_hz: float | None = _out("Hz", "loop rate")
    steps: int = Field(0, description="periods run (-)")
    deadline_misses: int = Field(0, description="periods whose step overran its deadline (-)")
    overruns: int = Field(0, description="periods whose control step overran its deadline, each a warning; a "
                          "run of [daemon] miss_limit of them in a row is the overrun fault (-)")
    step_ms_median: float | None = _out("ms", "median step time")
    step_ms_p99: float | None = _out("ms", "99th percentile step time")


class FaultEvent(Message):
    """One safety event."""

    t_s: float | None = _out("s", "loop time of the event")
    kind: str = Field(description="fault kind, e.g. sensor_nan, pressure_cap, leak")
    cause: str = Field("", description="what was seen, in words")


class Faults(Message):
    """Counts by kind since start, and the latest events (newest last)."""

    counts: dict[str, int] = Field(default_factory=dict, description="events per kind since start (-)")
    latest: list[FaultEvent] = Field(default_factory=list, description="the latest events, newest last")


class Status(Message):
    """GET /status."""

    mode: str = Field(description="starting, running, safe or stopped")
    t_s: float | None = _out("s", "loop time of this snapshot")
    age_ms: float | None = _out("ms", "time since the loop published this snapshot")
    stop_requested: bool = Field(False, description="a stop has been asked for (true/false)")
    chambers: list[ChamberStatus] = Field(default_factory=list, description="per chamber, by index")
    layers: list[LayerStatus] = Field(default_factory=list, description="per robot layer; empty on the rig")
    loop: LoopTiming = Field(default_factory=LoopTiming, description="step timing")
    faults: Faults = Field(default_factory=Faults, description="safety events")


class LiveEvent(Status):
    """One event of GET /stream (the ``data`` of a server-sent event): the status as GET /status gives
    it, and how the stream decimates."""

    every_steps: int | None = Field(None, description="loop periods between the statuses sent (-); null "
                                    "before the loop reports its rate")
    lost: int = Field(0, description="statuses published since the last event that the stream read too late "
                      "to choose from (-; 0 unless the client or the server fell behind)")


class SetpointApplied(Message):
    """What the loop will apply at its next period, after clipping (mm, deg)."""

    heights_mm: dict[int, float] = Field(default_factory=dict, description="height per chamber (mm)")
    layers: list[LayerStatus] = Field(default_factory=list, description="pose per layer (mm, deg)")


class SetpointReply(Message):
    """POST /setpoint: what will be applied and every clip made (an empty list: none)."""

    applied: SetpointApplied
    clipped: list[str] = Field(default_factory=list, description="one message per clipped target")


class StopReply(Message):
    """POST /stop: the stop is asked for; the loop sends the safe command at its next period."""

    stop_requested: bool = Field(True, description="always true")
    reason: str = Field(description="the first stop reason (a later stop keeps it)")
    mode: str = Field(description="the loop's mode when the stop was asked for")


class ResetReply(Message):
    """POST /reset: the readings are sane and the reset is asked for; the loop leaves the safe state
    at its next period (when the readings are still sane then)."""

    reset_requested: bool = Field(True, description="always true")
    detail: str = Field(description="what the loop will do")


class Health(Message):
    """GET /health: the API answers; ``mode`` and ``age_ms`` say how the loop is."""

    ok: bool = Field(True, description="always true: the API answers")
    mode: str = Field(description="starting, running, safe or stopped")
    age_ms: float | None = _out("ms", "time since the loop last published its status; null before")


class ErrorReply(Message):
    """Every error's body: one line, and the validation errors of a refused message."""

    error: str = Field(description="what was refused and why, one line")
    detail: Any = Field(None, description="the line again, or the list of validation errors (422)")
