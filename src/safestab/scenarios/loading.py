"""Load any scenario, ACC, obstacle or swarm, by preset name or file, dispatching on ``kind``.

The kinds are :mod:`safestab.scenarios.kinds`'s: each study kind names its presets and its
loader.
"""

from __future__ import annotations

from pathlib import Path

from . import kinds
from ._schema import parse_override
from .kinds import load

__all__ = ["KINDS", "load", "parse_override", "scenario_kind"]

#: The scenario kinds: a file's optional top-level ``kind`` key (``"acc"`` when absent).
KINDS = ("acc", "obstacle", "swarm")


def scenario_kind(name_or_path: str | Path) -> str:
    """The kind of a preset (by name) or a scenario file (its ``kind`` key, default ``"acc"``).

    Raises
    ------
    ScenarioError
        If the file cannot be read or parsed, or ``kind`` is not one of :data:`KINDS`.
    """
    return kinds.kind_of(name_or_path).kind
