"""The figure cache: a figure that shows the same values is drawn once and copied after."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.app.figstyle import FORMATS, save, saved_once


def test_saved_once_draws_a_figure_once_for_the_same_values_and_again_when_they_change(tmp_path, monkeypatch):
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(tmp_path / "cache"))
    drawn = []

    def draw_line(y):
        def draw(stem):
            drawn.append(stem)
            fig = Figure(figsize=(2, 2))
            fig.subplots().plot(y)
            save(fig, stem)
        return draw

    for run in "abc":
        (tmp_path / run).mkdir()
    y = np.array([0.0, 1.0, 4.0])
    first = saved_once(tmp_path / "a" / "fig", draw_line(y), y)
    second = saved_once(tmp_path / "b" / "fig", draw_line(y), y)
    assert len(drawn) == 1  # the second run copied the first's files
    assert [p.suffix for p in second] == [f".{ext}" for ext in FORMATS]
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(first, second))
    changed = saved_once(tmp_path / "c" / "fig", draw_line(y + 1.0), y + 1.0)
    assert len(drawn) == 2 and changed[0].read_bytes() != first[0].read_bytes()
    assert not list((tmp_path / "cache" / "figures").glob("*.part"))  # no half-stored figure left


def test_saved_once_draws_in_place_when_the_cache_cannot_be_written(tmp_path, monkeypatch):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("HBMA_CTRL_CACHE", str(blocker))

    def draw(stem):
        fig = Figure(figsize=(2, 2))
        fig.subplots().plot([0.0, 1.0])
        save(fig, stem)

    files = saved_once(tmp_path / "fig", draw, np.zeros(2))
    assert [p.name for p in files] == [f"fig.{ext}" for ext in FORMATS] and all(p.stat().st_size > 0 for p in files)
