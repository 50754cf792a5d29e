"""``hbma-ctrl scenarios list | copy NAME | keys``: the shipped scenario files and the reference of
every scenario key (type, unit, range, default, doc) printed as Markdown from the table models
(:mod:`hbma_ctrl.app.schema.reference`).

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from hbma_ctrl.app.cli.args import check_choice

__all__ = ["register", "keys", "list_scenarios", "copy"]

scenario_app = typer.Typer(add_completion=False, rich_markup_mode=None, no_args_is_help=True,
                           help="Scenario files: the shipped ones, and every key.")


def keys(
    table: Annotated[Optional[str], typer.Option("--table", help="one table only, e.g. controller (default: all)")] = None,
) -> None:
    """Print every scenario key with its type, unit, allowed range, default and doc (Markdown)."""
    # the schema imports every role's settings: only when the command runs
    from hbma_ctrl.app.schema.reference import TABLES, markdown

    if table is not None:
        check_choice("--table", table, TABLES)
    typer.echo(markdown(table), nl=False)


def list_scenarios() -> None:
    """List the scenario files shipped with the package: name and what it runs."""
    from hbma_ctrl.app.shipped import describe, shipped

    files = shipped()
    width = max(map(len, files), default=0)
    for name, path in files.items():
        text = describe(path)
        typer.echo(f"{name:<{width}}  {text[:100] + '...' if len(text) > 100 else text}")


def copy(
    name: Annotated[str, typer.Argument(help="a shipped scenario's name (see 'hbma-ctrl scenarios list')")],
    to: Annotated[Path, typer.Option("--to", help="folder or file to write (default: the current folder)")] = Path("."),
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace a file already there")] = False,
) -> None:
    """Copy a shipped scenario file out, to edit it and run it with 'hbma-ctrl run FILE'."""
    from hbma_ctrl.app.shipped import copy_scenario

    typer.echo(str(copy_scenario(name, to, overwrite)))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``scenarios list|copy|keys`` to the top-level CLI (nothing under ``bench``); ``scenario``
    stays a hidden name of the same group."""
    scenario_app.command("list")(list_scenarios)
    scenario_app.command("copy")(copy)
    scenario_app.command("keys")(keys)
    app.add_typer(scenario_app, name="scenarios")
    app.add_typer(scenario_app, name="scenario", hidden=True)
