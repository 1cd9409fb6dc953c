"""performance.md is written by several benchmark runs; each owns a block between markers."""

from __future__ import annotations

from pathlib import Path


def put_block(md_path: Path, block: str, begin: str, end: str) -> None:
    """Put ``block`` (which starts with ``begin`` and ends with ``end``) into the page.

    An existing block between the markers is replaced; otherwise the block is appended. The
    page is written atomically (a temporary file, then a rename).
    """
    text = md_path.read_text() if md_path.exists() else ""
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    tmp = md_path.with_name(md_path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(md_path)
