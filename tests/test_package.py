"""The package namespace: public names are functions, never shadowed by modules."""

import ast
import importlib
import pathlib
import types

import safestab


def test_simulate_is_the_function_before_and_after_importing_the_module():
    assert callable(safestab.simulate) and not isinstance(safestab.simulate, types.ModuleType)
    importlib.import_module("safestab.simulation")
    assert callable(safestab.simulate) and not isinstance(safestab.simulate, types.ModuleType)
    assert safestab.simulate is importlib.import_module("safestab.simulation").simulate


def test_no_public_name_is_a_module():
    for name in safestab.__all__:
        assert not isinstance(getattr(safestab, name), types.ModuleType), name


ROOT = pathlib.Path(__file__).resolve().parents[1]
#: The public API of namedtuples, underscored so that it cannot clash with field names.
NAMEDTUPLE_API = {"_replace", "_asdict", "_fields", "_make", "_field_defaults"}


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_uses(path: pathlib.Path) -> list[str]:
    """Underscore names a file takes from another module: imported, or read off an object.

    ``from m import _x`` is always one. ``obj._x`` is one unless ``obj`` is ``self`` or
    ``cls`` (a class's own and inherited members) or ``_x`` is defined in the same file (a
    module's private helpers on its own objects). Importing public names from an internal
    ``_module`` is fine: that is where shared unchecked kernels live.
    """
    tree = ast.parse(path.read_text())
    defined = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            defined.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            defined.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            defined.add(node.attr)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            found += [f"{node.lineno}: from {node.module} import {a.name}"
                      for a in node.names if _private(a.name)]  # fmt: skip
        elif (
            isinstance(node, ast.Attribute)
            and _private(node.attr)
            and node.attr not in NAMEDTUPLE_API | defined
            and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))
        ):
            found.append(f"{node.lineno}: .{node.attr}")
    return found


def test_private_uses_finds_what_it_should():
    import tempfile

    text = "from m import _a\nimport m\nm._b()\nx._c = 1\nx._c\nself._d\nt._replace()\n"
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "probe.py"
        path.write_text(text)
        assert private_uses(path) == ["1: from m import _a", "3: ._b"]


def test_no_module_uses_another_modules_underscore_names():
    # STYLE.md: a private name is private to its module. Other modules get public accessors.
    bad = {
        str(path.relative_to(ROOT)): uses
        for folder in ("src", "benchmarks", "tests", "scripts")
        for path in sorted((ROOT / folder).rglob("*.py"))
        if (uses := private_uses(path))
    }
    assert not bad, bad


def test_no_docstring_or_comment_in_src_names_an_issue_or_a_date():
    """History lives in git and the changelog: the code says what it does and why."""
    import re
    from pathlib import Path

    pattern = re.compile(
        r"\b20\d\d-\d\d-\d\d\b|\b[Ii]ssues? \d+|\bthe issue\b|\b[Uu]ntil 20\d\d"
        r"|\b[Bb]efore (this|the) (change|fix|limit|study pipeline)\b|\bpreviously\b"
        r"|\bno longer\b|\b[Mm]easured on this\b|\bwas (removed|added|changed|renamed)\b"
    )
    root = Path(__file__).resolve().parent.parent / "src" / "safestab"
    found = [
        f"{path.relative_to(root)}:{i}: {line.strip()}"
        for path in sorted(root.rglob("*.py"))
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not found, "\n".join(found)
    # the pattern finds what it should (the test can fail)
    assert pattern.search("# measured on 2026-11-27") and pattern.search("(issue 14)")
    for history in (
        "the figure the issue asks for",
        "Before this limit it crashed",
        "until 2026 it did",
        "it no longer compiles",
        "Measured on this machine",
    ):
        assert pattern.search(history), history
    assert not pattern.search("The law's input before the limits")
