"""The obstacle scenario file's schema: every key, its type, range and unit.

Internal: :mod:`safestab.scenarios.obstacle` checks TOML files and
:class:`~safestab.scenarios.obstacle.ObstacleScenario` objects with it; docs/obstacle.md
lists the keys. The machinery (messages, structure, limits) is shared with the ACC schema
(:mod:`safestab.scenarios._schema`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from ..errors import ScenarioError
from ._schema import (
    LIMITS,
    Check,
    check_learning_counts,
    choice,
    fail,
    integer,
    learning_fields,
    name_field,
    real,
    vector,
)
from ._schema import check_structure as _check_structure_with

__all__ = [
    "BETA_METHODS", "FIELDS", "KIND", "LIMIT_METHODS", "check_structure", "check_values"
]  # fmt: skip

#: The value of the required top-level ``kind`` key.
KIND = "obstacle"
#: How the GP-robust controller's beta is set: ``gp_beta`` as given ("chosen"), or calibrated
#: by split conformal prediction on fresh trajectories ("conformal", docs/obstacle.md).
BETA_METHODS = ("chosen", "conformal")
#: ``learning.input_gain``: trust the nominal input matrix, or learn its constant error.
INPUT_GAINS = ("nominal", "learned")
#: ``controller.limit_method``: the runs with input limits project the relaxed formula's input
#: onto the box (eq. (26)), or solve the safety filter with the box as constraints.
LIMIT_METHODS = ("projection", "filter")
MAX_GRID = 1000  # points per axis of the start grid and the map grid
#: Most calibration trajectories ``beta_method = "conformal"`` may collect (ceil(1/delta)).
MAX_CALIBRATION_TRAJECTORIES = 10_000

_BIG, _SMALL = LIMITS.max_magnitude, LIMITS.min_positive
_POS, _NONNEG, _SIGNED = real(_SMALL), real(0.0), real(-_BIG)
_GRID = integer(1, MAX_GRID)
_RANGE = vector(2, "low m, high m", _SIGNED)
_POINT = vector(2, "x1 m, x2 m", _SIGNED)


def _open_unit(path: str, value: Any, source: str) -> float:
    x = real(0.0, 1.0)(path, value, source)
    if not 0.0 < x < 1.0:
        raise fail(source, path, "a number in the open interval (0, 1)", value)
    return x


#: Every key of an obstacle scenario file (table path) and its check. ``name`` is optional.
FIELDS: dict[str, Check] = {
    "name": name_field,
    "kind": choice((KIND,)),
    "vehicle.gain_true": _POS,  # (m/s) of velocity per (m/s) commanded
    "vehicle.gain_nominal": _POS,
    "current.speed": _NONNEG,  # m/s along +x1 at the centre
    "current.inflow": _NONNEG,  # m/s towards the x1 axis, one width off it
    "current.x1": _SIGNED,  # m, centre on the x1 axis
    "current.width": _POS,  # m
    "obstacle.x1": _SIGNED,  # m, centre on the x1 axis
    "obstacle.radius": _POS,  # m
    "certificates.P": vector(2, "P11, P22, dimensionless", _POS),
    "certificates.lam": _NONNEG,  # 1/s
    "certificates.beta": _NONNEG,  # 1/s
    "controller.kappa": _NONNEG,
    "controller.rho": _NONNEG,
    "controller.phi": _NONNEG,  # 1/s^2
    "controller.varphi": _NONNEG,  # 1/s^2
    "controller.slack_weight": _POS,  # 1/m^2
    "controller.robust_clf_layer": _NONNEG,  # m, optional (default 0: Lemma 3's term)
    "controller.input_limit": _POS,  # m/s per component, for the runs with limits
    "controller.limit_method": choice(LIMIT_METHODS),  # optional, default "projection"
    "controller.doa_fraction": _open_unit,
    "starts.x1": _RANGE,
    "starts.n_x1": _GRID,
    "starts.x2_half_width": _NONNEG,  # m
    "starts.n_x2": _GRID,
    "map.x1": _RANGE,
    "map.n_x1": _GRID,
    "map.x2_half_width": _POS,  # m
    "map.n_x2": _GRID,
    "simulation.t_final": _POS,  # s
    "simulation.dt": _POS,  # s
    "simulation.ball_radius": _POS,  # m
    "simulation.rest_speed": _POS,  # m/s
    **learning_fields(_POINT),  # rates Hz, horizon s, noise m/s, excitation m/s
    "learning.beta_method": choice(BETA_METHODS),  # optional, default "chosen"
    "learning.delta": _open_unit,
    "learning.input_gain": choice(INPUT_GAINS),  # optional, default "nominal"
    "learning.n_inducing": integer(0, LIMITS.max_n_samples),  # 0: the exact GP
}
_OPTIONAL = {
    "name", "learning.beta_method", "learning.input_gain", "controller.robust_clf_layer",
    "controller.limit_method",
}  # fmt: skip


def check_structure(doc: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Flatten a parsed obstacle document to ``{"table.key": value}``, checking its shape.

    Raises
    ------
    ScenarioError
        For an unknown key or table, a missing key, or a scalar where a table belongs.
    """
    return _check_structure_with(doc, FIELDS, _OPTIONAL, source)


def _ordered(v: dict[str, Any], key: str, source: str) -> None:
    low, high = v[key]
    if not low < high:
        raise ScenarioError(f"{source}: {key}[0] must be < {key}[1] = {high!r}, got {low!r}")


def check_values(flat: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Check every field's type, finiteness and range, and the cross-field conditions.

    Parameters
    ----------
    flat : mapping
        ``{"table.key": value}`` for every key of :data:`FIELDS` (``name`` optional).
    source : str
        Where the values came from, for the messages.

    Returns
    -------
    dict
        The values normalised (floats as float, arrays as tuples).

    Raises
    ------
    ScenarioError
        Naming the key, what was received and what was expected.
    """
    v = {path: check(path, flat[path], source) for path, check in FIELDS.items() if path in flat}
    for key in ("starts.x1", "map.x1"):
        _ordered(v, key, source)
    xo, r = v["obstacle.x1"], v["obstacle.radius"]
    if not abs(xo) > r:
        raise ScenarioError(
            f"{source}: obstacle.radius must be < |obstacle.x1| = {abs(xo)!r} (the goal, the "
            f"origin, must lie outside the obstacle), got {r!r}"
        )
    check_learning_counts(v, source)
    if v.get("learning.beta_method") == "conformal" and math.ceil(1 / v["learning.delta"]) > (
        MAX_CALIBRATION_TRAJECTORIES
    ):
        raise ScenarioError(
            f"{source}: learning.delta must be >= {1 / MAX_CALIBRATION_TRAJECTORIES:g} with "
            f"learning.beta_method = 'conformal' (it needs ceil(1/delta) calibration "
            f"trajectories, at most {MAX_CALIBRATION_TRAJECTORIES:,}), got {v['learning.delta']!r}"
        )
    return v
