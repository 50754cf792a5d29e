"""The generated reference pages (hbma_ctrl/app/docgen.py): the committed pages are what the code gives
now, and each page covers everything its source defines."""

from __future__ import annotations

import pytest
import typer

from hbma_ctrl.app import docgen
from hbma_ctrl.app.cli.main import app
from checkout import ROOT


def test_committed_reference_pages_are_current():
    old = docgen.stale(ROOT)
    assert not old, f"stale generated pages {[str(p) for p in old]}: run python -m hbma_ctrl.app.docgen"


def test_cli_page_has_every_visible_command_and_option():
    page = docgen.cli_page()
    root = typer.main.get_command(app)

    def walk(cmd, path: str) -> None:
        for name, sub in getattr(cmd, "commands", {}).items():
            if sub.hidden:
                assert f"`{path} {name}`" not in page, f"hidden command {path} {name} is on the page"
                continue
            assert f"`{path} {name}`\n" in page, f"{path} {name} is not on the page"
            for p in sub.params:
                if getattr(p, "opts", None) and p.opts[0].startswith("--") and not getattr(p, "hidden", False):
                    assert p.opts[0] in page, f"{path} {name} {p.opts[0]} is not on the page"
            walk(sub, f"{path} {name}")

    walk(root, "hbma-ctrl")


def test_http_page_has_every_route_and_its_errors():
    from hbma_ctrl.app.daemon.api import make_app
    from hbma_ctrl.app.daemon.state import DaemonState

    page = docgen.http_page()
    routes = [(m, r.path) for r in make_app(DaemonState()).routes if r.path in ("/status", "/setpoint", "/stop", "/health")
              for m in r.methods]
    assert len(routes) == 4
    for method, path in routes:
        assert f"### `{method} {path}`" in page
    setpoint = page.split("### `POST /setpoint`")[1].split("###")[0]
    assert all(f"| {code} |" in setpoint for code in (200, 401, 409, 413, 422, 429, 503))


def test_api_pages_block_every_module_of_each_package():
    pages = docgen.api_pages(ROOT)
    for pkg in docgen.API_PACKAGES:
        text = pages[docgen.REF / "python" / f"{pkg}.md"]
        mods = [p.stem for p in (ROOT / "hbma_ctrl" / pkg).glob("*.py") if not p.stem.startswith("_")]
        assert mods and all(f"::: hbma_ctrl.{pkg}.{m}\n" in text for m in mods), pkg


def test_protocol_page_refills_its_blocks_and_refuses_an_unknown_one():
    text = "intro\n<!-- generated: example -->\nanything\n<!-- end: example -->\nend\n"
    out = docgen.protocol_page(text)
    assert out.startswith("intro\n<!-- generated: example -->\n```text\nhost -> HELLO 0 2*A8C3")
    assert out.endswith("```\n<!-- end: example -->\nend\n") and "anything" not in out
    with pytest.raises(ValueError, match="no generator for block 'nope'"):
        docgen.protocol_page("<!-- generated: nope -->\nx\n<!-- end: nope -->\n")


def test_cli_page_does_not_depend_on_the_terminal_width(monkeypatch):
    monkeypatch.setenv("COLUMNS", "40")
    narrow = docgen.cli_page()
    monkeypatch.setenv("COLUMNS", "250")
    assert docgen.cli_page() == narrow
