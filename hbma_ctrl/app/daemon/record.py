"""The daemon's ``log.mcap``: a :class:`hbma_ctrl.app.logs.signals.SignalLog` fed by the loop each period,
with the simulated rig's true state beside the loop's signals (topics: :mod:`hbma_ctrl.app.logs.signals`)."""

from __future__ import annotations

from pathlib import Path

from hbma_ctrl.app.logs.signals import GROUPS, SignalLog

__all__ = ["DaemonRecord"]


class DaemonRecord(SignalLog):
    """The daemon loop's MCAP log.

    path, names, design, metadata, attachments, queue_size : as :class:`hbma_ctrl.app.logs.signals.SignalLog`'s.
    truth : a callable giving the simulated rig's true state (``h`` m, ``p`` Pa, ``t`` s), None for a rig
        without one (then the log has no truth topics).
    """

    def __init__(self, path: Path | str, names, design=None, truth=None, metadata: dict | None = None,
                 attachments: dict | None = None, queue_size: int = 65536):
        groups = GROUPS if truth is not None else tuple(g for g in GROUPS if g != "truth")
        super().__init__(path, names, groups, design, metadata, attachments, queue_size)
        self.truth = truth

    def step(self, t: float, mode: str, p, p_est, h, h_std, target, u, step_s: float, faults: str) -> None:
        """Queue one period of the loop (SI arrays per chamber, ``u`` (3, n), ``step_s`` s, ``faults`` the
        latched kinds) with the rig's true state now; never blocks (a full queue drops and counts it)."""
        tr = None
        if self.truth is not None:
            d = self.truth()
            tr = (float(d.get("t", t)), d["h"], d["p"])
        self.period(t, p=p, p_est=p_est, h=h, h_std=h_std, target=target, u=u, truth=tr, mode=mode,
                    step_s=step_s, faults=faults)
