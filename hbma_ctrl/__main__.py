"""``python -m hbma_ctrl`` is the ``hbma-ctrl`` command (for a checkout that is not the installed one)."""

from hbma_ctrl.app.cli import app

app(prog_name="hbma-ctrl")
