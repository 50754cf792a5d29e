"""Constants the CLI needs when it registers its commands (option defaults and help text).

Copies of constants whose own modules are slow to import: :data:`OPT_FLAGS` and :data:`DEFAULT_OPT`
come from :mod:`hbma_ctrl.core.loopgen` (casadi), :data:`BOND_RADIUS_MM` from
:mod:`hbma_ctrl.robot.statics` (the exact membrane), the chamber's defaults that ``equilibrium`` and
``fit`` share from :class:`hbma_ctrl.core.params.Actuator` and :mod:`hbma_ctrl.models.defaults` (casadi). Registering the commands must not import those
modules, or every ``hbma-ctrl`` command (the protocol too) would pay for them;
tests/test_cli.py checks that each copy equals its source.
"""

from __future__ import annotations

__all__ = ["OPT_FLAGS", "DEFAULT_OPT", "BOND_RADIUS_MM", "CHAMBER_R1_MM", "CHAMBER_T0_MM", "MEMBRANE_LAW", "MAX_REPLAY_S"]

#: optimisation flags a generated C loop may be built with (``hbma_ctrl.core.loopgen_c.OPT_FLAGS``)
OPT_FLAGS = ("-O0", "-O1", "-O2", "-O3")
#: the default optimisation flag of that build (``hbma_ctrl.core.loopgen_c.CFLAGS[0]``)
DEFAULT_OPT = "-O1"
#: radius of the glue spot on each membrane of the bonded robot, mm (``hbma_ctrl.robot.statics.BOND_RADIUS``)
BOND_RADIUS_MM = 1.0
#: the default chamber's clamp radius r1 and thickness t0, mm (``hbma_ctrl.core.params.Actuator``'s r1, t0):
#: the geometry ``equilibrium`` and ``fit`` assume unless told
CHAMBER_R1_MM = 12.5
CHAMBER_T0_MM = 3.0
#: the membrane law the roles assume (``hbma_ctrl.models.defaults.DEFAULT_MEMBRANE``): ``equilibrium``'s
#: and ``fit``'s default wherever it can compute what they are asked
MEMBRANE_LAW = "exact"
#: the longest run ``fit`` replays unless told, s (``hbma_ctrl.app.tuning.fit_dynamic.MAX_REPLAY_S``)
MAX_REPLAY_S = 300.0
