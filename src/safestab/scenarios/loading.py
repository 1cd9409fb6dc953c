"""Load any scenario, ACC, obstacle or swarm, by preset name or file, dispatching on ``kind``.

The kinds are :mod:`safestab.scenarios.kinds`'s: each study kind names its presets and its
loader.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from . import kinds
from ._schema import parse_override

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


def load(name_or_path: str | Path, *, overrides: Mapping[str, Any] | None = None) -> Any:
    """Load a scenario of any kind by preset name or file.

    The presets are ``paper``, ``stress``, ``stress-ood`` (ACC), ``obstacle`` and ``swarm``.

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"table.key": value}`` set before the document is checked.

    Returns
    -------
    ACCScenario, ObstacleScenario or SwarmScenario

    Raises
    ------
    ScenarioError
        As the kind's loader (:func:`~safestab.scenarios.load_scenario`,
        :func:`~safestab.scenarios.load_obstacle_scenario`,
        :func:`~safestab.scenarios.swarm.load_swarm_scenario`), or for an unknown ``kind``.
    """
    return kinds.load(name_or_path, overrides=overrides)
