"""The ACC scenario file's schema: every key, its type and range.

Internal: :mod:`safestab.scenarios.acc` checks TOML files and :class:`ACCScenario` objects
with it. The ACC bounds live here, in :data:`FIELDS`; the shared limits in
:data:`~safestab.scenarios._schema.LIMITS`; docs/acc.md lists them. Messages have one form:
``"<source>: <table.key> must be <expected>, got <received>"``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from ._schema import (
    LIMITS,
    Check,
    ScenarioLimits,
    check_learning_counts,
    choice,
    fail,
    integer,
    is_real,
    learning_fields,
    name_field,
    num_text,
    real,
    vector,
)
from ._schema import check_structure as _check_structure_with
from .acc_braking import BARRIERS

__all__ = [
    "FIELDS", "LIMITS", "ScenarioLimits", "check_structure", "check_values", "fail", "choice",
    "integer", "real",
]  # fmt: skip

_BIG, _SMALL = LIMITS.max_magnitude, LIMITS.min_positive
INPUT_UNITS = ("newton", "normalized")

_POS, _NONNEG, _SIGNED = real(_SMALL), real(0.0), real(-_BIG)


def _input_limit(path: str, value: Any, source: str) -> float | None:
    if value is False or value is None:
        return None
    if not is_real(value) or not math.isfinite(value) or not _SMALL <= value <= _BIG:
        raise fail(
            source,
            path,
            f"a finite number in [{num_text(_SMALL)}, {num_text(_BIG)}] (the limit on |F| as a "
            "fraction of M g) or false (no limits)",
            value,
        )
    return float(value)


def _lead_decel(path: str, value: Any, source: str) -> float | None:
    if value is None:  # absent (the dataclass's default): only the headway barrier
        return None
    return real(_SMALL, 10.0)(path, value, source)


def _profile(path: str, value: Any, source: str) -> tuple[tuple[float, float], ...]:
    if not isinstance(value, list | tuple):
        raise fail(source, path, "an array of [end_time, acceleration] pairs", value)
    out: list[tuple[float, float]] = []
    for i, pair in enumerate(value):
        where = f"{path}[{i}]"
        if not isinstance(pair, list | tuple) or len(pair) != 2:
            raise fail(source, where, "a pair [end_time s, acceleration m/s^2]", pair)
        end = _POS(f"{where}[0]", pair[0], source)
        if out and not end > out[-1][0]:
            raise fail(
                source,
                f"{where}[0]",
                f"an end time after the previous one, {out[-1][0]!r} (end times must increase)",
                pair[0],
            )
        out.append((end, _SIGNED(f"{where}[1]", pair[1], source)))
    return tuple(out)


_VECTOR3 = vector(3, "v_f m/s, v_l m/s, D m", _SIGNED)
_DRAG = {"f0": _NONNEG, "f1": _NONNEG, "f2": _NONNEG}  # resistances: N, N s/m, N s^2/m^2

#: Every key of a scenario file (table path) and its check. ``name`` is optional.
FIELDS: dict[str, Check] = {
    "name": name_field,
    "kind": choice(("acc",)),  # optional: marks an ACC file for `safestab run`
    "vehicle.mass": _POS,
    "vehicle.gravity": _POS,
    **{f"drag.true.{k}": c for k, c in _DRAG.items()},
    **{f"drag.nominal.{k}": c for k, c in _DRAG.items()},
    "initial.v_f": _NONNEG,  # speeds >= 0: the drag law f0 + f1 v + f2 v^2 is for forward motion
    "initial.v_l": _NONNEG,
    "initial.D": _NONNEG,  # a gap distance
    "lead.profile": _profile,
    "certificates.v_d": _NONNEG,
    "certificates.tau": _POS,
    "certificates.lam": _NONNEG,
    "certificates.beta": _NONNEG,
    # optional: "headway" (the paper's D - tau v_f, the default) or "braking" (the
    # braking-distance barrier valid under controller.input_limit; acc_braking.py)
    "certificates.barrier": choice(BARRIERS),
    # the lead's largest deceleration (fraction of g) the braking barrier is valid for
    "certificates.lead_decel": _lead_decel,
    "controller.kappa": _NONNEG,
    "controller.rho": _NONNEG,
    "controller.phi": _NONNEG,
    "controller.varphi": _NONNEG,
    "controller.slack_weight": _POS,
    "controller.input_units": choice(INPUT_UNITS),
    "controller.input_limit": _input_limit,
    "simulation.t_final": _POS,
    "simulation.dt": _POS,
    **learning_fields(_VECTOR3),
    # optional, default 0: the exact GP in the GP-robust controller; M > 0: FastGP with at
    # most M inducing inputs per component (its band contains the exact band)
    "learning.n_inducing": integer(0, LIMITS.max_n_samples),
}
_OPTIONAL = {
    "name", "kind", "learning.n_inducing", "certificates.barrier", "certificates.lead_decel",
}  # fmt: skip


# -- whole-file checks ------------------------------------------------------------------


def check_structure(doc: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Flatten a parsed ACC document to ``{"table.key": value}``, checking its shape.

    Raises
    ------
    ScenarioError
        For an unknown key or table (sub-tables too), a missing key, or a scalar where a
        table belongs.
    """
    return _check_structure_with(doc, FIELDS, _OPTIONAL, source)


def check_values(flat: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Check every field's type, finiteness and range, and the cross-field conditions.

    Parameters
    ----------
    flat : mapping
        ``{"table.key": value}`` for every key of :data:`FIELDS` (``name`` optional).
    source : str
        Where the values came from (a file, a preset), for the messages.

    Returns
    -------
    dict
        The values normalised: floats as float, arrays as tuples, ``input_limit = false``
        as ``None``.

    Raises
    ------
    ScenarioError
        Naming the key, what was received and what was expected.
    """
    v = {path: check(path, flat[path], source) for path, check in FIELDS.items() if path in flat}
    check_learning_counts(v, source)
    _check_barrier(v, source)
    return v


def _check_barrier(v: Mapping[str, Any], source: str) -> None:
    """The braking barrier needs the braking limit and a lead bound the profile keeps."""
    braking = v.get("certificates.barrier", "headway") == "braking"
    decel = v.get("certificates.lead_decel")
    if not braking:
        if decel is not None:
            raise fail(source, "certificates.lead_decel", "absent with certificates.barrier = "
                       "'headway' (it is used only by the braking barrier)", decel)  # fmt: skip
        return
    if v["controller.input_limit"] is None:
        raise fail(source, "controller.input_limit", "a number (the braking limit, fraction of "
                   "M g) with certificates.barrier = 'braking'", False)  # fmt: skip
    if decel is None:
        raise fail(source, "certificates.lead_decel", "a number in (0, 10] (the lead's largest "
                   "deceleration, fraction of g) with certificates.barrier = 'braking'",
                   None)  # fmt: skip
    worst = -min((acc for _, acc in v["lead.profile"]), default=0.0)
    if worst > decel * v["vehicle.gravity"]:
        raise fail(
            source,
            "certificates.lead_decel",
            f">= the lead profile's largest "
            f"deceleration, {worst!r} m/s^2 = {worst / v['vehicle.gravity']!r} g",
            decel,
        )
