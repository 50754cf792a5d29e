"""One declarative schema (pydantic v2) for every table of a scenario file.

Each table is a model whose fields are named as the user writes them (``p_max_kpa``, ``r1_mm``),
in the user's units, with their bounds; each converts once to the SI objects the package runs on.
Errors are one line naming the table and key: see :mod:`.errors`.

Entry points: :func:`parse_scenario_tables` (whole file -> Scenario), :func:`parse_role` (one role
table -> its settings), :func:`search_space` (a table's numbers and bounds, for tuning).
"""

from hbma_ctrl.app.schema.base import (
           ActuatorTable,
           InputsTable,
           LoadTable,
           PneumaticsTable,
           ProtocolTable,
           ScenarioTable,
           SimTable,
)
from hbma_ctrl.app.schema.controller import ControllerTable
from hbma_ctrl.app.schema.document import (
           ROLE_TABLES,
           ScenarioFile,
           parse_role,
           parse_scenario_tables,
)
from hbma_ctrl.app.schema.errors import format_error
from hbma_ctrl.app.schema.estimator import EstimatorTable
from hbma_ctrl.app.schema.fields import RuleError, Table
from hbma_ctrl.app.schema.rig import RigTable
from hbma_ctrl.app.schema.robot import RobotTable
from hbma_ctrl.app.schema.space import search_space

__all__ = [
           "ROLE_TABLES",
           "ActuatorTable",
           "ControllerTable",
           "EstimatorTable",
           "InputsTable",
           "LoadTable",
           "PneumaticsTable",
           "ProtocolTable",
           "RigTable",
           "RobotTable",
           "RuleError",
           "ScenarioFile",
           "ScenarioTable",
           "SimTable",
           "Table",
           "format_error",
           "parse_role",
           "parse_scenario_tables",
           "search_space",
]
