"""What every role assumes of a chamber unless told otherwise (SI: seconds).

The estimator, the start-up calibration and the controller model the same chamber by default: the
exact membrane's law (README Model §9: the cap's pressure is up to 16 % low) and a small solenoid
valve's timing from its datasheet (it acts 5 ms after its command and cannot open for less than
2 ms), with the pressure sensor read 3 ms late behind its tube. These are the models' assumptions,
not the truth: the default simulated rig (:class:`hbma_ctrl.sim.rig.RigSettings`) has the same
nominal values but another structure (a first-order sensor lag, not a dead time; a pump map of
another shape; a minimum opening that drops or lengthens short pulses). A rig with other hardware
sets its own values in the scenario's ``[estimator]`` and ``[controller]`` tables, and the old cap
chamber is ``membrane = "cap"`` with the three times 0.
"""

from __future__ import annotations

__all__ = ["DEFAULT_MEMBRANE", "DEFAULT_VALVE_DELAY", "DEFAULT_SENSOR_DELAY", "DEFAULT_VALVE_MIN_ON",
           "CAP_CHAMBER"]

DEFAULT_MEMBRANE = "exact"
DEFAULT_VALVE_DELAY = 0.005
DEFAULT_SENSOR_DELAY = 0.003
DEFAULT_VALVE_MIN_ON = 0.002

#: the models' keywords for the cap chamber with instant valves and sensor (how the claims before
#: 2026-12-04 were measured, on the cap rig; pair with ``hbma_ctrl.sim.rig.CAP_RIG``)
CAP_CHAMBER = {"membrane": "cap", "valve_delay": 0.0, "sensor_delay": 0.0}
