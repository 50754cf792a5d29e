"""``python -m hbma_ctrl`` is the ``hbma-ctrl`` command (for a checkout that is not the installed one)."""

from hbma_ctrl.app.cli.main import app

# Guarded so that importing the module (the docs tests walk every module) does not run the CLI.
if __name__ == "__main__":
    app(prog_name="hbma-ctrl")
