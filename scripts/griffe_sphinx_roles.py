r"""A griffe extension for the API reference: Sphinx markup in docstrings to Markdown.

The docstrings use NumPy style with a little reStructuredText, which mkdocstrings would
print literally. At build time (nothing in the source changes) this turns

- roles such as ``:func:`clf_cbf``` or ``:class:`~safestab.formulas.Region``` into links to
  the object's entry in the API reference. Names are resolved from the documented object
  outwards (its class, then its module), as Sphinx does; a link whose target is not rendered
  anywhere falls back to plain code without a warning, so a strict build never fails on one;
- reStructuredText "simple tables" (rows between ``=====  ====`` rules) into Markdown tables;
- a paragraph ending in ``::`` before an indented literal block into one ending in ``:``;
- a line that starts with ``>`` (such as a parameter described as ``>= 0``), which Markdown
  would turn into a block quote, into an escaped ``\>``;
- Sphinx's ``#:`` comments (a block of them above an assignment, or one after it on the same
  line) into the docstring of the constant, attribute or enum member they document.

Loaded by mkdocs.yml (``extensions: [scripts/griffe_sphinx_roles.py]``).
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|data|attr|mod|exc|obj|const):`(~?)([^`<>]+)`")
RULE = re.compile(r"^(\s*)(=+)((?: +=+)+)\s*$")
PACKAGE = "safestab"


def _resolve(obj: griffe.Object, target: str) -> str | None:
    """The full path of ``target`` as seen from ``obj``, or None if it is not in the package."""
    if target.startswith(PACKAGE + ".") or target == PACKAGE:
        return target
    scope: Any = obj
    while scope is not None:
        try:
            scope[target]
        except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            scope = scope.parent
            continue
        return f"{scope.path}.{target}"
    return None


def _roles(obj: griffe.Object, text: str) -> str:
    def link(match: re.Match[str]) -> str:
        short, target = match.group(1) == "~", match.group(2).strip()
        title = html.escape(target.rsplit(".", 1)[-1] if short else target)
        path = _resolve(obj, target)
        if path is None:
            return f"`{target.rsplit('.', 1)[-1] if short else target}`"
        return f'<autoref identifier="{html.escape(path)}" optional><code>{title}</code></autoref>'

    return ROLE.sub(link, text)


def _cells(line: str, starts: list[int]) -> list[str]:
    bounds = [*starts[1:], len(line)]
    return [line[a:b].strip().replace("|", r"\|") for a, b in zip(starts, bounds, strict=True)]


def _simple_tables(text: str) -> str:
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = RULE.match(lines[i])
        # a simple table: rule, header, rule, rows, rule
        if m and i + 2 < len(lines) and RULE.match(lines[i + 2]):
            end = next((j for j in range(i + 3, len(lines)) if RULE.match(lines[j])), None)
            if end is not None:
                indent = m.group(1)
                starts = [s.start() for s in re.finditer(r"=+", lines[i])]
                header = _cells(lines[i + 1], starts)
                out.append(indent + "| " + " | ".join(header) + " |")
                out.append(indent + "|" + "---|" * len(header))
                for row in lines[i + 3 : end]:
                    if row.strip():
                        out.append(indent + "| " + " | ".join(_cells(row, starts)) + " |")
                i = end + 1
                continue
        out.append(lines[i])
        i += 1
    return "\n".join(out)


def _literal_blocks(text: str) -> str:
    # "Dynamics::" + blank line + indented block: Markdown already shows the block as code.
    return re.sub(r"(\S)::\n(\s*\n)", r"\1:\n\2", text)


def _quotes(text: str) -> str:
    return re.sub(r"^(\s*)>(?!>)", r"\1\\>", text, flags=re.MULTILINE)


def convert(obj: griffe.Object, text: str) -> str:
    """The docstring ``text`` of ``obj`` with its reStructuredText markup made Markdown."""
    return _quotes(_literal_blocks(_simple_tables(_roles(obj, text))))


COMMENT = re.compile(r"^\s*#:\s?(.*)$")
TRAILING = re.compile(r"#:\s?(.*)$")


def comment_docstring(obj: griffe.Object) -> str | None:
    """The ``#:`` documentation of an attribute from its module's source lines, if any."""
    if not obj.is_attribute or obj.lineno is None:
        return None
    try:
        lines = obj.module.lines
    except (AttributeError, ValueError, KeyError):
        return None
    if not 0 < obj.lineno <= len(lines):
        return None
    trailing = TRAILING.search(lines[obj.lineno - 1].split("=", 1)[-1])
    if trailing:
        return trailing.group(1).strip()
    above: list[str] = []
    k = obj.lineno - 2
    while k >= 0 and (m := COMMENT.match(lines[k])):
        above.insert(0, m.group(1))
        k -= 1
    return "\n".join(above).strip() or None


class SphinxRoles(griffe.Extension):
    """Rewrite docstrings once the whole package is loaded (names can then be resolved)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:  # noqa: D102
        if pkg.path != PACKAGE:
            return
        seen: set[int] = set()
        stack: list[griffe.Object] = [pkg]
        while stack:
            obj = stack.pop()
            if id(obj) in seen:
                continue
            seen.add(id(obj))
            if obj.docstring is None and (text := comment_docstring(obj)):
                parent_doc = obj.parent.docstring if obj.parent is not None else None
                obj.docstring = griffe.Docstring(
                    text,
                    lineno=obj.lineno,
                    parent=obj,
                    parser=parent_doc.parser if parent_doc else None,
                    parser_options=parent_doc.parser_options if parent_doc else None,
                )
            if obj.docstring is not None:
                obj.docstring.value = convert(obj, obj.docstring.value)
            stack.extend(m for m in obj.members.values() if not m.is_alias)
