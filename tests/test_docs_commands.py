"""Every shell command in README.md and docs/ runs as written, from a fresh folder.

The Python blocks run in ``tests/test_docs_examples.py``; this runs the ``bash``, ``sh``,
``shell`` and ``console`` blocks (for ``console``, the lines after a ``$`` prompt). The
commands of one block run one after another, each as written, in one fresh temporary working
folder, as a reader typing them into a new terminal would: with this Python's ``bin`` folder
first on ``PATH`` (its ``safestab`` and ``python``), this safestab on ``PYTHONPATH``, and a
path into the repository's ``scripts/``, ``benchmarks/`` or ``examples/`` made absolute (the
reader is in a checkout). A command fails the test if it exits non-zero or runs past its
block's time budget.

HTML comments right before a block (blank lines allowed) change how it runs:

* ``<!-- slow: reason -->``: run only with ``-m slow``, with a longer budget; the reason
  says how long it takes and which documented command also runs it;
* ``<!-- needs: PROGRAM ... -->``: skipped, with the reason, where a program is not on
  ``PATH`` (the Arm toolchain of ``safestab export --target``);
* ``<!-- not-run: reason -->``: not run (a cluster address, a script that installs
  ``.venv``); the reason is required.

A fenced block without a language fails the test (a command would hide there), and so does a
marker that no shell block follows. Every other shell block runs: none is left out unmarked.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import safestab

from .test_docs_examples import ROOT, markdown_files, parse

SHELL_LANGS = {"bash", "sh", "shell", "console"}
#: Seconds a block's commands may take together: in the default run and with ``-m slow``.
BUDGET, SLOW_BUDGET = 120, 1800
_MARKER = re.compile(r"^\s*<!--\s*(?P<key>not-run|slow|needs)\b\s*:?(?P<rest>.*?)-->\s*$")
#: Paths into the repository that a command names relative to its root.
_REPO_PATH = re.compile(r"(?<![\w./-])(?=(?:scripts|benchmarks|examples)/)")


@dataclasses.dataclass(frozen=True)
class ShellBlock:
    """A shell block: where it is, its commands and its markers (key -> text)."""

    file: str
    line: int  # of the first code line, 1-based
    commands: tuple[str, ...]
    markers: dict[str, str]

    @property
    def id(self) -> str:
        return f"{self.file}:{self.line}"


def commands_of(code: str, lang: str) -> tuple[str, ...]:
    """The commands of a block: lines joined at a trailing backslash, comments dropped."""
    lines = code.splitlines()
    if lang == "console":  # the prompts' lines are the commands, the rest is output
        lines = [ln[2:] for ln in lines if ln.startswith("$ ")]
    commands, current = [], ""
    for line in lines:
        current += line
        if current.endswith("\\"):
            current = current[:-1] + " "
            continue
        if current.strip() and not current.lstrip().startswith("#"):
            commands.append(current.strip())
        current = ""
    return tuple(commands)


def markers_before(lines: list[str], fence: int) -> dict[str, str]:
    """The markers on the lines right before the fence at index ``fence`` (blanks allowed)."""
    found: dict[str, str] = {}
    i = fence - 1
    while i >= 0 and (not lines[i].strip() or _MARKER.match(lines[i])):
        m = _MARKER.match(lines[i])
        if m:
            found[m.group("key")] = m.group("rest").strip()
        i -= 1
    return found


def shell_blocks(path: Path, text: str | None = None) -> tuple[list[ShellBlock], list[str]]:
    """A Markdown file's shell blocks, and its problems (untagged blocks, stray markers)."""
    text = path.read_text(encoding="utf-8") if text is None else text
    lines = text.splitlines()
    name = str(path.relative_to(ROOT)) if path.is_absolute() else str(path)
    blocks, problems = [], []
    for block in parse(text)[0]:
        fence = block.line - 2  # index of the opening fence
        if not block.lang:
            problems.append(f"{name}:{block.line - 1}: a fenced block without a language")
        if block.lang not in SHELL_LANGS:
            continue
        markers = markers_before(lines, fence)
        blocks.append(ShellBlock(name, block.line, commands_of(block.code, block.lang), markers))
    for i, line in enumerate(lines):
        m = _MARKER.match(line)
        if not m:
            continue
        j = i + 1
        while j < len(lines) and (not lines[j].strip() or _MARKER.match(lines[j])):
            j += 1
        fence = re.match(r"^\s*(`{3,}|~{3,})\s*(\w*)", lines[j]) if j < len(lines) else None
        if fence is None or fence.group(2).lower() not in SHELL_LANGS:
            problems.append(
                f"{name}:{i + 1}: a {m.group('key')} marker not followed by a shell block"
            )
        elif m.group("key") != "needs" and not m.group("rest").strip():
            problems.append(f"{name}:{i + 1}: a {m.group('key')} marker without a reason")
    return blocks, problems


def all_blocks() -> list[ShellBlock]:
    return [b for path in markdown_files() for b in shell_blocks(path)[0]]


def prepared(command: str) -> str:
    """``command`` with the repository's script paths made absolute."""
    return _REPO_PATH.sub(f"{ROOT}/", command)


def command_environment() -> dict[str, str]:
    """This environment, with this Python's scripts and this safestab first on the paths."""
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    source = str(Path(safestab.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in [source, env.get("PYTHONPATH")] if p)
    env.setdefault("MPLBACKEND", "Agg")
    return env


def run_block(block: ShellBlock, cwd: Path, budget: float) -> None:
    """Run the block's commands in ``cwd`` within ``budget`` seconds; fail naming the line."""
    env = command_environment()
    for command in block.commands:
        try:
            proc = subprocess.run(
                ["bash", "-c", prepared(command)], cwd=cwd, env=env, capture_output=True,
                text=True, timeout=budget,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            pytest.fail(f"{block.id}: `{command}` ran past the block's budget of {budget:g} s")
        if proc.returncode != 0:
            tail = (proc.stderr.strip() or proc.stdout.strip())[-3000:]
            pytest.fail(
                f"{block.id}: `{command}` exited with {proc.returncode} "
                f"(run in a fresh folder, {cwd}):\n{tail}"
            )


def _param(block: ShellBlock):
    marks = []
    if "slow" in block.markers:
        marks.append(pytest.mark.slow)
    return pytest.param(block, marks=marks, id=block.id)


RUN = [b for b in all_blocks() if "not-run" not in b.markers]


@pytest.mark.parametrize("block", [_param(b) for b in RUN])
def test_shell_commands_run_as_written(block: ShellBlock, tmp_path: Path) -> None:
    missing = [p for p in block.markers.get("needs", "").split() if shutil.which(p) is None]
    if missing:
        pytest.skip(f"needs {', '.join(missing)} on PATH")
    run_block(block, tmp_path, SLOW_BUDGET if "slow" in block.markers else BUDGET)


def test_every_block_is_tagged_and_every_marker_has_its_block_and_reason() -> None:
    problems = [p for path in markdown_files() for p in shell_blocks(path)[1]]
    assert not problems, "\n".join(problems)


def test_the_blocks_are_found() -> None:
    # guards the discovery: the docs' commands are there, and the commands of the issue run
    blocks = all_blocks()
    commands = [c for b in RUN for c in b.commands]
    assert len(blocks) >= 10 and all(b.commands for b in blocks)
    assert "safestab export --scenario paper --target cortex-m4" in " ".join(commands)
    assert all(b.markers["not-run"] for b in blocks if "not-run" in b.markers)


# -- the runner itself, on hand-written Markdown ---------------------------------------------

SAMPLE = """\
```bash
echo one > a.txt   # a comment
# a comment line
cat a.txt \\
  scripts/run-acc.sh
```

<!-- not-run: needs a cluster -->
```console
$ safestab mc --backend ray --address auto
output line
```

<!-- slow: a minute -->
<!-- needs: no-such-program-here -->

```sh
false
```

```
untagged
```

<!-- slow -->
Some text.
"""


def test_parse_commands_markers_and_problems() -> None:
    blocks, problems = shell_blocks(Path("SAMPLE.md"), SAMPLE)
    assert [(b.line, b.commands, b.markers) for b in blocks] == [
        (2, ("echo one > a.txt   # a comment", "cat a.txt    scripts/run-acc.sh"), {}),
        (10, ("safestab mc --backend ray --address auto",), {"not-run": "needs a cluster"}),
        (18, ("false",), {"slow": "a minute", "needs": "no-such-program-here"}),
    ]
    assert problems == [
        "SAMPLE.md:21: a fenced block without a language",
        "SAMPLE.md:25: a slow marker not followed by a shell block",
    ]
    assert prepared("bash scripts/x.sh && python benchmarks/y.py") == (
        f"bash {ROOT}/scripts/x.sh && python {ROOT}/benchmarks/y.py"
    )
    assert prepared("ls my/scripts/x") == "ls my/scripts/x"  # only the repository's own


def test_a_failing_command_fails_the_test_naming_its_line(tmp_path: Path) -> None:
    blocks, _ = shell_blocks(Path("SAMPLE.md"), SAMPLE)
    ok = ShellBlock("SAMPLE.md", 2, ("echo one > a.txt", "test -s a.txt"), {})
    run_block(ok, tmp_path, budget=30)  # runs in the given folder
    assert (tmp_path / "a.txt").read_text() == "one\n"
    with pytest.raises(pytest.fail.Exception, match=r"SAMPLE.md:18: `false` exited with 1"):
        run_block(blocks[2], tmp_path, budget=30)
    slow = ShellBlock("SAMPLE.md", 3, ("sleep 5",), {})
    with pytest.raises(pytest.fail.Exception, match=r"SAMPLE.md:3: `sleep 5` ran past .* 0.5 s"):
        run_block(slow, tmp_path, budget=0.5)
