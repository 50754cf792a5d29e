"""The moving-horizon estimator's settings: the EKF's (the same model, noise and priors) and the window's."""

from __future__ import annotations

from dataclasses import dataclass

from hbma_ctrl.core.settings import setting
from hbma_ctrl.estimators.common import FilterSettings

__all__ = ["MHESettings", "SOLVERS", "QP_SOLVERS"]

SOLVERS = ("rti", "ipopt")
QP_SOLVERS = ("daqp", "qrqp", "osqp")


@dataclass
class MHESettings(FilterSettings):
    """MHE settings: the EKF's (:class:`hbma_ctrl.estimators.common.FilterSettings`, the same model, noise and
    priors) and the window's."""

    horizon: int = setting(20, integer=True, lo=2, hi=200, unit="samples",
                           doc="MHE: samples in the window (readings constraining it)")
    solver: str = setting("rti", choices=SOLVERS,
                          doc="MHE: one Gauss-Newton step per sample as generated C (rti) or a full IPOPT solve (ipopt)")
    qp_solver: str = setting("daqp", choices=QP_SOLVERS, doc="MHE: the RTI step's QP solver (its C generated with the step)")
    huber: float = setting(3.0, lo=0.0, hi=100.0,
                           doc="MHE: readings beyond this many sigmas weigh as Huber's loss does (0: least squares)")
    relinearise: int = setting(1, integer=True, lo=0, hi=200, unit="nodes",
                               doc="MHE: the newest nodes linearised afresh each step, the older keep theirs (0: all)")
    companion_ekf: bool = setting(True, doc="MHE: run the EKF beside it every sample, to restart the window from")
    reseed_cost: float = setting(5.0, lo=0.0, hi=1e6,
                                 doc="MHE: restart the window from the EKF above this cost per sample (0: never)")
    ipopt_iter: int = setting(50, integer=True, lo=1, hi=10000, unit="iterations",
                              doc="MHE: IPOPT's iteration limit per sample (solver ipopt)")
