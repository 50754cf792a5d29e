"""Constants the CLI needs when it registers its commands (option defaults and help text).

Copies of constants whose own modules are slow to import: :data:`OPT_FLAGS` and :data:`DEFAULT_OPT`
come from :mod:`hbma_ctrl.core.loopgen` (casadi), :data:`BOND_RADIUS_MM` from
:mod:`hbma_ctrl.robot.statics` (the exact membrane). Registering the commands must not import those
modules, or every ``hbma-ctrl`` command (the protocol too) would pay for them;
tests/test_cli.py checks that each copy equals its source.
"""

from __future__ import annotations

__all__ = ["OPT_FLAGS", "DEFAULT_OPT", "BOND_RADIUS_MM"]

#: optimisation flags a generated C loop may be built with (``hbma_ctrl.core.loopgen_c.OPT_FLAGS``)
OPT_FLAGS = ("-O0", "-O1", "-O2", "-O3")
#: the default optimisation flag of that build (``hbma_ctrl.core.loopgen_c.CFLAGS[0]``)
DEFAULT_OPT = "-O1"
#: radius of the glue spot on each membrane of the bonded robot, mm (``hbma_ctrl.robot.statics.BOND_RADIUS``)
BOND_RADIUS_MM = 1.0
