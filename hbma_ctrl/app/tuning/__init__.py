"""Calibrate and tune: material and dynamic fits from recorded data (``hbma-ctrl fit``) and the
estimator and controller settings search (``hbma-ctrl tune``)."""
