"""The documentation runs as written: every code block of docs/**/*.md and README.md, every relative
link and anchor, and the site's strict build.

Code blocks, by their language:

- ``python``: run in one namespace per page;
- ``bash`` (also ``sh``, ``shell``): each block run with ``bash -eo pipefail``;
- ``toml``: must parse, and a block holding a ``[scenario]`` table is a whole scenario file that
  must validate;
- anything else (``text`` for output, ``c``, ``json``, ...) is shown, not run; ``console`` and ``py``
  are refused (write ``bash`` or ``python`` to run, ``text`` to show).

A page's python and bash blocks run in page order in one scratch folder (one process a page), as a
reader following the page would. A python or bash block that truly cannot run here (hardware, a process that runs until stopped) is
preceded by the line ``<!-- docs: not run: <reason> -->``; the reason is required and the blocks not
run are counted in a warning. Each block gets HBMA_DOCS_BLOCK_TIMEOUT seconds (default 300: a guard against a hang, not a
speed check: a loaded machine may take several times as long as an idle one); a
failure names the page and the block's line.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tomllib
import unicodedata
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

from checkout import ROOT

BLOCK_TIMEOUT = float(os.environ.get("HBMA_DOCS_BLOCK_TIMEOUT", "300"))
RUN = {"python": "python", "bash": "bash", "sh": "bash", "shell": "bash", "toml": "toml"}
REFUSED = {"console": "bash (a command) or text (output)", "py": "python", "python3": "python",
           "pycon": "python (a script) or text (a session)"}
NOT_RUN = re.compile(r"^\s*<!--\s*docs:\s*not run\s*(?::\s*(?P<reason>.*?))?\s*-->\s*$")
FENCE = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*\{?\.?(?P<lang>[\w+-]*)")


def _pages() -> list[Path]:
    """Every Markdown page of the site and the README, found when the tests are collected."""
    return sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]


def _rel(page: Path) -> str:
    return str(page.relative_to(ROOT))


@dataclass(frozen=True)
class Block:
    page: str
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    not_run: str | None  # the marker's reason ("" when the marker has none), None without a marker

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """The fenced code blocks of ``page`` in order; a fence not closed runs to the end of the page."""
    lines = page.read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, start = len(m["indent"]), m["fence"], i
        close = re.compile(rf"^\s*{re.escape(fence[0])}{{{len(fence)},}}\s*$")
        j = i + 1
        while j < len(lines) and not close.match(lines[j]):
            j += 1
        body = "\n".join(ln[indent:] if not ln[:indent].strip() else ln.lstrip() for ln in lines[i + 1:j])
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        marker = NOT_RUN.match(prev)
        out.append(Block(_rel(page), start + 1, m["lang"].lower(), body + "\n",
                         None if marker is None else (marker["reason"] or "")))
        i = j + 1
    return out


#: pages whose blocks take a minute or more (a recording, a fit, a study, a C build): their blocks run
#: with the sweeps (`pytest -m sweep`), not in every CI run, which the other pages' blocks keep short
LONG_PAGES = {"docs/tutorials/calibrate.md", "docs/tutorials/embed.md", "docs/how-to/tune-storage.md",
              "docs/tutorials/rig.md", "docs/how-to/interrupted-runs.md",
              "docs/how-to/fit-bonded.md"}


def _params(*langs: str) -> list:
    """One pytest param per page with a block of one of ``langs`` (pages found at collection); a page of
    :data:`LONG_PAGES` is marked ``sweep`` when the blocks are to run."""
    run = {"python", "bash"} & set(langs)
    return [pytest.param(p, id=_rel(p), marks=[pytest.mark.sweep] if run and _rel(p) in LONG_PAGES else [])
            for p in _pages() if any(RUN.get(b.lang) in langs for b in blocks(p))]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.setdefault("MPLBACKEND", "Agg")
    env.setdefault("NO_MKDOCS_2_WARNING", "1")  # Material's banner would fill the output shown on a failure
    env.pop("HBMA_CTRL_TRACEBACK", None)
    return env


def _run(cmd: list[str], cwd: Path, timeout: float, what: str) -> None:
    """Run ``cmd`` in its own process group; a failure or a timeout names ``what`` with the output's tail."""
    proc = subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{what}: timed out after {timeout:g} s\n--- stdout ---\n{out[-2000:]}\n--- stderr ---\n{err[-3000:]}",
                    pytrace=False)
    if proc.returncode != 0:
        head = next((ln[8:] for ln in reversed(err.splitlines()) if ln.startswith("FAILED: ")), None)
        if head:  # the blocks' driver said which block failed and showed it
            pytest.fail(f"{head}\n{err[-5000:]}", pytrace=False)
        pytest.fail(f"{what}: exit code {proc.returncode}\n--- stdout ---\n{out[-2000:]}\n--- stderr ---\n{err[-3000:]}",
                    pytrace=False)


# --------------------------------------------------------------------------------------------- the blocks' form
@pytest.mark.parametrize("page", [pytest.param(p, id=_rel(p)) for p in _pages()])
def test_blocks_have_a_known_language_and_markers_a_reason(page):
    bad = []
    for b in blocks(page):
        if b.lang in REFUSED:
            bad.append(f"{b.where}: ```{b.lang} is not run; write {REFUSED[b.lang]}")
        if b.not_run is not None and not b.not_run:
            bad.append(f"{b.where}: '<!-- docs: not run -->' needs a reason: <!-- docs: not run: <reason> -->")
        if b.not_run is not None and RUN.get(b.lang) not in ("python", "bash"):
            bad.append(f"{b.where}: a not-run marker before a ```{b.lang or '(no language)'} block, which never "
                       "runs: remove the marker")
    if bad:
        pytest.fail("\n".join(bad), pytrace=False)
    skipped = [f"{b.where} ({b.not_run})" for b in blocks(page) if b.not_run]
    if skipped:
        warnings.warn(f"{_rel(page)}: {len(skipped)} block(s) not run: {'; '.join(skipped)}", UserWarning)


@pytest.mark.parametrize("page", _params("toml"))
def test_toml_blocks_parse_and_scenarios_validate(page, capsys):
    from hbma_ctrl.app.schema.document import parse_scenario_tables

    for b in blocks(page):
        if RUN.get(b.lang) != "toml":
            continue
        error = None
        try:
            data = tomllib.loads(b.code)
            if "scenario" in data:
                parse_scenario_tables(data, ROOT / b.page)
        except tomllib.TOMLDecodeError as exc:
            error = f"not valid TOML: {exc}"
        except ValueError as exc:
            error = f"the scenario does not validate: {exc}"
        if error:
            pytest.fail(f"{b.where}: {error}", pytrace=False)
        if "scenario" in data:
            notice = capsys.readouterr().err
            assert not notice, f"{b.where}: the scenario uses an old key name: {notice}"


# --------------------------------------------------------------------------------------------- running them
DRIVER = """
import json, os, signal, subprocess, sys, traceback
blocks = json.load(open(sys.argv[1]))
ns = {"__name__": "__main__"}

def _timeout(signum, frame):
    raise TimeoutError("the block timed out")

def _failed(b, why, out="", err=""):
    print(f"--- block ---\\n{b['code']}--- stdout ---\\n{out[-2000:]}\\n--- stderr ---\\n{err[-3000:]}", file=sys.stderr)
    print(f"FAILED: the {b['lang']} block at {b['page']}:{b['line']}: {why}", file=sys.stderr)
    sys.exit(1)

signal.signal(signal.SIGALRM, _timeout)
for b in blocks:
    if b["lang"] == "bash":
        p = subprocess.Popen(["bash", "-eo", "pipefail", "-c", b["code"]], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            out, err = p.communicate(timeout=b["timeout"])
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            out, err = p.communicate()
            _failed(b, f"timed out after {b['timeout']:g} s", out, err)
        if p.returncode:
            _failed(b, f"exit code {p.returncode}", out, err)
        continue
    signal.setitimer(signal.ITIMER_REAL, b["timeout"])
    try:
        # the block's code at its own lines of the page: a traceback names the page and the line
        exec(compile("\\n" * b["line"] + b["code"], b["page"], "exec"), ns)
    except BaseException:
        signal.setitimer(signal.ITIMER_REAL, 0)
        _failed(b, "raised", err=traceback.format_exc())
    signal.setitimer(signal.ITIMER_REAL, 0)
"""


@pytest.mark.subprocess
@pytest.mark.slow
@pytest.mark.parametrize("page", _params("python", "bash"))
def test_code_blocks_run_in_page_order(page, tmp_path):
    """The page's python blocks in one namespace and its bash blocks, in page order, in one scratch folder."""
    run = [b for b in blocks(page) if RUN.get(b.lang) in ("python", "bash") and b.not_run is None]
    if not run:
        pytest.skip("every block of the page is marked not run")
    spec = tmp_path / ".blocks.json"
    spec.write_text(json.dumps([{"page": b.page, "line": b.line, "lang": RUN[b.lang], "code": b.code,
                                 "timeout": BLOCK_TIMEOUT} for b in run]))
    driver = tmp_path / ".driver.py"
    driver.write_text(DRIVER)
    _run([sys.executable, str(driver), str(spec)], tmp_path, BLOCK_TIMEOUT * len(run) + 30, _rel(page))


# --------------------------------------------------------------------------------------------- links
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?(?P<target>[^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
#: a reference definition as Python-Markdown reads one: nothing after the target but a quoted title
REF_DEF = re.compile(r"^\s{0,3}\[[^\]^][^\]]*\]:\s*<?(?P<target>\S+?)>?\s*(?:\"[^\"]*\"|'[^']*'|\([^)]*\))?\s*$")
HEADING = re.compile(r"^(#{1,6})\s+(?P<text>.*?)\s*(?:\{[^}]*#(?P<id>[\w.:-]+)[^}]*\})?\s*#*\s*$")
HTML_ID = re.compile(r"<[a-zA-Z][^>]*\sid=[\"'](?P<id>[^\"']+)[\"']")
API_BLOCK = re.compile(r"^:::\s*(?P<module>[\w.]+)", re.M)


def _prose(page: Path, blank_code: bool = True) -> list[tuple[int, str]]:
    """(line number, text) of the page outside fenced blocks, inline code spans blanked (``blank_code``)."""
    fenced = {n for b in blocks(page) for n in range(b.line, b.line + b.code.count("\n") + 2)}
    return [(n, re.sub(r"(`+).+?\1", "``", text) if blank_code else text)
            for n, text in enumerate(page.read_text().splitlines(), 1) if n not in fenced]


def _slug(text: str, github: bool) -> str:
    """The anchor of a heading: Python-Markdown's toc slug for the site, GitHub's for the README."""
    text = re.sub(r"`([^`]*)`", r"\1", text)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading: its text
    text = re.sub(r"<[^>]+>", "", text).replace("*", "")
    if github:
        return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    return re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", text).strip().lower())


def anchors(page: Path) -> set[str]:
    """Every anchor a link may name in ``page``: headings (duplicates get _1, _2 on the site, -1, -2 on
    GitHub), explicit ``{#id}`` and HTML ids."""
    github = page.parent == ROOT
    seen: dict[str, int] = {}
    out: set[str] = set()
    for _, text in _prose(page, blank_code=False):
        m = HEADING.match(text)
        if m:
            slug = m["id"] or _slug(m["text"], github)
            if slug in seen and not m["id"]:
                seen[slug] += 1
                slug = f"{slug}{'-' if github else '_'}{seen[slug]}"
            else:
                seen.setdefault(slug, 0)
            out.add(slug)
        out.update(h["id"] for h in HTML_ID.finditer(text))
    return out


def _links(page: Path) -> list[tuple[int, str]]:
    out = []
    for n, text in _prose(page):
        out += [(n, m["target"]) for m in LINK.finditer(text)]
        m = REF_DEF.match(text)
        if m:
            out.append((n, m["target"]))
    return out


@pytest.mark.parametrize("page", [pytest.param(p, id=_rel(p)) for p in _pages()])
def test_relative_links_and_anchors_resolve(page):
    docs = ROOT / "docs"
    bad = []
    for n, target in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:, ...
            continue
        path, _, anchor = target.partition("#")
        where = f"{_rel(page)}:{n}: {target}"
        dest = page if not path else (page.parent / path).resolve()
        if path.startswith("/"):
            bad.append(f"{where}: an absolute path; link relative to the page")
            continue
        if not dest.exists():
            bad.append(f"{where}: no such file")
            continue
        if docs in page.parents and docs not in dest.parents and dest != docs:
            bad.append(f"{where}: outside docs/, which the site does not carry; link into docs/ or to the repository")
            continue
        if dest.is_dir():
            dest = dest / ("index.md" if docs in dest.parents or dest == docs else "README.md")
            if not dest.exists():
                bad.append(f"{where}: a folder without {dest.name}")
                continue
        if anchor and dest.suffix == ".md":
            api = [m["module"] for m in API_BLOCK.finditer(dest.read_text())]
            if anchor not in anchors(dest) and not any(anchor == m or anchor.startswith(m + ".") for m in api):
                bad.append(f"{where}: no heading or id '{anchor}' in {_rel(dest)}")
    if bad:
        pytest.fail("\n".join(bad), pytrace=False)


# --------------------------------------------------------------------------------------------- the site
@pytest.mark.subprocess
@pytest.mark.slow
def test_site_builds_strict(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    # not --quiet: it hides the warnings, and --strict fails a build only on the warnings it sees
    _run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
         ROOT, 600, "mkdocs build --strict")
    assert (tmp_path / "site" / "reference" / "cli" / "index.html").is_file()
