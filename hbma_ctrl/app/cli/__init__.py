"""The ``hbma-ctrl`` command line: :mod:`hbma_ctrl.app.cli.main` holds the application and its top-level
commands; each other module registers one group of commands with ``register(app, bench_app)``."""
