"""How the observer model's casadi Functions are called by the filters: through preallocated buffers,
compiled once per process, and the flat or full variant by the step's mode (SI).

Used by :class:`hbma_ctrl.estimators.ekf.EKF` (its reference path) and :class:`hbma_ctrl.estimators.ukf.UKF`, and by
:mod:`hbma_ctrl.app.scenes.evaluate`.
"""

from __future__ import annotations

import warnings

import casadi as ca

from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.ekf_step import cse, observer_model
from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, compiled
from hbma_ctrl.core.params import Actuator, Pneumatics

__all__ = ["fast", "observer_functions"]

_FN_CACHE: dict = {}


def fast(fun: ca.Function, compile: bool) -> FastFunction:
    """A buffered caller of ``fun``, compiled once per process (generating the C source only to look
    up the cached library costs milliseconds, paid per filter otherwise)."""
    key = (id(fun), compile)
    if key not in _FN_CACHE:
        done = compiled(fun, HOT_OPT, HOT_FLAGS) if compile else fun
        if compile and done is fun:
            warnings.warn(f"{fun.name()}: no working C compiler (cc, gcc or clang): the estimator runs on "
                          "casadi's virtual machine, several times slower per step", RuntimeWarning, stacklevel=2)
        _FN_CACHE[key] = (fun, done)  # fun kept: its id stays unique
    return FastFunction(_FN_CACHE[key][1], False)


class _ByMode:
    """Two buffered callers of one signature: ``rest`` for a resting step (argument ``i_hold`` > 0.5),
    ``full`` otherwise, the choice the compiled step's switch makes between the model's flat and full
    Functions (so both paths compute the same bits). theta (argument ``i_theta``; None = the last one)
    goes into both buffers."""

    def __init__(self, rest: FastFunction, full: FastFunction, i_hold: int, i_theta: int):
        self.rest, self.full, self.i_hold, self.i_theta = rest, full, i_hold, i_theta

    def __call__(self, *args) -> list:
        th = args[self.i_theta]
        if th is not None:
            for f in (self.rest, self.full):
                f.inp[self.i_theta][:] = th
            args = args[:self.i_theta] + (None,) + args[self.i_theta + 1:]
        return (self.rest if args[self.i_hold] > 0.5 else self.full)(*args)


def observer_functions(actuator: Actuator, pneumatics: Pneumatics, s: FilterSettings):
    """(ObserverModel, predict, outputs, propagate Function, fast update): predict and outputs call the
    model's flat Functions on a resting step and its full ones otherwise, as the compiled step does; the
    casadi Functions are shared per configuration, the fast (buffered) callers are per filter."""
    om = observer_model(actuator, pneumatics, s)
    # the predict with its common subexpressions merged, as in the compiled step (the implicit-function
    # Jacobian evaluates each stage's shape Jacobian again, which cse merges): the same results
    pred = _ByMode(fast(cse(om.predict_rest), s.compile), fast(cse(om.predict), s.compile), 4, 3)
    outf = _ByMode(fast(cse(om.outputs_rest), s.compile), fast(cse(om.outputs), s.compile), 3, 2)
    return om, pred, outf, om.propagate, fast(om.update, s.compile)
