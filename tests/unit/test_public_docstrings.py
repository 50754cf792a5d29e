"""Meta-tests (as python-control's docstrings_test): public API documented, settings fields explained."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil

import pytest

PACKAGES = ("hbma_ctrl",)


def _modules() -> list[str]:
    out = []
    for pkg in PACKAGES:
        p = importlib.import_module(pkg)
        out += [m.name for m in pkgutil.walk_packages(p.__path__, prefix=f"{pkg}.")]
    return out


def _public(mod) -> list[str]:
    names = getattr(mod, "__all__", None)
    if names is not None:
        return list(names)
    return [n for n, o in vars(mod).items()
            if not n.startswith("_") and (inspect.isfunction(o) or inspect.isclass(o))
            and getattr(o, "__module__", None) == mod.__name__]


@pytest.mark.parametrize("modname", _modules())
def test_public_functions_and_classes_have_docstrings(modname):
    mod = importlib.import_module(modname)
    assert inspect.getdoc(mod), f"{modname} has no module docstring"
    missing = [n for n in _public(mod)
               if (inspect.isfunction(getattr(mod, n, None)) or inspect.isclass(getattr(mod, n, None)))
               and not inspect.getdoc(getattr(mod, n))]
    assert not missing, f"{modname}: undocumented public names {missing}"


@pytest.mark.parametrize("modname", _modules())
def test_settings_dataclass_fields_are_documented(modname):
    """Every field of a *Settings / *Section dataclass has a doc in its declaration
    (:func:`hbma_ctrl.core.settings.setting`) or is named in its (or a base's) docstring."""
    mod = importlib.import_module(modname)
    for n in _public(mod):
        cls = getattr(mod, n, None)
        if not (inspect.isclass(cls) and dataclasses.is_dataclass(cls) and n.endswith(("Settings", "Section"))):
            continue
        doc = " ".join(inspect.getdoc(c) or "" for c in cls.__mro__ if dataclasses.is_dataclass(c))
        undocumented = [f.name for f in dataclasses.fields(cls)
                        if not getattr(f.metadata.get("setting"), "doc", "") and f.name not in doc]
        assert not undocumented, f"{modname}.{n}: fields without a word in the docstring: {undocumented}"
