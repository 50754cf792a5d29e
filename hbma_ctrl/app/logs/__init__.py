"""Run logs as MCAP files: the writer (:mod:`hbma_ctrl.app.logs.writer`), the reader
(:mod:`hbma_ctrl.app.logs.reader`) and the CSV export (:mod:`hbma_ctrl.app.logs.export`)."""
