"""Assemble the C source, the header and the cffi declarations of one exported function."""

from __future__ import annotations

import re
import textwrap
from collections.abc import Sequence

import numpy as np

from ._cgen import Emitter
from ._ir import Stmt, Val


def _short_where(where: str) -> str:
    """``safestab/formulas.py:160 (fn)`` from ``/abs/.../safestab/formulas.py:160:9 (fn)``."""
    loc, _, fn = where.partition(" ")
    parts = loc.rsplit(":", 2)
    file, line = (parts[0], parts[1]) if len(parts) == 3 else (loc, "")
    if "/safestab/" in file:
        file = "safestab/" + file.rsplit("/safestab/", 1)[1]
    else:
        file = file.rsplit("/", 1)[-1]
    fn = fn.strip("()").replace(".<locals>", "")
    return f"{file}:{line} {fn}".strip() if line else f"{file} {fn}".strip()


_SHORT = {"float64": "f64", "float32": "f32", "int32": "i32", "int64": "i64", "uint8": "u8"}


def _shape_text(v: Val) -> str:
    return f"{_SHORT.get(v.dtype.name, v.dtype.name)}[{','.join(str(s) for s in v.shape)}]"


def _plain(doc: str) -> str:
    """Docstring text without reST markup."""
    doc = re.sub(r":\w+:`~?(?:[\w.]*\.)?(\w+)`", r"\1", doc)
    return doc.replace("``", "")


def _comment(text: str) -> str:
    return "/* " + text.replace("*/", "* /") + " */"


def _block_comment(text: str, width: int = 92) -> list[str]:
    lines = ["/*"]
    for para in text.split("\n"):
        wrapped = textwrap.wrap(para, width - 3) or [""]
        lines += [(" * " + w).rstrip() for w in wrapped]
    return lines + " */".split("\n")


_SIZEOF = {"double": 8, "float": 4, "int": 4, "long long": 8, "unsigned char": 1}


def stack_bytes(e: Emitter, stmts: Sequence[Stmt], work: int = 0) -> int:
    """Bytes of the run-time values the statements declare, nested blocks and scratch included.

    An upper bound on the temporaries: the shared work arrays (``work`` bytes) plus every
    other value of every block counted as if all were live at once (the compiler overlaps
    them).
    """
    total = work
    for st in stmts:
        outs_rt = [v for v in st.outs if v.const is None and v.base is None and id(v) not in e.work]
        total += sum(v.size * _SIZEOF.get(e.ctype(v.dtype), 8) for v in outs_rt + list(st.scratch))
        total += sum(stack_bytes(e, block) for block in st.blocks)
    return total


#: Work array names per C type (one array per type keeps every access well typed).
WORK_NAMES = {"double": "ss_work", "float": "ss_work", "int": "ss_iwork",
              "long long": "ss_lwork", "unsigned char": "ss_bwork"}  # fmt: skip


_LOOPS = ("while", "scan")


def plan_work(e: Emitter, stmts: Sequence[Stmt], outs: Sequence[Val]) -> dict[str, int]:
    """Place the arrays in one work array per C type by their lifetimes; their lengths.

    Statements are numbered depth first (a loop's or a branch's body right after the loop
    statement). A value lives from the statement that defines it to the last statement that
    reads or writes it, where a use inside a loop's body of a value defined outside the loop
    counts to the end of the loop: the body runs again, so the value stays live for all of
    it (a branch runs once: its uses are ordinary ones). A block's results, which the
    enclosing statement reads after the block, live to its end. The function's outputs live
    to the end. Values whose lifetimes are disjoint share storage (first fit, in order of
    definition); a statement's outputs never share with its inputs. This bounds the stack by
    the largest set of arrays live at once instead of their sum.
    """
    defs: list[tuple[int, Val]] = []
    def_at: dict[int, int] = {}
    last: dict[int, int] = {}
    counter = 0

    def visit(block: Sequence[Stmt], enclosing: tuple[tuple[int, list[int]], ...]) -> None:
        nonlocal counter
        for st in block:
            idx = counter
            counter += 1
            for v in st.outs:
                if v.const is None and v.base is None and v.param is None and v.size > 1:
                    if e.ctype(v.dtype) in WORK_NAMES and id(v) not in def_at:
                        defs.append((idx, v))
                        def_at[id(v)] = idx
            pending.append((idx, enclosing, [id(v.root()) for v in list(st.ins) + list(st.outs)]))
            if st.blocks:
                end_cell = [idx]
                # a loop's body runs again: what it reads from outside stays live to its end;
                # a branch runs once, so its uses are ordinary ones
                inner = (*enclosing, (idx, end_cell)) if st.prim in _LOOPS else enclosing
                for sub in st.blocks:
                    visit(sub, inner)
                end_cell[0] = counter - 1
                # the statement's own code reads the blocks' results after them
                pending.append((counter - 1, enclosing, [id(v.root()) for v in st.results]))

    pending: list[tuple[int, tuple[tuple[int, list[int]], ...], list[int]]] = []
    visit(stmts, ())
    for idx, enclosing, keys in pending:
        for key in keys:
            use = idx
            start = def_at.get(key)
            for block_start, end_cell in enclosing:
                if start is None or start <= block_start:  # defined outside this block
                    use = max(use, end_cell[0])
                    break  # the outermost such block already covers the inner ones
            last[key] = max(last.get(key, use), use)
    end = counter
    for v in outs:
        last[id(v.root())] = end
    live: dict[str, list[tuple[int, int, int]]] = {}  # per type: (last use, offset, size)
    sizes: dict[str, int] = {}
    e.work = {}
    for i, v in sorted(defs, key=lambda item: item[0]):
        key, ct = id(v), e.ctype(v.dtype)
        pool = [item for item in live.get(ct, []) if item[0] >= i]
        off = 0
        for _, o, n in sorted(pool, key=lambda item: item[1]):
            if off + v.size <= o:
                break
            off = max(off, o + n)
        e.work[key] = (WORK_NAMES[ct], off)
        pool.append((last.get(key, i), off, v.size))
        live[ct] = pool
        sizes[ct] = max(sizes.get(ct, 0), off + v.size)
    return sizes


def render(e: Emitter, stmts: Sequence[Stmt]) -> list[str]:
    """C lines of statements, each after a comment naming its outputs, primitive and origin."""
    lines: list[str] = []
    for st in stmts:
        outs_rt = [v for v in st.outs if v.const is None and v.base is None]
        names = ", ".join(f"{e.name(v)} {_shape_text(v)}" for v in outs_rt)
        lines.append(_comment(f"{names} = {st.prim}   {_short_where(st.where)}"))
        lines += st.gen(e)
    return lines


def assemble(
    *,
    name: str,
    precision: str,
    n_states: int,
    leaves: Sequence,
    outs: Sequence[Val],
    primary: int,
    stmts: Sequence[Stmt],
    emitter: Emitter,
    description: str,
    version: str,
    share_work: bool = False,
) -> tuple[str, str, str, int]:
    """Return ``(source, header, cdef, stack_bytes)``.

    ``share_work``: place the top-level arrays in one work array by their lifetimes
    (:func:`plan_work`; the embedded layout, where the stack is small).
    """
    e = emitter
    real = e.real
    upper = name.upper()
    n = n_states

    # -- body of the step -------------------------------------------------------------
    work = plan_work(e, stmts, outs) if share_work else {}
    body = render(e, stmts)
    decls = [
        f"{ct} {WORK_NAMES[ct]}[{n}];  /* arrays never live at once share its elements */"
        for ct, n in sorted(work.items())
    ]
    body = decls + body
    stack = stack_bytes(e, stmts, work=sum(n * _SIZEOF.get(ct, 8) for ct, n in work.items()))

    # -- outputs ---------------------------------------------------------------------
    writes: list[str] = []
    checks: list[str] = []
    params: list[str] = []
    for leaf, val in zip(leaves, outs, strict=True):
        if leaf.size == 0:
            continue
        ct = e.io_ctype(leaf.dtype)
        cast = "(unsigned char)" if leaf.dtype == np.bool_ else ""
        if leaf.shape == ():
            params.append(f"{ct} *{leaf.name}")
            writes.append(f"*{leaf.name} = {cast}{e.ref(val, 0)};")
            if e.is_float(leaf.dtype):
                checks.append(
                    f"if (!isfinite(*{leaf.name})) status |= {upper}_STATUS_NONFINITE_OUTPUT;"
                )
        else:
            params.append(f"{ct} {leaf.name}[{leaf.size}]")
            if leaf.size == 1:
                writes.append(f"{leaf.name}[0] = {cast}{e.ref(val, 0)};")
            else:
                writes.append(
                    f"for (int i = 0; i < {leaf.size}; ++i) "
                    f"{leaf.name}[i] = {cast}{e.ref(val, 'i')};"
                )
            if e.is_float(leaf.dtype):
                checks.append(
                    f"for (int i = 0; i < {leaf.size}; ++i) if (!isfinite({leaf.name}[i])) "
                    f"status |= {upper}_STATUS_NONFINITE_OUTPUT;"
                )

    prim = leaves[primary]
    info_leaves = [lf for i, lf in enumerate(leaves) if i != primary and lf.size > 0]
    xdecl = f"const {real} x[{upper}_N_STATES]"

    def prim_param(dims: bool) -> str:
        ct = e.io_ctype(prim.dtype)
        if prim.shape == ():
            return f"{ct} *{prim.name}"
        return f"{ct} {prim.name}[{upper}_N_OUT]" if dims else f"{ct} *{prim.name}"

    # -- source -----------------------------------------------------------------------
    body_lines = ["    " + ln for ln in body]
    tables = e.tables()  # after the body: only tables the live code referenced
    helpers = list(e.helpers.values())
    eval_sig = f"static int {name}_eval(const {real} x[{n}], " + ", ".join(params) + ")"
    src = [
        f"/* {name}.c: generated by safestab {version} (do not edit; see {name}.h). */",
        "#include <math.h>",
        *[f"#include {inc}" for inc in sorted(e.includes)],
        f'#include "{name}.h"',
        "",
    ]
    if helpers:
        src += ["/* helpers with XLA's semantics */"] + [h + "\n" for h in helpers]
    if tables:
        src += ["/* constants: parameters, GP cache, index tables */"] + tables + [""]
    src += [
        eval_sig,
        "{",
        "    int status = 0;",
        f"    for (int i = 0; i < {n}; ++i) if (!isfinite(x[i])) "
        f"status |= {upper}_STATUS_NONFINITE_STATE;",
        *body_lines,
        "    /* outputs */",
        *["    " + w for w in writes],
        *["    " + c for c in checks],
        "    return status;",
        "}",
        "",
    ]
    call_args = []
    col_args = []
    col_params = []
    for i, leaf in enumerate(leaves):
        if leaf.size == 0:
            continue
        ct = e.io_ctype(leaf.dtype)
        col_params.append(f"{ct} *{leaf.name}")
        col_args.append(f"{leaf.name} + k * {leaf.size}" if leaf.size > 1 else f"{leaf.name} + k")
        if i == primary:
            call_args.append(prim.name)
        elif leaf.shape == ():
            call_args.append(f"&info->{leaf.name}")
        else:
            call_args.append(f"info->{leaf.name}")
    out_stride = max(prim.size, 1)
    src += [
        f"int {name}_step({xdecl}, {prim_param(True)}, {name}_info *info)",
        "{",
        f"    {name}_info scratch;",
        "    if (info == 0) info = &scratch;",
        f"    return {name}_eval(x, {', '.join(call_args)});",
        "}",
        "",
        f"int {name}_step_batch(long count, const {real} *x, "
        f"{e.io_ctype(prim.dtype)} *{prim.name}, {name}_info *info)",
        "{",
        "    int status = 0;",
        "    for (long k = 0; k < count; ++k)",
        f"        status |= {name}_step(x + k * {upper}_N_STATES, {prim.name} + k * {out_stride}, "
        "info ? info + k : 0);",
        "    return status;",
        "}",
        "",
        f"int {name}_step_columns(long count, const {real} *x, {', '.join(col_params)})",
        "{",
        "    int status = 0;",
        "    for (long k = 0; k < count; ++k)",
        f"        status |= {name}_eval(x + k * {upper}_N_STATES, {', '.join(col_args)});",
        "    return status;",
        "}",
    ]
    source = "\n".join(src) + "\n"

    # -- header -----------------------------------------------------------------------
    fields = []
    cdef_fields = []
    for leaf in info_leaves:
        ct = e.io_ctype(leaf.dtype)
        decl = f"{ct} {leaf.name}" + ("" if leaf.shape == () else f"[{leaf.size}]")
        shape = "scalar" if leaf.shape == () else f"shape {leaf.shape}"
        doc = f" {_plain(leaf.doc)}" if leaf.doc else ""
        kind = "0 or 1" if leaf.dtype == np.bool_ else leaf.dtype.name
        fields.append(f"    {decl};  /* {leaf.path}: {kind}, {shape}.{doc} */")
        cdef_fields.append(f"    {decl};")
    if not fields:
        fields = cdef_fields = ["    char unused_;  /* the function has a single output */"]
    doc = (
        f"{name}.h: one step of an exported function, generated by safestab {version}.\n"
        "Do not edit: regenerate with safestab.export_c or `safestab export`.\n\n"
        f"{description}\n\n"
        f"int {name}_step(const {real} x[{n}], {e.io_ctype(prim.dtype)} "
        f"{prim.name}{'' if prim.shape == () else f'[{prim.size}]'}, {name}_info *info);\n"
        f"  x: the state, shape ({n},). {prim.name}: output '{prim.path}' "
        f"({_plain(prim.doc) or 'see below'}), "
        f"{'a scalar' if prim.shape == () else f'shape {prim.shape}'}. info: every other output "
        "(fields below), or NULL.\n"
        f"  Returns {upper}_STATUS_OK (0), or a bitwise OR of {upper}_STATUS_NONFINITE_STATE "
        "(x contains NaN or inf; the outputs are then meaningless) and "
        f"{upper}_STATUS_NONFINITE_OUTPUT (some real output is NaN or inf).\n"
        f"{name}_step_batch: the same over count states stored one after another (x: count * "
        f"{n} values), info: an array of count structs or NULL; returns the OR of the statuses.\n"
        f"{name}_step_columns: the same with every output in its own array (count rows each), "
        f"in the order of the outputs ({', '.join(lf.name for lf in leaves if lf.size)}).\n\n"
        f"Precision: {real}. Needs only <math.h>; no heap allocation, no recursion, no global "
        f"state (re-entrant); about {stack} bytes of temporaries on the stack. Compile with "
        f"{' '.join(('cc',) + C_FLAGS_DOC)} {name}.c; never with -ffast-math (it breaks the NaN "
        "handling and the order of operations the results depend on)."
    )
    header = "\n".join(
        [
            f"#ifndef {upper}_H",
            f"#define {upper}_H",
            *_block_comment(doc),
            "",
            "#ifdef __cplusplus",
            'extern "C" {',
            "#endif",
            "",
            f"#define {upper}_N_STATES {n}",
            f"#define {upper}_N_OUT {max(prim.size, 1)}",
            f"#define {upper}_STATUS_OK 0",
            f"#define {upper}_STATUS_NONFINITE_STATE 1",
            f"#define {upper}_STATUS_NONFINITE_OUTPUT 2",
            "",
            f"typedef struct {name}_info {{",
            *fields,
            f"}} {name}_info;",
            "",
            f"int {name}_step({xdecl}, {prim_param(True)}, {name}_info *info);",
            f"int {name}_step_batch(long count, const {real} *x, {e.io_ctype(prim.dtype)} "
            f"*{prim.name}, {name}_info *info);",
            f"int {name}_step_columns(long count, const {real} *x, {', '.join(col_params)});",
            "",
            "#ifdef __cplusplus",
            "}",
            "#endif",
            "",
            f"#endif /* {upper}_H */",
            "",
        ]
    )
    cdef = "\n".join(
        [
            f"typedef struct {name}_info {{",
            *cdef_fields,
            f"}} {name}_info;",
            f"int {name}_step(const {real} *x, {prim_param(False)}, {name}_info *info);",
            f"int {name}_step_batch(long count, const {real} *x, {e.io_ctype(prim.dtype)} "
            f"*{prim.name}, {name}_info *info);",
            f"int {name}_step_columns(long count, const {real} *x, {', '.join(col_params)});",
        ]
    )
    return source, header, cdef, stack


C_FLAGS_DOC = ("-std=c99", "-O2", "-ffp-contract=off", "-c")
