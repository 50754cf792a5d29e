"""Controllers of one HBMA chamber's height, all with ``step(t, estimate, reference) -> Command``.

- :class:`controllers.mpc.NMPC` (settings :class:`controllers.mpc.MPCSettings`): nonlinear MPC,
  variant 'rti_c_osqp' (real-time iteration, one OSQP QP per step, its data as generated C: fast;
  'rti_osqp' the same QP built in numpy), 'rti_fn_hpipm' etc. (the
  same step as one casadi Function, :mod:`controllers.rti_step`), 'ipopt' or 'fatrop' (multiple
  shooting to convergence: accurate), on the gas-mass model of :mod:`controllers.prediction`.
- :class:`controllers.baselines.PIDController`, :class:`controllers.baselines.BangBangController`:
  the baselines the MPC is measured against.
- :mod:`controllers.scene`: the ``[controller]`` scenario section and the closed loop
  rig -> EKF -> controller -> rig; :mod:`controllers.bench`: ``hbma-ctrl bench mpc``;
  :mod:`controllers.dompc_ref`: do-mpc on the same OCP (benchmark-only extra).

Submodules are imported on use (this package imports nothing heavy by itself).
"""
