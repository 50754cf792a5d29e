"""Controllers of one HBMA chamber's height, all with ``step(t, estimate, reference) -> Command``.

- :class:`hbma_ctrl.controllers.mpc.NMPC` (settings :class:`hbma_ctrl.controllers.mpc.MPCSettings`): nonlinear MPC,
  variant 'rti_c_osqp' (real-time iteration, one OSQP QP per step, its data as generated C: fast;
  'rti_osqp' the same QP data on casadi's virtual machine), 'rti_fn_hpipm' etc. (the
  same step as one casadi Function, :mod:`hbma_ctrl.controllers.rti_step`), 'ipopt' or 'fatrop' (multiple
  shooting to convergence: accurate), on the gas-mass model of :class:`hbma_ctrl.models.tables.PredictionModel`.
- :class:`hbma_ctrl.controllers.baselines.PIDController`, :class:`hbma_ctrl.controllers.baselines.BangBangController`:
  the baselines the MPC is measured against.
- :class:`hbma_ctrl.controllers.robot_mpc.RobotNMPC`, :class:`hbma_ctrl.controllers.robot_pid.RobotPressurePID`:
  the robot's chambers, all at once.
- :mod:`hbma_ctrl.controllers.dompc_ref`: do-mpc on the same OCP (benchmark-only extra).

Submodules are imported on use (this package imports nothing heavy by itself).
"""
