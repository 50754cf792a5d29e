"""Checks shared by the CLI tests (imported by them; the pytest config puts this folder on sys.path)."""

from __future__ import annotations


def one_line_error(res, *needles: str) -> str:
    """Assert a CLI result is exactly one ``error: ...`` line with exit code 2, containing every needle."""
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]
