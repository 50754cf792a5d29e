"""Models of one chamber built on the core: the fidelity ladder the simulator integrates, the reduced
chamber model every estimator and controller shares, its equilibrium tables and mapped banks.
"""
