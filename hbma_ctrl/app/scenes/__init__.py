"""Scenes: what ``hbma-ctrl run`` and ``protocol`` simulate from a scenario (open loop, estimator,
controller, robot), with their metrics, logs and plots; :mod:`hbma_ctrl.app.scenes.runner` dispatches."""
