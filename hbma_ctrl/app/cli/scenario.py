"""``hbma-ctrl scenario keys [--table NAME]``: the reference of every scenario key (type, unit, range,
default, doc), printed as Markdown from the table models (:mod:`hbma_ctrl.app.schema.reference`).

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`.
"""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from hbma_ctrl.app.cli.args import check_choice

__all__ = ["register", "keys"]

scenario_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Scenario files: their keys.")


def keys(
    table: Annotated[Optional[str], typer.Option("--table", help="one table only, e.g. controller (default: all)")] = None,
) -> None:
    """Print every scenario key with its type, unit, allowed range, default and doc (Markdown)."""
    # the schema imports every role's settings: only when the command runs
    from hbma_ctrl.app.schema.reference import TABLES, markdown

    if table is not None:
        check_choice("--table", table, TABLES)
    typer.echo(markdown(table), nl=False)


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``scenario keys`` to the top-level CLI (nothing under ``bench``)."""
    scenario_app.command("keys")(keys)
    app.add_typer(scenario_app, name="scenario")
