"""Load any scenario, ACC or obstacle, by preset name or file, dispatching on its ``kind``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..errors import ScenarioError
from . import acc, obstacle
from ._schema import parse_override, read_document

__all__ = ["KINDS", "load", "parse_override", "scenario_kind"]

#: The scenario kinds: a file's optional top-level ``kind`` key (``"acc"`` when absent).
KINDS = ("acc", "obstacle")


def scenario_kind(name_or_path: str | Path) -> str:
    """The kind of a preset (by name) or a scenario file (its ``kind`` key, default ``"acc"``).

    Raises
    ------
    ScenarioError
        If the file cannot be read or parsed, or ``kind`` is not one of :data:`KINDS`.
    """
    if str(name_or_path) in acc.PRESETS:
        return "acc"
    if str(name_or_path) in obstacle.PRESETS:
        return "obstacle"
    doc, _, source = read_document(name_or_path, acc.PRESETS + obstacle.PRESETS, __package__)
    kind = doc.get("kind", "acc")
    if not isinstance(kind, str) or kind not in KINDS:
        raise ScenarioError(
            f"{source}: kind must be one of {', '.join(repr(k) for k in KINDS)} "
            f"(or absent for 'acc'), got {kind!r}"
        )
    return kind


def load(
    name_or_path: str | Path, *, overrides: Mapping[str, Any] | None = None
) -> acc.ACCScenario | obstacle.ObstacleScenario:
    """Load a scenario of any kind: presets ``paper``, ``stress`` (ACC), ``obstacle``, or a file.

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"table.key": value}`` set before the document is checked.

    Returns
    -------
    ACCScenario or ObstacleScenario

    Raises
    ------
    ScenarioError
        As the kind's loader (:func:`~safestab.scenarios.load_scenario`,
        :func:`~safestab.scenarios.load_obstacle_scenario`), or for an unknown ``kind``.
    """
    if scenario_kind(name_or_path) == "obstacle":
        return obstacle.load_obstacle_scenario(name_or_path, overrides=overrides)
    return acc.load_scenario(name_or_path, overrides=overrides)
