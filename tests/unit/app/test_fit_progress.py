"""The dynamic fit's progress on stderr when it is not a terminal (hbma_ctrl.app.cli.fit._progress)."""

from __future__ import annotations

from hbma_ctrl.app.cli import fit as fit_cli


def test_without_a_terminal_the_fit_prints_a_progress_line_every_10_s_with_the_time_left(capsys, monkeypatch):
    now = [100.0]
    monkeypatch.setattr(fit_cli._progress, "clock", staticmethod(lambda: now[0]))
    monkeypatch.setattr(fit_cli.sys.stderr, "isatty", lambda: False, raising=False)
    with fit_cli._progress() as bar:
        bar(1, 40)  # at once: no line yet
        now[0] = 109.0
        bar(4, 40)  # 9 s: still none
        now[0] = 110.0
        bar(5, 40)  # 10 s: 5 of 40 in 10 s, 35 left at 2 s each
        now[0] = 115.0
        bar(8, 40)  # 5 s after the last line: none
        now[0] = 121.0
        bar(40, 40)  # done: the command's own output follows, no line
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("fit:")]
    assert lines == ["fit: 5/40 replays (at most), 10 s, at most 70 s left"]
