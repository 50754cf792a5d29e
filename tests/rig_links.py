"""Rig links wrapped for tests (imported by them; the pytest config puts this folder on sys.path)."""

from __future__ import annotations

from hbma_ctrl.app.daemon.state import DaemonState

__all__ = ["UntilRigTime"]


class UntilRigTime:
    """A rig link that asks the loop to stop once its samples have covered ``duration`` s of the rig's
    own time. The loop's duration counts its periods; a firmware process that a loaded machine runs
    late streams fewer samples in as many periods (a microcontroller would not), and the run is to
    cover the same rig time as the lockstep one it is compared with."""

    def __init__(self, rig, state: DaemonState, duration: float):
        self.rig, self.state, self.duration = rig, state, duration
        self.n, self.sample_period = rig.n, rig.sample_period
        self._t0 = None

    def read(self):
        r = self.rig.read()
        if r.t is not None:
            self._t0 = r.t if self._t0 is None else self._t0
            if r.t - self._t0 >= self.duration - 1e-9:
                self.state.request_stop("rig time")
        return r

    def __getattr__(self, name):
        return getattr(self.rig, name)
