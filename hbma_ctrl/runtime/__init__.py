"""The runtime layer a daemon embeds: ``tick(t, readings) -> commands`` objects composing estimator(s),
controller and one safety supervisor, with no I/O inside.
"""
