"""Fault injection between the daemon's loop and a rig: :class:`FaultyRig` wraps any RigIO (SI inside).

Each fault acts on chosen chambers (an index or all) from ``start`` (rig time, s) for ``duration``
s (None = until the end); the rig time is the readings' own time stamp (``Readings.t``; the number of
writes times the sample period when the rig gives none). Faults on what is READ:

- ``dropout``: the reading is NaN (no value);
- ``frozen``: the reading repeats the last value delivered before the fault began, ``fresh`` False;
- ``offset``: the reading is off by ``offset`` Pa;
- ``out_of_range``: the reading is ``value`` Pa (e.g. a broken wire: far below the vacuum floor);
- ``link_loss``: :meth:`FaultyRig.read` raises :class:`RigLinkError`.

Faults on what is WRITTEN (the command the loop sends is modified before it reaches the rig; the
loop's own record of what it sent is unchanged, as on a real rig):

- ``stuck_inlet`` / ``stuck_outlet``: that valve's duty is ``value`` whatever is commanded;
- ``leak``: the outlet opens ``value`` more than commanded (at most fully): an extra outlet
  conductance of ``value`` times the outlet valve's;
- ``pump_failure``: the pump speed is 0 on those chambers.

A write is judged at the time of the last read (the command holds from then for one period).
:meth:`FaultyRig.safe` passes straight to the rig: a loop that stays in its safe state writes
:func:`~hbma_ctrl.system.rigio.safe_u` every period, and those writes go through the faults (a
stuck inlet stays stuck in the safe state too).

``[[daemon.fault]]`` tables (:func:`parse_faults`), in the user's units::

    [[daemon.fault]]
    kind = "offset"          # dropout, frozen, offset, out_of_range, stuck_inlet, stuck_outlet,
    chamber = 0              #   leak, pump_failure, link_loss; chamber: index or "all" (default)
    start_s = 2.0            # default 0
    duration_s = 1.5         # default: until the end
    offset_kpa = 3.0         # offset: offset_kpa; out_of_range: value_kpa; stuck_*, leak: duty
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from hbma_ctrl.system.rigio import Readings, RigIO, RigLinkError, check_u
from hbma_ctrl.app.schema.errors import format_error
from hbma_ctrl.app.schema.fields import RuleError, Table, choice, num
from hbma_ctrl.core import units as U

__all__ = ["INJECTED_KINDS", "FaultSpec", "FaultTable", "FaultyRig", "parse_faults"]

#: what :class:`FaultyRig` can inject, and the value key each kind takes (None: no value)
VALUE_KEY = {"dropout": None, "frozen": None, "offset": "offset_kpa", "out_of_range": "value_kpa",
             "stuck_inlet": "duty", "stuck_outlet": "duty", "leak": "duty", "pump_failure": None,
             "link_loss": None}
INJECTED_KINDS = tuple(VALUE_KEY)
_READ_KINDS = ("dropout", "frozen", "offset", "out_of_range", "link_loss")
#: what a fault on what is written does: (the command's row, its new value from the commanded one and the
#: fault's value)
_WRITE_FAULTS = {"stuck_inlet": (1, lambda u, v: v), "stuck_outlet": (2, lambda u, v: v),
                 "leak": (2, lambda u, v: np.minimum(1.0, u + v)), "pump_failure": (0, lambda u, v: 0.0)}
_VALUE_TO_SI = {"offset_kpa": U.kpa, "value_kpa": U.kpa, "duty": float}


@dataclass(frozen=True)
class FaultSpec:
    """One fault to inject (SI): kind (one of INJECTED_KINDS), chamber index (None = all), start s,
    duration s (None = until the end), value (Pa for offset and out_of_range, duty in [0, 1] for the
    stuck valves and the leak, unused otherwise)."""

    kind: str
    chamber: int | None = None
    start: float = 0.0
    duration: float | None = None
    value: float = 0.0

    def active(self, t: float) -> bool:
        """Whether the fault acts at rig time t (s): start <= t < start + duration."""
        eps = 1e-9
        return t + eps >= self.start and (self.duration is None or t + eps < self.start + self.duration)

    def columns(self, n: int) -> slice | list:
        """The chamber columns it acts on for an n-chamber rig."""
        return slice(None) if self.chamber is None else [self.chamber]


class FaultTable(Table):
    """One [[daemon.fault]] table in the user's units (see the module doc); :meth:`to_spec` gives SI."""

    kind: Literal[INJECTED_KINDS] = choice(..., "what fails")
    chamber: int | Literal["all"] = Field("all", description="chamber index (0 = first) or \"all\"")
    start_s: float = num(0.0, 0.0, 1e6, "s", "rig time the fault begins")
    duration_s: float | None = num(None, 0.0, 1e6, "s", "how long it lasts; default: until the end",
                                   lo_open=True)
    offset_kpa: float | None = num(None, -100.0, 100.0, "kPa", "offset: added to the reading")
    value_kpa: float | None = num(None, -1000.0, 1000.0, "kPa", "out_of_range: the reading reported")
    duty: float | None = num(None, 0.0, 1.0, "-", "stuck_inlet/stuck_outlet: the valve's duty; "
                             "leak: extra outlet opening")

    @field_validator("chamber", mode="before")
    @classmethod
    def _chamber(cls, v):
        # one message for every wrong chamber (pydantic would report each member of the union)
        if v == "all" or (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
            return v
        raise RuleError(f"chamber = {v!r} must be a chamber index >= 0 or \"all\"")

    @model_validator(mode="after")
    def _value_keys(self) -> "FaultTable":
        want = VALUE_KEY[self.kind]
        for key in ("offset_kpa", "value_kpa", "duty"):
            given = getattr(self, key) is not None
            if given and key != want:
                takes = f"it takes {want}" if want else "it takes no value key"
                raise RuleError(f"{key}: not a key of kind '{self.kind}' ({takes})")
        if want is not None and getattr(self, want) is None:
            raise RuleError(f"kind '{self.kind}' needs {want} ({type(self).model_fields[want].description})")
        return self

    def to_spec(self) -> FaultSpec:
        """The SI fault."""
        key = VALUE_KEY[self.kind]
        value = _VALUE_TO_SI[key](getattr(self, key)) if key else 0.0
        return FaultSpec(self.kind, None if self.chamber == "all" else int(self.chamber), float(self.start_s),
                         None if self.duration_s is None else float(self.duration_s), float(value))


def parse_faults(rows, n: int | None = None) -> list[FaultSpec]:
    """The ``[[daemon.fault]]`` array of tables (a list of dicts, user's units) as SI faults.

    ``n``: the rig's chamber count, to check the chamber indices (None = not checked). Bad input
    raises ONE ValueError naming the table and key as written and the allowed values, e.g.
    ``[daemon.fault[1]] offset_kpa = 500.0 is out of range [-100, 100] kPa``.
    """
    if rows is None:
        return []
    if not isinstance(rows, (list, tuple)):
        raise ValueError("[daemon] fault must be an array of tables ([[daemon.fault]]), "
                         f"got {type(rows).__name__}")
    out = []
    for i, raw in enumerate(rows):
        where = f"daemon.fault[{i}]"
        if not isinstance(raw, dict):
            raise ValueError(f"[{where}] must be a table (kind, chamber, start_s, duration_s, value key), "
                             f"got {type(raw).__name__}")
        try:
            spec = FaultTable.model_validate(raw).to_spec()
        except ValidationError as exc:
            raise ValueError(format_error(exc, FaultTable, where)) from None
        if n is not None and spec.chamber is not None and spec.chamber >= n:
            raise ValueError(f"[{where}] chamber = {spec.chamber} is out of range: the rig has {n} "
                             f"chamber(s), allowed 0..{n - 1} or \"all\"")
        out.append(spec)
    return out


class FaultyRig:
    """A RigIO that passes through to ``rig`` with ``faults`` injected (see module doc).

    ``t`` is the rig time of the last read (s); ``injected`` counts, per kind, the periods a fault acted.
    """

    def __init__(self, rig: RigIO, faults):
        self.rig = rig
        self.simulated: bool = bool(getattr(rig, "simulated", False))
        self.n: int = int(rig.n)
        self.sample_period: float = float(rig.sample_period)
        self.faults: list[FaultSpec] = [f if isinstance(f, FaultSpec) else f.to_spec() for f in faults]
        for f in self.faults:
            if f.kind not in INJECTED_KINDS:
                raise ValueError(f"fault kind '{f.kind}': allowed {', '.join(INJECTED_KINDS)}")
            if f.chamber is not None and not 0 <= f.chamber < self.n:
                raise ValueError(f"fault chamber = {f.chamber}: allowed 0..{self.n - 1} or all")
        self.t = 0.0
        self.injected: dict = {k: 0 for k in INJECTED_KINDS}
        self._writes = 0
        self._last_p: np.ndarray | None = None
        self._frozen: dict = {}  # fault index -> the values it holds

    def active(self, t: float | None = None) -> list[FaultSpec]:
        """The faults acting at rig time t (default: the last read's)."""
        t = self.t if t is None else t
        return [f for f in self.faults if f.active(t)]

    def read(self) -> Readings:
        """The rig's readings with the sensor faults applied; raises RigLinkError under a link loss."""
        r = self.rig.read()
        self.t = float(r.t) if r.t is not None else self._writes * self.sample_period
        p = np.array(r.p, dtype=float)
        fresh = np.array(r.fresh, dtype=bool) if np.size(r.fresh) == self.n else np.ones(self.n, dtype=bool)
        for j, f in enumerate(self.faults):
            if f.kind not in _READ_KINDS or not f.active(self.t):
                continue
            c = f.columns(self.n)
            self.injected[f.kind] += 1
            if f.kind == "link_loss":
                raise RigLinkError(f"link lost (injected fault from {f.start:g} s)")
            if f.kind == "dropout":
                p[c] = np.nan
            elif f.kind == "frozen":
                if j not in self._frozen:
                    before = p if self._last_p is None else self._last_p
                    self._frozen[j] = np.array(before, dtype=float)[c].copy()
                p[c] = self._frozen[j]
                fresh[c] = False
            elif f.kind == "offset":
                p[c] = p[c] + f.value
            elif f.kind == "out_of_range":
                p[c] = f.value
        self._last_p = p.copy()
        return Readings(t=r.t, p=p, seq=r.seq, fresh=fresh, held=r.held)

    def write(self, u: np.ndarray) -> None:
        """Pass ``u`` (3, n) on with the actuator faults acting at the last read's time applied."""
        out = check_u(u, self.n).copy()
        for f in self.faults:
            if f.kind in _WRITE_FAULTS and f.active(self.t):
                row, value = _WRITE_FAULTS[f.kind]
                c = f.columns(self.n)
                out[row, c] = value(out[row, c], f.value)
                self.injected[f.kind] += 1
        self.rig.write(out)
        self._writes += 1

    def safe(self) -> None:
        """The rig's own safe command (passed straight through; see the module doc)."""
        self.rig.safe()

    def close(self) -> None:
        """Close the rig."""
        self.rig.close()

    def truth(self) -> dict:
        """The wrapped rig's true state (simulated rigs only)."""
        return self.rig.truth()
