"""OSQP's embedded code generation (osqp >= 1.0) with its memory moved into one caller-owned struct.

OSQP's ``codegen`` (embedded mode 2: the matrices' values can change, their sparsity cannot) writes the
solver's sources and a ``<prefix>workspace.c`` that defines every array and structure of one solver
as a global variable, wired to each other by address. A library whose caller owns all memory needs
them in a struct instead: :func:`own_workspace` rewrites that file into

- ``<prefix>mem_t``: a struct with one member per global (arrays keep their sizes, so
  ``sizeof(<prefix>mem_t)`` is the solver's memory, known at compile time);
- ``<prefix>mem_init(<prefix>mem_t*)``: sets every member to the global's initial value, with every
  address of a global taken inside the struct (the setup's factorisation, scaling and settings are
  the generated values, copied from constant tables);
- ``<prefix>mem_solver(<prefix>mem_t*)``: the ``OSQPSolver*`` the OSQP functions take.

No allocation and no global state: two structs are two independent solvers.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["own_workspace", "Definition", "parse_workspace"]

# one top-level definition: type, name, optional array size, optional initializer (to the closing "};"
# at the line start, or a one-line value)
_DEF = re.compile(r"^(?P<type>[A-Za-z_]\w*)\s+(?P<name>[A-Za-z_]\w*)\s*(?P<dim>\[[^\]]*\])?\s*"
                  r"(?:=\s*(?P<init>\{.*?^\}|[^;{]+))?;", re.M | re.S)


class Definition:
    """One global of the workspace file: C type, name, array size text ('' for a scalar or struct),
    initializer text (None: zero)."""

    def __init__(self, ctype: str, name: str, dim: str, init: str | None):
        self.ctype, self.name, self.dim, self.init = ctype, name, dim, init

    def __repr__(self) -> str:
        return f"Definition({self.ctype} {self.name}{self.dim})"


def parse_workspace(text: str) -> tuple[list[str], list[Definition]]:
    """(the file's #include lines, its global definitions in order)."""
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    includes = [ln for ln in text.splitlines() if ln.startswith("#include")]
    body = "\n".join(ln for ln in text.splitlines() if not ln.startswith("#"))
    defs = [Definition(m["type"], m["name"], m["dim"] or "", m["init"]) for m in _DEF.finditer(body)]
    return includes, defs


def own_workspace(folder: Path | str, prefix: str) -> tuple[Path, Path]:
    """Rewrite ``folder/<prefix>workspace.c`` and ``.h`` (from osqp's ``codegen``) as the caller-owned
    struct of the module docstring; returns the two paths. ValueError when the file has a definition
    this rewriting does not understand (a check that the result still holds every global)."""
    folder = Path(folder)
    src, hdr = folder / f"{prefix}workspace.c", folder / f"{prefix}workspace.h"
    text = src.read_text()
    includes, defs = parse_workspace(text)
    names = {d.name for d in defs}
    n_globals = len(re.findall(rf"^[A-Za-z_]\w*\s+{re.escape(prefix)}\w+", re.sub(r"/\*.*?\*/", "", text, flags=re.S),
                               re.M))
    if n_globals != len(defs):
        raise ValueError(f"{src.name}: {n_globals} globals, {len(defs)} understood")
    ident = re.compile(r"\b(" + "|".join(sorted(map(re.escape, names), key=len, reverse=True)) + r")\b")
    solver = f"{prefix}solver"
    if solver not in names:
        raise ValueError(f"{src.name}: no {solver}")
    members = "\n".join(f"  {d.ctype} {d.name}{d.dim};" for d in defs)
    tables, inits = [], []
    for d in defs:
        if d.init is None:
            continue  # zero: the struct is cleared first
        if d.dim:
            if ident.search(d.init):
                raise ValueError(f"{src.name}: array {d.name} is initialised with addresses")
            tables.append(f"static const {d.ctype} {d.name}_init{d.dim} = {d.init};")
            inits.append(f"  memcpy(m->{d.name}, {d.name}_init, sizeof {d.name}_init);")
        else:
            val = ident.sub(lambda mt: f"m->{mt.group(1)}", d.init)
            if val.lstrip().startswith("{"):
                inits.append(f"  m->{d.name} = ({d.ctype}){val};")
            else:
                inits.append(f"  m->{d.name} = {val.strip()};")
    guard = f"{prefix.upper()}WORKSPACE_H"
    hdr.write_text(f"""/* One OSQP solver's memory as a struct the caller owns (OSQP's generated workspace, every global
 * a member; written by hbma_ctrl.core.osqp_embed). */
#ifndef {guard}
#define {guard}

#include "osqp_api_types.h"
#include "algebra_impl.h"
#include "qdldl_interface.h"

#ifdef __cplusplus
extern "C" {{
#endif

typedef struct {{
{members}
}} {prefix}mem_t;

/* Set m to the generated solver (settings, data, scaling, factorisation), every address inside m. */
void {prefix}mem_init({prefix}mem_t* m);

/* The solver in m, for the OSQP functions. */
static inline OSQPSolver* {prefix}mem_solver({prefix}mem_t* m) {{ return &m->{solver}; }}

#ifdef __cplusplus
}}
#endif

#endif
""")
    src.write_text(f"""/* The initial values of one OSQP solver's memory (OSQP's generated workspace, rewritten by
 * hbma_ctrl.core.osqp_embed: constant tables copied into a caller-owned struct). */
#include <string.h>

{chr(10).join(includes)}
#include "{hdr.name}"

{chr(10).join(tables)}

void {prefix}mem_init({prefix}mem_t* m) {{
  memset(m, 0, sizeof *m);
{chr(10).join(inits)}
}}
""")
    return src, hdr
