"""Benchmarks behind ``hbma-ctrl bench ...``: each module measures one part (simulator, loop, NMPC, fit,
soak, drills, poses) and writes its JSON and plots into a run directory."""
