"""Results pages of the benchmarks (``hbma-ctrl bench <sub> --report DIR``): ``DIR/<sub>.md`` and its
figures, and ``DIR/index.md`` listing the pages there.

A page is generated, never typed: what the bench measures and against what truth (from its own
docstring), the command that reproduces it (the exact argv), the machine it ran on (CPU, cores,
Python, casadi and osqp versions, load average when it started), the results tables and, for a
speed/accuracy bench, its Pareto figure (PNG and SVG beside the page). :func:`open_report` is called
before the run (it checks ``DIR`` and notes the machine), :meth:`Report.write` after it with the
:class:`Page` a bench's builder in :mod:`hbma_ctrl.app.bench.pages` makes from its result.
"""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
import shlex
import tempfile
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

__all__ = ["Table", "Pareto", "Page", "Report", "open_report", "machine", "docstring_paragraph", "write_index",
           "fmt", "ratio"]
#: figure resolution, dots per inch (the pages' figures stay small)
DPI = 130
#: the page order of DIR/index.md
ORDER = ("sim", "protocol", "ekf", "loop", "mpc", "robot", "fit", "soak", "drills", "poses", "api", "live", "log", "codegen")
_DATE = re.compile(r"^Measured on (\d{4}-\d{2}-\d{2})", re.M)
#: the first line of the index a bench writes
_INDEX = re.compile(r"\A# Benchmark results\n")


@dataclass
class Table:
    """A results table: cell texts under ``columns`` (units in the headers), with a caption."""

    caption: str
    columns: list[str]
    rows: list[list[str]]


@dataclass
class Pareto:
    """A cost/accuracy figure: ``panels`` of (ylabel, points) sharing the cost axis ``xlabel``, a point
    (label, (colour group, marker group), cost, error[, on_front]) as :func:`hbma_ctrl.app.bench.plots.pareto_figure`
    takes them; saved as ``<stem>.png`` and ``<stem>.svg``."""

    stem: str
    caption: str
    xlabel: str
    panels: list[tuple[str, list[tuple]]]
    markers: dict | None = None


@dataclass
class Page:
    """A bench's results: a title, what it measures (one paragraph), tables, figures and notes."""

    title: str
    about: str
    tables: list[Table]
    figures: list[Pareto] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def fmt(x, spec: str = ".3g", none: str = "-") -> str:
    """A number as ``spec`` (None, NaN and non-numbers as ``none``; a bool as yes/no; an int as is)."""
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    if not isinstance(x, float) or x != x:
        return none
    return format(x, spec)


def ratio(x, ref) -> str:
    """``x / ref`` as '2.5x' or '660x' ('-' when either is missing or ref is 0)."""
    try:
        r = x / ref
    except (TypeError, ZeroDivisionError):
        return "-"
    return f"{r:.2g}x" if r < 100 else f"{r:.0f}x"


def docstring_paragraph(doc: str | None, index: int | slice = 0, cut: str = "") -> str:
    """Paragraph(s) ``index`` of a docstring as one line of Markdown: reST roles and literals become code;
    with ``cut``, only the text before it (e.g. " Returns ", where a function's docstring turns to its result)."""
    paras = [p for p in re.split(r"\n\s*\n", doc or "") if p.strip()]
    chosen = paras[index] if isinstance(index, slice) else paras[index:index + 1]
    text = " ".join(" ".join(p.split()) for p in chosen)
    text = re.sub(r":\w+:`~?([^`]+)`", lambda m: f"`{m.group(1).split('.')[-1] if '~' in m.group(0) else m.group(1)}`",
                  text)
    text = text.replace("``", "`")
    return text.partition(cut)[0] if cut else text


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine() -> dict:
    """What the numbers depend on: CPU model, cores, OS, Python, casadi and osqp versions, load average now."""
    try:
        load = "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())
    except OSError:
        load = "unknown"
    return {"CPU": _cpu_model(), "cores": str(os.cpu_count() or "unknown"),
            "OS": f"{platform.system()} {platform.release()}", "Python": platform.python_version(),
            "casadi": _version("casadi"), "osqp": _version("osqp"), "hbma-ctrl": _version("hbma-ctrl"),
            "load average at start (1, 5, 15 min)": load}


def _busy() -> bool:
    """More runnable processes (the 1-min load average) than cores."""
    try:
        return os.getloadavg()[0] > (os.cpu_count() or 1)
    except OSError:
        return False


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _table_md(t: Table) -> list[str]:
    out = [f"**{t.caption}**", "", "| " + " | ".join(_cell(c) for c in t.columns) + " |",
           "|" + "|".join("---" for _ in t.columns) + "|"]
    out += ["| " + " | ".join(_cell(c) for c in r) + " |" for r in t.rows]
    return out + [""]


def _check_writable(folder: Path) -> Path:
    """``folder`` made and written to once; ValueError naming ``--report`` when that fails."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--report {folder}: not a directory")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".report-check-"):
            pass
    except OSError as exc:
        raise ValueError(f"--report {folder}: cannot write there ({exc.strerror or exc})") from None
    return folder


def _write(path: Path, text: str) -> None:
    # written beside and renamed: a page being read (or another bench's index) never sees half a file
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


class Report:
    """A results page in the making: the folder (checked), the command line and the machine at the start."""

    def __init__(self, folder: Path | str, sub: str, argv: list[str]):
        self.folder = _check_writable(Path(folder))
        for name, own in ((f"{sub}.md", _DATE), ("index.md", _INDEX)):
            # rewritten whole: only a page (or index) a bench wrote, never a user's file of that name
            path = self.folder / name
            if path.exists() and not (path.is_file() and own.search(path.read_text(errors="replace")[:4096])):
                raise ValueError(f"--report {folder}: holds {name}, which no bench wrote; it would be replaced: "
                                 "choose another folder")
        self.sub = sub
        self.argv = list(argv)
        self.machine = machine()
        self.busy = _busy()
        self.date = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d")

    def write(self, page: Page) -> Path:
        """``<folder>/<sub>.md`` with its figures, and ``index.md`` updated; the page's path."""
        from hbma_ctrl.app.bench.plots import pareto_figure, save_figure

        lines = [f"# {page.title}", "",
                 f"Measured on {self.date} (UTC) by `hbma-ctrl bench {self.sub}`; this page is written by the "
                 "bench itself.", "", "## What is measured", "", page.about, "", "## Command", "",
                 "<!-- docs: not run: it repeats the measurement and rewrites this page -->", "```bash",
                 "hbma-ctrl " + shlex.join(self.argv), "```", "", "## Machine", "", "| | |", "|---|---|"]
        lines += [f"| {k} | {_cell(v)} |" for k, v in self.machine.items()]
        lines += ["", "Wall times depend on the machine and on what else it runs: compare rows of one page."]
        if self.busy:
            lines += ["", f"The machine was busy when this ran (more runnable processes than its {os.cpu_count()} "
                          "cores): its wall times are longer than on a machine of its own."]
        lines += ["", "## Results", ""]
        for t in page.tables:
            lines += _table_md(t)
        lines += [f"- {n}" for n in page.notes] + ([""] if page.notes else [])
        for fig in page.figures:
            f = pareto_figure(fig.panels, fig.xlabel, fig.caption, fig.markers)
            png, svg = save_figure(f, self.folder / f"{fig.stem}.png", dpi=DPI, svg=True)
            lines += [f"![{fig.caption}]({png.name})", "",
                      f"{fig.caption}. Ringed points are non-dominated (no other point is both cheaper and more "
                      f"accurate). Files: [{png.name}]({png.name}), [{svg.name}]({svg.name}).", ""]
        path = self.folder / f"{self.sub}.md"
        _write(path, "\n".join(lines).rstrip() + "\n")
        write_index(self.folder)
        return path


def open_report(folder: Path | str | None, sub: str, argv: list[str]) -> Report | None:
    """A :class:`Report` for ``bench <sub>`` into ``folder`` (None: no page), checked before any work."""
    return None if folder is None else Report(folder, sub, argv)


def write_index(folder: Path | str) -> Path:
    """``folder/index.md``: the results pages present there, each with its title and date of measurement."""
    folder = Path(folder)
    pages = sorted((p for p in folder.glob("*.md") if p.name != "index.md"),
                   key=lambda p: (ORDER.index(p.stem) if p.stem in ORDER else len(ORDER), p.stem))
    lines = ["# Benchmark results", "",
             "Each page here is written by a bench, `hbma-ctrl bench <name> --report docs/results`: what it "
             "measures, the command that reproduces it, the machine, the results and, for the speed/accuracy "
             "benches, a Pareto figure.", "", "| page | measured on |", "|---|---|"]
    for p in pages:
        text = p.read_text()
        title = text.splitlines()[0].lstrip("# ").strip() if text else p.stem
        m = _DATE.search(text)
        lines.append(f"| [{_cell(title)}]({p.name}) | {m.group(1) if m else '-'} |")
    path = folder / "index.md"
    _write(path, "\n".join(lines) + "\n")
    return path
