"""Every fenced Python block in README.md and docs/ runs, so no example goes stale (issue 12).

The blocks of one file run in order in one shared namespace, as a reader pasting them one
after the other would run them, in a temporary working directory. A block is skipped only
when an HTML comment ``<!-- skip: reason -->`` comes right before it (blank lines allowed);
the reason is required and checked by ``test_every_skip_has_a_reason``. Pages whose examples
collect data and fit a GP are marked ``slow`` (CI runs them; ``-m "not slow"`` skips them).
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import matplotlib.pyplot as plt
import pytest

ROOT = Path(__file__).resolve().parents[1]
PYTHON_LANGS = {"python", "py"}
_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^`]*)$")
_SKIP = re.compile(r"^\s*<!--\s*skip\b(?P<rest>.*?)-->\s*$", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class Block:
    """One fenced block: its language, first code line (1-based), code and skip reason."""

    lang: str
    line: int
    code: str
    skip: str | None  # None: run it; "": marked without a reason (an error); else the reason


@dataclasses.dataclass(frozen=True)
class Marker:
    """A skip comment and where it is; ``block`` is False when no Python block follows it."""

    line: int
    reason: str
    block: bool


def parse(text: str) -> tuple[list[Block], list[Marker]]:
    """Fenced blocks and skip markers of a Markdown text (CommonMark fences, any indent)."""
    lines = text.splitlines()
    blocks: list[Block] = []
    markers: list[Marker] = []
    pending: tuple[int, str] | None = None  # a skip marker waiting for its block
    i = 0
    while i < len(lines):
        line = lines[i]
        skip = _SKIP.match(line)
        fence = _FENCE.match(line)
        if skip:
            if pending is not None:
                markers.append(Marker(pending[0], pending[1], block=False))
            rest = skip.group("rest").strip()
            pending = (i + 1, rest[1:].strip() if rest.startswith(":") else "")
            i += 1
        elif fence:
            indent, mark = fence.group("indent"), fence.group("fence")
            info = fence.group("info").strip()
            lang = info.split()[0].lstrip("{.").rstrip("}") if info else ""
            close = re.compile(rf"^[ \t]*{re.escape(mark[0])}{{{len(mark)},}}[ \t]*$")
            body: list[str] = []
            j = i + 1
            while j < len(lines) and not close.match(lines[j]):
                body.append(lines[j][len(indent) :] if lines[j].startswith(indent) else lines[j])
                j += 1
            is_python = lang.lower() in PYTHON_LANGS
            reason = None
            if pending is not None:
                markers.append(Marker(pending[0], pending[1], block=is_python))
                reason = pending[1] if is_python else None
                pending = None
            blocks.append(Block(lang.lower(), i + 2, "\n".join(body) + "\n", reason))
            i = j + 1
        else:
            if pending is not None and line.strip():
                markers.append(Marker(pending[0], pending[1], block=False))
                pending = None
            i += 1
    if pending is not None:
        markers.append(Marker(pending[0], pending[1], block=False))
    return blocks, markers


def markdown_files() -> list[Path]:
    """README.md and every Markdown page under docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def python_blocks(path: Path) -> list[Block]:
    """The Python blocks of one file, in order."""
    return [b for b in parse(path.read_text(encoding="utf-8"))[0] if b.lang in PYTHON_LANGS]


def run_blocks(blocks: list[Block], filename: str) -> dict:
    """Run the blocks in order in one namespace; tracebacks name the Markdown file and line."""
    namespace: dict = {"__name__": "__docs__"}
    for block in blocks:
        if block.skip is not None:
            continue
        # Pad so that line numbers in a traceback are those of the Markdown file.
        source = "\n" * (block.line - 1) + block.code
        exec(compile(source, filename, "exec"), namespace)  # noqa: S102 - that is the test
    return namespace


FILES_WITH_CODE = [p for p in markdown_files() if python_blocks(p)]


def _param(path: Path):
    # Pages that collect data and fit a GP take 5-20 s each (mostly JAX compilation): slow.
    slow = any("collect_data(" in b.code for b in python_blocks(path) if b.skip is None)
    return pytest.param(
        path, marks=[pytest.mark.slow] if slow else [], id=str(path.relative_to(ROOT))
    )


@pytest.mark.parametrize("path", [_param(p) for p in FILES_WITH_CODE])
def test_python_blocks_run(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # examples that write files write them here
    try:
        run_blocks(python_blocks(path), str(path.relative_to(ROOT)))
    finally:
        plt.close("all")


def test_every_skip_has_a_reason() -> None:
    problems = []
    for path in markdown_files():
        name = path.relative_to(ROOT)
        for m in parse(path.read_text(encoding="utf-8"))[1]:
            if not m.reason:
                problems.append(f"{name}:{m.line}: skip marker without a reason")
            if not m.block:
                problems.append(f"{name}:{m.line}: skip marker not followed by a Python block")
    assert not problems, "\n".join(problems)


def test_docs_have_python_examples() -> None:
    # Guards the file discovery: README.md and the getting-started page have examples.
    names = {str(p.relative_to(ROOT)) for p in FILES_WITH_CODE}
    assert {"README.md", "docs/getting-started.md"} <= names


# -- the extractor itself, on hand-written Markdown -----------------------------------------

SAMPLE = """\
# Title

```python
x = 1
```

Text.

<!-- skip: needs a GPU -->

```python
raise RuntimeError("not run")
```

````markdown
```python
inside = "a code block shown inside another: not Python"
```
````

- item

    ```py
    y = x + 1
    ```

```bash
echo hi
```

<!-- skip -->
```python
z = 0
```

<!-- skip: nothing follows -->
Some text.
"""


def test_parse_finds_blocks_markers_and_lines() -> None:
    blocks, markers = parse(SAMPLE)
    assert [(b.lang, b.line, b.skip) for b in blocks] == [
        ("python", 4, None),
        ("python", 12, "needs a GPU"),
        ("markdown", 16, None),
        ("py", 24, None),
        ("bash", 28, None),
        ("python", 33, ""),
    ]
    assert blocks[3].code == "y = x + 1\n"  # indentation of the fence removed
    assert markers == [
        Marker(9, "needs a GPU", block=True),
        Marker(31, "", block=True),
        Marker(36, "nothing follows", block=False),
    ]


def test_run_blocks_shares_namespace_and_reports_markdown_lines() -> None:
    blocks, _ = parse(SAMPLE)
    python = [b for b in blocks if b.lang in PYTHON_LANGS]
    ns = run_blocks([b for b in python if b.skip is None], "SAMPLE.md")
    assert ns["y"] == 2  # the second block saw the first one's x
    failing = Block("python", 7, "a = 1\nundefined_name\n", None)
    with pytest.raises(NameError, match="undefined_name") as info:
        run_blocks([failing], "SAMPLE.md")
    frame = info.traceback[-1]
    assert (Path(str(frame.path)).name, frame.lineno + 1) == ("SAMPLE.md", 8)
