"""``hbma-ctrl report``: the figures of any run, scene or daemon, from its log
(:mod:`hbma_ctrl.app.report.load`, :mod:`hbma_ctrl.app.report.figures`)."""
