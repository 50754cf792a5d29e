"""What every role assumes of a chamber unless told otherwise (SI: seconds).

The estimator, the start-up calibration and the controller model the same chamber by default: the
exact membrane's law (docs/concepts/model.md §9: the cap's pressure is up to 16 % low) and a small solenoid
valve's timing from its datasheet (it acts 5 ms after its command and cannot open for less than
2 ms), with the pressure sensor read 3 ms late behind its tube. These are the models' assumptions,
not the truth: the default simulated rig (:class:`hbma_ctrl.sim.rig.RigSettings`) has the same
nominal values but another structure (a first-order sensor lag, not a dead time; a pump map of
another shape; a minimum opening that drops or lengthens short pulses). A rig with other hardware
sets its own values in the scenario's ``[estimator]`` and ``[controller]`` tables, and the cap
chamber (:data:`CAP_CHAMBER`) is ``membrane = "cap"`` with the three times 0.

The robot's loop assumes the same valves (``[robot] valve_min_on_ms``, ``valve_delay_ms``) and, by
measurement, a sensor read at once (:data:`ROBOT_SENSOR_DELAY`); its chambers' law is the cap (the
robot's chambers run past the exact tables' reach).
"""

from __future__ import annotations

__all__ = ["DEFAULT_MEMBRANE", "DEFAULT_VALVE_DELAY", "DEFAULT_SENSOR_DELAY", "DEFAULT_VALVE_MIN_ON",
           "ROBOT_SENSOR_DELAY", "CAP_CHAMBER", "ROBOT_INSTANT"]

DEFAULT_MEMBRANE = "exact"
DEFAULT_VALVE_DELAY = 0.005
DEFAULT_SENSOR_DELAY = 0.003
DEFAULT_VALVE_MIN_ON = 0.002
#: the robot's chamber filters take the sensor as read at once by default: on the robot's structured
#: rig (3 ms first-order lag) a 3 ms dead time settled fewer tip-load runs over rig seeds 0-19 (16
#: against 20 of 20; docs/concepts/truth.md, "What the rig differs in")
ROBOT_SENSOR_DELAY = 0.0

#: the models' keywords for the cap chamber with instant valves and sensor (the models of docs/concepts/truth.md,
#: "The simple rig"; pair with ``hbma_ctrl.sim.rig.CAP_RIG``)
CAP_CHAMBER = {"membrane": "cap", "valve_delay": 0.0, "sensor_delay": 0.0}
#: the robot loop's keywords (:class:`hbma_ctrl.system.sections.RobotSettings`) for instant valves and
#: sensor: the loop for the robot rig without structure (``hbma_ctrl.sim.rig.IDEAL_STRUCTURE``)
ROBOT_INSTANT = {"valve_min_on": 0.0, "valve_delay": 0.0, "sensor_delay": 0.0}
