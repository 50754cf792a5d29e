"""Objects many test modules build the same way, built once per session.

Each is a few seconds of table building (interpolants over a gas-mass, load grid). The objects are
not changed by the tests that take them: the controllers and filters built on them read the tables
and only fill their own lazy caches of casadi Functions, which are the same whichever test fills
them. The imports are inside the fixtures so a run that uses none of them does not pay for them.
"""

from __future__ import annotations

import os

import pytest

# Every Function and generated program the tests build is compiled unoptimised (and subprocesses
# inherit it): a clean machine compiles each in seconds instead of a minute, most of a CI run, and
# no level changes a result (no level enables fast-math; test_compile_flags.py builds the shipped
# levels and checks them bit for bit against this one). A value already set is kept.
os.environ.setdefault("HBMA_CTRL_CC_OPT", "-O0")


@pytest.fixture(scope="session")
def prediction_model():
    """The controller's prediction model of the default chamber under the default (exact) law."""
    from hbma_ctrl.core.params import Actuator, Pneumatics
    from hbma_ctrl.models.tables import PredictionModel

    return PredictionModel(Actuator(), Pneumatics())


@pytest.fixture(scope="session")
def cap_prediction_model():
    """The controller's prediction model of the default chamber under the spherical-cap law."""
    from hbma_ctrl.core.params import Actuator, Pneumatics
    from hbma_ctrl.models.tables import PredictionModel

    return PredictionModel(Actuator(), Pneumatics(), membrane="cap")


def _robot_bank(topology: str):
    from hbma_ctrl.system.roles import make_model
    from hbma_ctrl.core.params import Pneumatics
    from hbma_ctrl.robot.design import RobotDesign

    # make_model reads only the design's chamber, the same for any number of layers
    return make_model(RobotDesign(n_layers=1).validate(), Pneumatics(), topology)


@pytest.fixture(scope="session")
def robot_bank():
    """The robot's nominal per-chamber model (ChamberBank), one pump per chamber."""
    return _robot_bank("per_chamber")


@pytest.fixture(scope="session")
def shared_robot_bank():
    """The robot's nominal per-chamber model (ChamberBank), one pump shared by the chambers."""
    return _robot_bank("shared")
