"""The application: scenario files, scenes, the protocol, metrics, CSV and plots, benchmarks and the
``hbma-ctrl`` command line. The only layer that imports the roles (estimators, controllers).
"""
