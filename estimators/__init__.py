"""Estimators of one HBMA chamber's shape and contact force from its pressure, and of the robot's chambers.

All take ``step(t, reading, applied_command) -> Estimate``:

- :class:`hbma_ctrl.estimators.ekf.EKF` (settings :class:`hbma_ctrl.estimators.ekf.EKFSettings`): the
  extended Kalman filter on the gas mass, load and the pump, modulus and dead-volume factors; its step
  is one casadi Function (:mod:`hbma_ctrl.estimators.ekf_step`).
- :class:`hbma_ctrl.estimators.ukf.UKF`: the unscented filter on the same model, for comparison.
- :class:`hbma_ctrl.estimators.robot_ekf.ChamberEKFBank`: one filter per chamber of the robot, stepped together.
- :mod:`hbma_ctrl.estimators.observability`: what the pressure alone can tell, regime by regime.

Submodules are imported on use (this package imports nothing heavy by itself).
"""
