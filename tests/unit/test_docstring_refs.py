"""Every code reference written in a docstring or comment of the package names something that exists.

Docstrings and comments point at code with Sphinx roles (``:mod:``, ``:class:``, ``:func:``,
``:meth:``, ``:data:``, ``:attr:``, ``:exc:``, ``:obj:``, ``:const:``) and with double-backtick
dotted paths that start with ``hbma_ctrl.``. A reference resolves when it names an object, looked
up much as Sphinx's Python domain does (plus the module's imports):

* ``~`` and ``!`` and a leading ``.`` are stripped, ``title <target>`` keeps the target, a trailing
  ``()`` is ignored, and for a double-backtick path a trailing call or subscript is ignored;
* relative first: the target's first name is looked up in the enclosing classes (innermost first,
  their bases included through ``getattr``), then in the module's globals (its own names and what
  it imports, including imports under ``if TYPE_CHECKING:``), then in the builtins, and the rest of
  the dotted path is followed with ``getattr``;
* absolute otherwise: the longest importable module prefix is imported and the rest followed with
  ``getattr`` (``hbma_ctrl`` and installed packages only, not a folder that happens to be on
  ``sys.path``);
* for ``:attr:`` the last name may also be an instance attribute that ``getattr`` on the class cannot
  see: a dataclass field, a class annotation, a ``__slots__`` entry, or a ``self.<name> =`` in
  ``__init__`` / ``__post_init__`` or in a method of the class they call on ``self`` (a ``reset()``).

The docstrings are those of each module and of the classes, functions, methods, properties (cached
or not), static and class methods it defines (collected with :mod:`inspect`); the comments are read
with :mod:`tokenize` and resolved in the class that encloses their line. One test per module, so a
failure names the module, where the reference is, and the reference.

The package's Python files also carry no issue numbers and no commit hashes: comments say what the
code does and why, and the version history lives in git.
"""

from __future__ import annotations

import ast
import builtins
import dataclasses
import functools
import importlib
import importlib.util
import inspect
import io
import pathlib
import pkgutil
import re
import textwrap
import tokenize
import types

import pytest

import hbma_ctrl

ROLES = ("mod", "class", "func", "meth", "data", "attr", "exc", "obj", "const")
ROLE_RE = re.compile(r":(?:py:)?(" + "|".join(ROLES) + r"):`([^`]+)`")
# ``hbma_ctrl.a.b`` (optionally followed by a call or subscript, e.g. ``hbma_ctrl.a.FLAGS[0]``)
BACKTICK_RE = re.compile(r"(?<!`)``(hbma_ctrl(?:\.[A-Za-z_]\w*)+)(?:\(.*?\)|\[.*?\])?``(?!`)")
DOTTED_RE = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*")
REPO = pathlib.Path(hbma_ctrl.__file__).resolve().parent.parent

_MISSING = object()


def _modules() -> list[str]:
    return sorted(m.name for m in pkgutil.walk_packages(hbma_ctrl.__path__, prefix="hbma_ctrl."))


# ---------------------------------------------------------------- extracting references


def extract_refs(text: str) -> list[tuple[str, str]]:
    """(role, target) for each reference in ``text``; role ``"literal"`` for a double-backtick path."""
    refs = []
    for m in ROLE_RE.finditer(text):
        target = m.group(2).strip()
        titled = re.fullmatch(r"(?s).*<(.+)>", target)
        if titled:
            target = titled.group(1).strip()
        refs.append((m.group(1), target))
    for m in BACKTICK_RE.finditer(text):
        refs.append(("literal", m.group(1)))
    return refs


def _normalise(target: str) -> str:
    target = target.lstrip("~!").lstrip(".")
    if target.endswith("()"):
        target = target[:-2]
    return target


# ---------------------------------------------------------------- resolving


def _follow(obj, names: list[str]):
    for n in names:
        obj = getattr(obj, n, _MISSING)
        if obj is _MISSING:
            return _MISSING
    return obj


def _instance_attributes(cls) -> set[str]:
    """Names an instance of ``cls`` carries that ``getattr(cls, name)`` may not show."""
    names: set[str] = set()
    if dataclasses.is_dataclass(cls):
        names |= {f.name for f in dataclasses.fields(cls)}
    for klass in getattr(cls, "__mro__", (cls,)):
        names |= set(vars(klass).get("__annotations__", {}))
        slots = vars(klass).get("__slots__", ())
        names |= {slots} if isinstance(slots, str) else set(slots)
    # self.<name> = ... in __init__ / __post_init__ and in the methods they call on self (a reset())
    todo, done = ["__init__", "__post_init__"], set()
    while todo:
        meth = todo.pop()
        done.add(meth)
        fn = inspect.getattr_static(cls, meth, None)
        fn = _unwrap(fn)
        if not inspect.isfunction(fn):
            continue
        try:
            src = inspect.getsource(fn)
        except (OSError, TypeError):
            continue
        names |= set(re.findall(r"\bself\.([A-Za-z_]\w*)\s*(?::[^=\n]*)?=(?!=)", src))
        todo += [m for m in re.findall(r"\bself\.([A-Za-z_]\w*)\(", src) if m not in done]
    return names


def _follow_attr(obj, names: list[str]):
    """Like :func:`_follow`, but the last name may be an instance attribute of a class."""
    owner = _follow(obj, names[:-1])
    if owner is _MISSING:
        return _MISSING
    found = getattr(owner, names[-1], _MISSING)
    if found is _MISSING and inspect.isclass(owner) and names[-1] in _instance_attributes(owner):
        return owner
    return found


def _importable_root(name: str) -> bool:
    """``hbma_ctrl`` or an installed/standard module, not a folder that is merely on ``sys.path``."""
    if name == "hbma_ctrl":
        return True
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return False
    if spec is None:
        return False
    origin = spec.origin or next(iter(spec.submodule_search_locations or []), None)
    if origin in (None, "built-in", "frozen"):
        return True
    return REPO not in pathlib.Path(origin).resolve().parents


def _absolute(names: list[str], role: str):
    if not _importable_root(names[0]):
        return _MISSING
    for i in range(len(names), 0, -1):
        try:
            mod = importlib.import_module(".".join(names[:i]))
        except ImportError:
            continue
        follow = _follow_attr if role == "attr" else _follow
        return follow(mod, names[i:]) if names[i:] else mod
    return _MISSING


def resolve(target: str, role: str, scopes: list) -> object:
    """The object ``target`` names, looked up from ``scopes`` (innermost first), or ``_MISSING``."""
    target = _normalise(target)
    if not DOTTED_RE.fullmatch(target):
        return _MISSING
    names = target.split(".")
    follow = _follow_attr if role == "attr" else _follow
    for scope in [*scopes, builtins]:
        if scope is None:
            continue
        if isinstance(scope, dict):  # extra globals (TYPE_CHECKING imports)
            if names[0] not in scope:
                continue
            found = follow(scope[names[0]], names[1:]) if names[1:] else scope[names[0]]
        else:
            found = follow(scope, names)
        if found is not _MISSING:
            return found
    return _absolute(names, role)


def unresolved(text: str, scopes: list) -> list[str]:
    """The references in ``text`` that do not resolve from ``scopes``, as written."""
    return [f":{role}:`{target}`" if role != "literal" else f"``{target}``"
            for role, target in extract_refs(text)
            if resolve(target, role, scopes) is _MISSING]


# ---------------------------------------------------------------- collecting docstrings and comments


def _type_checking_imports(mod) -> dict:
    """Names a module imports under ``if TYPE_CHECKING:`` (absent from its globals at run time)."""
    try:
        tree = ast.parse(inspect.getsource(mod))
    except (OSError, TypeError):
        return {}
    out = {}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)):
            continue
        for stmt in node.body:
            if isinstance(stmt, ast.ImportFrom):
                base = importlib.util.resolve_name("." * stmt.level + (stmt.module or ""), mod.__package__) \
                    if stmt.level else stmt.module
                for alias in stmt.names:
                    obj = _absolute([*base.split("."), alias.name], "obj")
                    if obj is not _MISSING:
                        out[alias.asname or alias.name] = obj
            elif isinstance(stmt, ast.Import):
                for alias in stmt.names:
                    obj = _absolute(alias.name.split("."), "mod")
                    if obj is not _MISSING:
                        out[alias.asname or alias.name.split(".")[0]] = obj
    return out


def _unwrap(member):
    if isinstance(member, (staticmethod, classmethod)):
        return member.__func__
    return member


def _documented(mod) -> list[tuple[str, str, list]]:
    """(where, docstring, enclosing classes innermost first) for the module and what it defines."""
    out = [(mod.__name__, mod.__doc__ or "", [])]
    seen = set()

    def visit_class(cls, qual, outer):
        if id(cls) in seen:
            return
        seen.add(id(cls))
        classes = [cls, *outer]
        out.append((qual, cls.__doc__ or "", classes))
        for name, member in vars(cls).items():
            member = _unwrap(member)
            if isinstance(member, property):
                for fn in (member.fget, member.fset, member.fdel):
                    if fn is not None and fn.__doc__:
                        out.append((f"{qual}.{name}", fn.__doc__, classes))
            elif isinstance(member, functools.cached_property):
                if member.func.__doc__:
                    out.append((f"{qual}.{name}", member.func.__doc__, classes))
            elif inspect.isclass(member) and member.__module__ == mod.__name__:
                visit_class(member, f"{qual}.{name}", classes)
            elif callable(member) and getattr(member, "__module__", None) == mod.__name__ \
                    and getattr(member, "__doc__", None):
                out.append((f"{qual}.{name}", member.__doc__, classes))

    for name, obj in vars(mod).items():
        if getattr(obj, "__module__", None) != mod.__name__:
            continue
        if inspect.isclass(obj):
            visit_class(obj, f"{mod.__name__}.{name}", [])
        elif callable(obj) and getattr(obj, "__doc__", None):
            out.append((f"{mod.__name__}.{name}", obj.__doc__, []))
    return out


def _comments(mod) -> list[tuple[str, str, list]]:
    """(where, comment, enclosing classes innermost first) for each ``#`` comment of a module."""
    try:
        src = inspect.getsource(mod)
    except (OSError, TypeError):
        return []
    spans = []  # (first line, last line, class qualname)

    def walk(node, qual):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                q = [*qual, child.name]
                spans.append((child.lineno, child.end_lineno, q))
                walk(child, q)
            else:
                walk(child, qual)

    walk(ast.parse(src), [])
    out = []
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type != tokenize.COMMENT:
            continue
        line = tok.start[0]
        enclosing = [q for a, b, q in spans if a <= line <= b]
        classes = []
        for qual in sorted(enclosing, key=len, reverse=True):
            cls = _follow(mod, qual)
            if cls is not _MISSING:
                classes.append(cls)
        out.append((f"{mod.__name__} line {line}", tok.string, classes))
    return out


@pytest.mark.parametrize("modname", _modules())
def test_references_resolve(modname):
    mod = importlib.import_module(modname)
    extra = _type_checking_imports(mod)
    bad = []
    for where, text, classes in _documented(mod) + _comments(mod):
        for ref in unresolved(text, [*classes, mod, extra]):
            bad.append(f"{where}: {ref}")
    assert not bad, f"{modname}: references that name nothing:\n  " + "\n  ".join(bad)


# ---------------------------------------------------------------- the resolver itself


class _Fake:
    """A class with a :meth:`go`, an :attr:`size` set in ``__init__`` and a :meth:`missing`."""

    def __init__(self):
        self.size = 1

    def go(self):
        """Calls :meth:`go`, reads :attr:`size`, not :attr:`colour`."""


def test_resolver_finds_what_exists_and_flags_what_does_not():
    fake = types.ModuleType("fake")
    fake.np = importlib.import_module("json")
    doc = textwrap.dedent("""
        Uses :func:`hbma_ctrl.core.physics.does_not_exist` and :mod:`~hbma_ctrl.core.physics`,
        :func:`np.dumps`, :func:`.np.loads()`, :class:`dict`, ``hbma_ctrl.core.units`` and
        ``hbma_ctrl.core.nothing_here``, :class:`Gone` and :class:`the physics <hbma_ctrl.core.physics>`.
    """)
    assert unresolved(doc, [fake]) == [":func:`hbma_ctrl.core.physics.does_not_exist`", ":class:`Gone`",
                                       "``hbma_ctrl.core.nothing_here``"]
    # relative to the enclosing class; instance attributes count for :attr: only
    assert unresolved(_Fake.__doc__, [_Fake, fake]) == [":meth:`missing`"]
    assert unresolved(_Fake.go.__doc__, [_Fake, fake]) == [":attr:`colour`"]
    assert unresolved(":meth:`size`", [_Fake, fake]) == [":meth:`size`"]
    # a folder on sys.path that is not an installed package does not count as absolute
    assert unresolved(":mod:`controllers`", [fake]) == [":mod:`controllers`"]


# ---------------------------------------------------------------- no history in the code

ISSUE_RE = re.compile(r"(?i)\bissues?[\s_-]*#?[0-9]+")
# 7 to 40 hex digits with at least one letter and one digit, not part of a word, a number, a 0x literal or
# a #colour
HASH_RE = re.compile(r"(?<![#\w.])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def _package_files() -> list[pathlib.Path]:
    files = []
    for root in hbma_ctrl.__path__:
        files += pathlib.Path(root).rglob("*.py")
    for sub in ("controllers", "estimators"):  # linked into the package; rglob does not follow links
        files += (pathlib.Path(hbma_ctrl.__path__[0]) / sub).resolve().rglob("*.py")
    return sorted(set(f.resolve() for f in files))


def test_package_files_name_no_issues_and_no_commits():
    bad = []
    for path in _package_files():
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for rx in (ISSUE_RE, HASH_RE):
                for m in rx.finditer(line):
                    bad.append(f"{path.relative_to(REPO)}:{n}: {m.group(0)!r}")
    assert not bad, "history belongs in git, not in the code:\n  " + "\n  ".join(bad)
