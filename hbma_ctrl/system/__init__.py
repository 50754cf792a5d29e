"""The system layer: a validated scenario's pieces assembled into what runs, and the rigs it runs on (SI).

- :mod:`hbma_ctrl.system.sections`: the scenario in SI units (:class:`~hbma_ctrl.system.sections.Scenario`
  and its role sections), what the application's loader builds from a scenario file;
- :mod:`hbma_ctrl.system.rigio`: the one rig interface, ``read() -> Readings`` and ``write(u)`` with
  ``u`` of shape (3, n), for the chamber and the robot alike;
- :mod:`hbma_ctrl.system.sim_rig` (the simulated rigs in lockstep) and
  :mod:`hbma_ctrl.system.serial_link` (firmware speaking the line protocol) implement it.
"""
