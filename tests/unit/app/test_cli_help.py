"""Every command's --help keeps what its help texts say, bracketed table names included."""

from __future__ import annotations

import re

import click
import typer
from typer.testing import CliRunner

from hbma_ctrl.app.cli.main import app

BRACKETED = re.compile(r"\[[A-Za-z_.]+\]")


def _commands(group: click.Group, path: tuple = ()):
    for name, cmd in group.commands.items():
        if getattr(cmd, "hidden", False):
            continue
        yield path + (name,), cmd
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, path + (name,))


def _texts(cmd: click.Command) -> list[str]:
    return [t for t in [cmd.help or ""] + [getattr(p, "help", None) or "" for p in cmd.params] if t]


def test_every_bracketed_word_of_every_help_text_is_in_the_printed_help():
    root = typer.main.get_command(app)
    checked = 0
    for path, cmd in _commands(root):
        res = CliRunner().invoke(app, [*path, "--help"], terminal_width=200)
        assert res.exit_code == 0, (path, res.output)
        printed = " ".join(res.output.split())
        for text in _texts(cmd):
            for word in BRACKETED.findall(text):
                assert word in printed, (path, word)
                checked += 1
    assert checked >= 4  # the daemon's commands name their [daemon] table
