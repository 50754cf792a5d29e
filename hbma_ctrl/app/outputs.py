"""Results directories that are never lost or mixed: checked, locked, written aside, moved in whole.

Every command that writes a results directory does its work inside :func:`run_dir`::

    with run_dir(out, command="run", argv=argv, scenario_path=file, overwrite=False) as tmp:
        ...write into tmp...

Before any work ``--out`` is checked (a non-directory, a device, an unwritable parent or a run
already there without ``overwrite``: one ValueError naming ``--out``) and locked (``.<name>.lock``
beside it, created with O_EXCL, holding the pid; a lock whose pid is gone is taken over). The work
goes to a temporary directory beside ``--out`` (``.<name>.tmp-<pid>-<random>``: same filesystem, so
the final move is one rename). On success ``manifest.json`` is written last and the directory renamed
to ``--out`` (an old run under ``--overwrite`` is moved aside first and deleted once the new one is in
place). On Ctrl-C or an exception the directory becomes ``<out>.interrupted-<UTC stamp>`` or
``<out>.failed-<UTC stamp>`` with its manifest saying so: nothing that looks complete is left at
``--out``. A second ending signal skips the rest of the clean-up but still renames the work to
``<out>.interrupted-*`` (marked cut short) and releases the lock; what a process killed outright left
hidden is made visible by the next run on the same ``--out``, which says so on stderr.

``manifest.json`` keys: :data:`MANIFEST_KEYS`, and ``files``: what the run wrote (relative paths), so
that ``--overwrite`` refuses a run directory someone has since put other files into.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import hashlib
import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from importlib import metadata
from pathlib import Path
from hbma_ctrl.app.endsignals import holding_signals, open_runs, pending_signal, signal_name, signal_number
from hbma_ctrl.app.shipped import resolve

try:  # typer >= 0.24 vendors click as typer._click; older typer uses click itself
    from typer._click.globals import get_current_context
except ImportError:  # pragma: no cover
    from click import get_current_context

__all__ = [
    "MANIFEST_KEYS",
    "NAME_RULE",
    "OVERWRITE_HELP",
    "RunInterrupted",
    "ARGV_KEY",
    "check_out",
    "foreign_entries",
    "WRITTEN_LIST",
    "cli_argv",
    "redact_argv",
    "default_out",
    "is_plain_name",
    "is_run_dir",
    "manifest",
    "run_dir",
    "pid_alive",
]

#: the keys of every manifest.json (times ISO 8601 UTC; status complete | interrupted | failed)
MANIFEST_KEYS = ("command", "argv", "version", "git_commit", "scenario_path", "scenario_sha256",
                 "started_utc", "finished_utc", "status", "error")

#: help text of every writing command's --overwrite flag
OVERWRITE_HELP = "replace a run of hbma-ctrl already in --out (otherwise refused; a directory of other files never)"

#: the rule a name must follow to become a directory name (quoted by the errors)
NAME_RULE = "letters, digits, '-', '_' and '.' only, not starting with '.'"

#: the longest results-directory name, bytes: the filesystem's 255 less what the lock, temporary and
#: kept-aside siblings add to it (``.<name>.lock.stale-<pid>``, ``<name>.interrupted-<stamp>-<k>``)
MAX_NAME_BYTES = 200
#: the file in a folder of ``report``'s figures or ``export``'s tables naming what they wrote there, one
#: name a line: those files are theirs to replace (and a run directory holding that folder is still a run's)
WRITTEN_LIST = ".hbma-ctrl-written"

#: the longest results-directory path, bytes: Linux's PATH_MAX (4096) less a name's worth for the files in it
MAX_PATH_BYTES = 4096 - 256

#: where the top-level CLI group keeps the command line it was given (in the click context's meta)
ARGV_KEY = "hbma_ctrl.argv"

_PLAIN = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")
_PKG_ROOT = Path(__file__).resolve().parents[2]  # the folder holding the hbma_ctrl package


def _cut_short(run: dict, why: str) -> Path | None:
    """What a second signal does to an open run: its temporary directory renamed beside ``--out`` and
    marked interrupted, a run it replaced removed, its lock released; returns where the work went."""
    where = run.get("parked")
    tmp = run.get("tmp")
    if tmp is not None and os.path.isdir(tmp):
        where = _park(tmp, run["out"], "interrupted", run["man"], why, run)
    old = run.get("old")
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    _unlock(run["lock"])
    return where


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM, SIGHUP) inside :func:`run_dir`; ``partial`` is the ``.interrupted-*``
    directory kept, ``signum`` the signal's number."""

    def __init__(self, partial: Path, signum: int = int(signal.SIGINT)):
        super().__init__(str(partial))
        self.partial = partial
        self.signum = signum


def is_plain_name(name: str) -> bool:
    """True when ``name`` can be one directory name: see :data:`NAME_RULE`."""
    return isinstance(name, str) and _PLAIN.fullmatch(name) is not None


def default_out(name: str, root: Path | str = "runs") -> Path:
    """``root/name`` for a scenario without ``--out``; ValueError naming ``[scenario] name`` otherwise."""
    if not is_plain_name(name):
        raise ValueError(f"[scenario] name = {name!r} cannot name the output directory: use {NAME_RULE} "
                         f"(no path separators), or pass --out")
    if len(name.encode()) > MAX_NAME_BYTES:
        raise ValueError(f"[scenario] name = '{name[:40]}...' is {len(name.encode())} characters long: at most "
                         f"{MAX_NAME_BYTES} can name the output directory; shorten it or pass --out")
    return Path(root) / name


def cli_argv() -> list[str]:
    """The arguments of the running ``hbma-ctrl`` command (as the CLI got them), else sys.argv[1:]."""
    ctx = get_current_context(silent=True)
    argv = ctx.meta.get(ARGV_KEY) if ctx is not None else None
    return list(argv) if argv is not None else list(sys.argv[1:])


def _utc() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


def _stamp() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def _version() -> str | None:
    try:
        return metadata.version("hbma-ctrl")
    except metadata.PackageNotFoundError:
        return None


def _git_commit() -> str | None:
    # only when the package itself runs from a checkout (a linked checkout has a .git file, not a folder)
    if not (_PKG_ROOT / ".git").exists():
        return None
    try:
        res = subprocess.run(["git", "-C", str(_PKG_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    sha = res.stdout.strip()
    return sha if res.returncode == 0 and re.fullmatch(r"[0-9a-f]{40}", sha) else None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


#: flags whose value is a secret: a manifest keeps the flag, never its value
SECRET_FLAGS = ("--token",)
REDACTED = "<redacted>"


def redact_argv(argv: Sequence[str]) -> list[str]:
    """``argv`` with the value of every :data:`SECRET_FLAGS` flag (``--token X`` or ``--token=X``) replaced
    by :data:`REDACTED`."""
    out: list[str] = []
    for a in argv:
        flag, eq, _ = str(a).partition("=")
        if out and out[-1] in SECRET_FLAGS:
            out.append(REDACTED)
        elif eq and flag in SECRET_FLAGS:
            out.append(f"{flag}={REDACTED}")
        else:
            out.append(str(a))
    return out


def manifest(command: str, argv: Sequence[str] | None = None, scenario_path: Path | str | None = None) -> dict:
    """A fresh manifest (status "running", no end time) with every key of :data:`MANIFEST_KEYS`; the
    argv's secrets redacted (:func:`redact_argv`). A shipped scenario's name is hashed as the file it names."""
    scn = resolve(scenario_path) if scenario_path is not None else None
    return {
        "command": command,
        "argv": redact_argv(argv if argv is not None else sys.argv[1:]),
        "version": _version(),
        "git_commit": _git_commit(),
        "scenario_path": str(scenario_path) if scenario_path is not None else None,
        "scenario_sha256": _sha256(scn) if scn is not None and scn.is_file() else None,
        "started_utc": _utc(),
        "finished_utc": None,
        "status": "running",
        "error": None,
    }


def _bad(out: Path | str, why: str) -> ValueError:
    return ValueError(f"--out {out}: {why}")


def check_out(out: Path | str, overwrite: bool = False) -> Path:
    """Check ``--out`` before any work; returns it absolute. ValueError (naming --out) when unusable.

    Refused: something that is not a directory (a file, a device, a pipe), a parent that is a file
    or not writable, and a non-empty directory unless ``overwrite``. ``overwrite`` replaces only a run
    of this package (a directory whose ``manifest.json`` has :data:`MANIFEST_KEYS`), never the current
    directory, a home directory or a directory holding either: anything else there may be a user's own.
    """
    given = Path(out)
    path = Path(os.path.abspath(given.expanduser()))
    for i, part in enumerate(path.parts):
        most = MAX_NAME_BYTES if i == len(path.parts) - 1 else 255
        if len(part.encode()) > most:
            raise _bad(f"{str(given)[:60]}...", f"the name '{part[:40]}...' is {len(part.encode())} bytes long; a "
                       f"folder name may have at most {most}")
    if len(os.fsencode(path)) > MAX_PATH_BYTES:
        raise _bad(f"{str(given)[:60]}...", f"the path is {len(os.fsencode(path))} bytes long; a path may have at "
                   f"most {MAX_PATH_BYTES}")
    if path.parent == path:
        raise _bad(given, "is a filesystem root; choose a directory below it")
    if path.exists() or path.is_symlink():
        mode = os.stat(path).st_mode if path.exists() else 0
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
            raise _bad(given, "is a device, not a directory")
        if not stat.S_ISDIR(mode):
            raise _bad(given, "exists and is not a directory")
        path = path.resolve()  # a symlinked run dir: lock and replace the real one
        if any(path.iterdir()):
            if not overwrite:
                raise _bad(given, "already holds a run (a non-empty directory); pass --overwrite or choose "
                                  "another directory")
            cwd = Path.cwd().resolve()
            if path == cwd or path in cwd.parents or path == Path.home().resolve():
                raise _bad(given, "is the current directory, a home directory or holds the current directory: "
                                  "--overwrite replaces only a run's own directory; choose another --out")
            if not is_run_dir(path):
                raise _bad(given, "holds files but no run of hbma-ctrl (no manifest.json of one): --overwrite "
                                  "replaces only a run's own directory; choose another --out")
            added = foreign_entries(path)
            if added:
                raise _bad(given, f"holds {added[0]!r}{f' and {len(added) - 1} more' if len(added) > 1 else ''}, "
                                  "which its run did not write: --overwrite replaces only what a run wrote; move "
                                  "it out or choose another --out")
    anc = path.parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise _bad(given, f"{anc} is not a directory")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise _bad(given, f"{anc} is not writable")
    return path


def is_run_dir(path: Path | str) -> bool:
    """True when ``path`` holds a run of this package: a ``manifest.json`` with every key of
    :data:`MANIFEST_KEYS` (a complete, interrupted or failed run's)."""
    try:
        man = json.loads((Path(path) / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(man, dict) and set(MANIFEST_KEYS) <= set(man)


def _listing(folder: Path) -> list[str]:
    """Every file and folder under ``folder``, relative, '/'-separated, sorted (manifest.json left out)."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.name != "manifest.json")


def foreign_entries(path: Path | str) -> list[str]:
    """What a run directory holds that its run did not write: entries missing from its manifest's
    ``files`` (put there by hand afterwards). Empty for a manifest without ``files`` (older runs)."""
    path = Path(path)
    try:
        listed = json.loads((path / "manifest.json").read_text()).get("files")
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(listed, list):
        return []
    known = set(map(str, listed))
    for sub in path.iterdir():  # a folder report or export added to the run (its figures, its tables)
        written = sub / WRITTEN_LIST
        if sub.is_dir() and written.is_file():
            names = [ln for ln in written.read_text(errors="replace").splitlines() if ln]
            known |= {sub.name, f"{sub.name}/{WRITTEN_LIST}"} | {f"{sub.name}/{n}" for n in names}
    return [e for e in _listing(path) if e not in known and not e.startswith(".manifest.json")]


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this host (another user's live process counts)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def _read_pid(path: Path) -> int | None:
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def _lock(out: Path, given: Path) -> Path:
    """Create ``.<name>.lock`` beside out (O_EXCL, our pid); a lock of a dead pid is taken over."""
    lock = out.parent / f".{out.name}.lock"
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            pid = _read_pid(lock)
            for _ in range(10):  # a writer between its O_EXCL create and writing its pid: give it a moment
                if pid is not None or not lock.exists():
                    break
                time.sleep(0.05)
                pid = _read_pid(lock)
            if pid is not None and pid_alive(pid):
                raise _bad(given, f"is in use by another run (pid {pid}, lock {lock}); wait for it or choose "
                                  "another directory") from None
            # stale: move it aside atomically, so two takers cannot both remove a fresh lock
            aside = lock.with_name(f"{lock.name}.stale-{os.getpid()}")
            try:
                os.rename(lock, aside)
            except FileNotFoundError:
                continue
            if _read_pid(aside) != pid:  # another taker's fresh lock was moved: put it back, then retry
                with contextlib.suppress(OSError):
                    os.link(aside, lock)
            with contextlib.suppress(OSError):
                os.unlink(aside)
            continue
        except OSError as exc:  # a place no file can be made in (sysfs, procfs, a read-only mount)
            raise _bad(given, f"no file can be created in {out.parent} ({exc.strerror}); choose another "
                              "directory") from None
        with os.fdopen(fd, "w") as fh:
            fh.write(f"{os.getpid()}\n")
        return lock
    raise _bad(given, f"could not take the lock {lock}; try again")


def _beside(out: Path, tag: str) -> Path:
    base = out.parent / f"{out.name}.{tag}-{_stamp()}"
    path, k = base, 1
    while path.exists():
        path, k = Path(f"{base}-{k}"), k + 1
    return path


def _write_manifest(man: dict, folder: Path) -> None:
    tmp = folder / ".manifest.json.tmp"
    tmp.write_text(json.dumps(man, indent=1) + "\n")
    os.replace(tmp, folder / "manifest.json")


def _park(tmp: Path, out: Path, status: str, man: dict, error: str | None, run: dict | None = None) -> Path:
    """Mark the work ``status`` and rename it beside out; returns where it went (tmp if the rename fails).
    ``run``: the open run's record, which learns where the work went."""
    with contextlib.suppress(OSError):
        man["files"] = _listing(tmp)
    man.update(status=status, finished_utc=_utc(), error=error)
    with contextlib.suppress(OSError):
        _write_manifest(man, tmp)
    dest = _beside(out, status)
    try:
        os.rename(tmp, dest)
    except OSError:
        return tmp
    if run is not None:
        run["parked"] = dest
    return dest


def _install(tmp: Path, out: Path, run: dict) -> None:
    """Move the finished run into place: one rename; an old run is moved aside (``run["old"]``), for
    the caller to delete once the lock is about to go."""
    if out.exists():
        if any(out.iterdir()):
            old = out.parent / f".{out.name}.old-{_stamp()}-{os.getpid()}"
            os.rename(out, old)
            run["old"] = old
        else:
            out.rmdir()
    try:
        os.rename(tmp, out)
    except OSError:
        if run.get("old") is not None:
            os.rename(run.pop("old"), out)
        raise


def _unlock(lock: Path) -> None:
    with contextlib.suppress(OSError):
        if _read_pid(lock) == os.getpid():
            lock.unlink()


def _recover(out: Path, given: Path) -> None:
    """Under the lock of ``out``: make visible what a process that died inside :func:`run_dir` (a
    SIGKILL, a power cut, a third signal) left hidden beside it, one line on stderr for each.

    Its temporary directory (``.<name>.tmp-<pid>-<random>``, or without the pid as older versions
    named it) becomes ``<name>.interrupted-<stamp>``, its manifest marked interrupted; a run it had
    moved aside to replace (``.<name>.old-<stamp>-<pid>``) goes back to ``out`` when ``out`` is gone, else
    becomes ``<name>.replaced-<stamp>`` (which run replaced it is unknown, so it is kept). Only names
    of exactly these forms, whose pid is not running, are touched; nothing is deleted. The lock
    proves no live process owns them: each of these exists only while its writer holds the lock.
    """
    tmp_form = re.compile(rf"\.{re.escape(out.name)}\.tmp-(?:(\d+)-)?[a-z0-9_]{{8}}")
    old_form = re.compile(rf"\.{re.escape(out.name)}\.old-\d{{8}}T\d{{6}}Z-(\d+)")
    try:
        entries = sorted(os.scandir(out.parent), key=lambda e: e.name)
    except OSError:
        return
    for e in entries:
        t, o = tmp_form.fullmatch(e.name), old_form.fullmatch(e.name)
        if not (t or o) or not e.is_dir(follow_symlinks=False):
            continue
        pid = int((t or o).group(1)) if (t or o).group(1) else None
        if pid is not None and (pid == os.getpid() or pid_alive(pid)):
            continue
        who = f"a run of pid {pid}" if pid is not None else "a run"
        src = Path(e.path)
        try:
            if t:
                _mark_cut_short(src, f"cut short: {who} ended without its clean-up; found by a later run")
                dest = _beside(out, "interrupted")
                os.rename(src, dest)
                what = f"{who} that ended without its clean-up had left its work hidden in {e.name}; kept as {dest}"
            elif not out.exists():
                os.rename(src, out)
                what = f"{who} that ended while replacing it had left it hidden in {e.name}; put back"
            else:
                dest = _beside(out, "replaced")
                os.rename(src, dest)
                what = (f"{who} that ended while replacing it had left the run it replaced in {e.name}; "
                        f"kept as {dest}")
        except OSError as exc:
            what = (f"{e.name}, left hidden by {who} that ended without its clean-up, could not be moved: "
                    f"{exc.strerror or exc}")
        print(f"note: --out {given}: {what}", file=sys.stderr, flush=True)


def _mark_cut_short(folder: Path, why: str) -> None:
    """Mark a dead run's work interrupted: its manifest (written when the work began) updated, or a new
    one when there is none of this package's."""
    man_path = folder / "manifest.json"
    man = None
    with contextlib.suppress(OSError, ValueError):
        man = json.loads(man_path.read_text())
    if not (isinstance(man, dict) and set(MANIFEST_KEYS) <= set(man)):
        if man_path.exists() or man_path.is_symlink():
            return  # a manifest.json not of this package: left as it is
        man = dict.fromkeys(MANIFEST_KEYS)
    man.update(status="interrupted", error=why)
    with contextlib.suppress(OSError):
        _write_manifest(man, folder)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@contextlib.contextmanager
def run_dir(out: Path | str, *, command: str, argv: Sequence[str] | None = None,
            scenario_path: Path | str | None = None, overwrite: bool = False,
            carry: Sequence[str] = ()) -> Iterator[Path]:
    """Check and lock ``out``, yield a temporary directory beside it, move it to ``out`` on success.

    ``command``/``argv``/``scenario_path`` go to manifest.json. ``carry``: glob patterns of files
    copied from the run being replaced (``overwrite``) into the new one before the work, e.g. a
    self-validating cache. Ctrl-C raises :class:`RunInterrupted` (``partial`` = the
    ``.interrupted-*`` directory); another exception propagates with ``partial_results`` set.
    """
    given = Path(out)
    path = check_out(given, overwrite)
    man = manifest(command, argv, scenario_path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _bad(given, f"cannot create its parent: {exc.strerror or exc}") from None
    # the record a second signal parks (it ends the process before this function's own clean-up)
    run: dict = {"lock": _lock(path, given), "out": path, "man": man, "tmp": None, "parked": None, "old": None}
    run["cut_short"] = functools.partial(_cut_short, run)
    open_runs.append(run)
    try:
        _recover(path, given)  # first: a run it puts back at --out is then checked as any other
        path = check_out(given, overwrite)  # again under the lock: another writer may have finished meanwhile
        run["out"] = path
        try:
            # the pid in the name lets a later run tell a dead run's leftover from a live one's work
            run["tmp"] = tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-{os.getpid()}-", dir=path.parent))
        except OSError as exc:
            raise _bad(given, f"cannot write beside it: {exc.strerror or exc}") from None
        try:
            _write_manifest(man, tmp)  # status "running": what a later run marks interrupted if this one dies
            if overwrite and path.is_dir():
                for pattern in carry:
                    for f in path.glob(pattern):
                        if f.is_file():
                            shutil.copy2(f, tmp / f.name)
        except BaseException as exc:
            shutil.rmtree(tmp, ignore_errors=True)  # no work in it yet, only what was just written or copied
            run["tmp"] = None
            if isinstance(exc, OSError):
                raise _bad(given, f"cannot write beside it: {exc.strerror or exc}") from None
            raise
        try:
            yield tmp
        except KeyboardInterrupt as exc:
            signum = signal_number(exc)
            raise RunInterrupted(_park(tmp, path, "interrupted", man, signal_name(signum), run), signum) from None
        except BaseException as exc:
            signum = pending_signal()
            if signum is not None:  # the error is the signal's, turned into another by the code it hit
                raise RunInterrupted(_park(tmp, path, "interrupted", man, signal_name(signum), run),
                                     signum) from None
            dest = _park(tmp, path, "failed", man, _one_line(exc), run)
            with contextlib.suppress(AttributeError, TypeError):
                exc.partial_results = dest  # the CLI's one-line error says where the partial work is
            raise
        signum = pending_signal()
        if signum is not None:  # the signal's exception was lost on its way up: the run is still cut short
            raise RunInterrupted(_park(tmp, path, "interrupted", man, signal_name(signum), run), signum)
        with holding_signals():
            man.update(status="complete", finished_utc=_utc(), files=_listing(tmp))
            _write_manifest(man, tmp)  # last: a manifest saying complete means every file is there
            _install(tmp, path, run)
    finally:
        if run["old"] is not None:  # the run replaced, once the new one is in place
            shutil.rmtree(run["old"], ignore_errors=True)
        _unlock(run["lock"])
        open_runs.remove(run)
