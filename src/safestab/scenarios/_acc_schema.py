"""The ACC scenario file's schema: every key, its type and range, and the resource limits.

Internal: :mod:`safestab.scenarios.acc` checks TOML files and :class:`ACCScenario` objects
with it. All bounds live here, in :data:`LIMITS` and :data:`FIELDS`; docs/acc.md lists them.
Messages have one form: ``"<source>: <table.key> must be <expected>, got <received>"``.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import numbers
import re
from collections.abc import Callable, Mapping
from typing import Any

from ..errors import ScenarioError

__all__ = [
    "FIELDS", "LIMITS", "ScenarioLimits", "check_structure", "check_values", "fail", "choice",
    "integer", "real",
]  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ScenarioLimits:
    """Bounds on scenario values that keep a run's size and arithmetic sane.

    Attributes
    ----------
    max_steps : int
        Most simulation steps ``round(t_final / dt)``, and most samples per excitation
        trajectory ``round(sample_horizon * sample_rate)``. A trajectory's history takes about
        70 bytes per step (0.2 GB for the study's three runs at the limit); the GP-corrected
        run costs about 5 ms per step at ``Q = 2000`` on 2 cores (docs/acc.md), so the limit
        allows runs of an hour or more but not the absurd ones (``t_final = 1e12``).
    max_n_samples : int
        Most GP samples ``Q`` (and ``hyper_subset``). The exact GP keeps a ``Q x Q`` Cholesky
        factor per state component (3 for ACC, 0.8 GB each at ``Q = 10,000``): collecting
        10,000 samples and fitting the GP peaked at 8.3 GB resident memory (about 5 minutes
        on 2 cores). Before this limit ``n_samples = 10**12`` aborted the interpreter.
    min_gp_rows : int
        Fewest GP samples (and ``hyper_subset``): the GP fits ``n + 2 = 5`` hyperparameters
        per component and needs more rows than that; 10 leaves a small margin.
    max_seed : int
        Largest seed, ``2**32 - 1``; seeds are non-negative (NumPy's generators refuse
        negative ones, and JAX keys are 32-bit words).
    max_magnitude : float
        Largest magnitude of any real value, in the file's units (kg, m, s, N). Far beyond
        any vehicle, and products of a few such values stay far from overflow.
    min_positive : float
        Smallest value of a strictly positive parameter (mass, gravity, tau, slack weight,
        time step, rates, input limit): its reciprocal stays below ``max_magnitude``.
    max_name_length : int
        Longest scenario name (the name is part of output file names).
    """

    max_steps: int = 1_000_000
    max_n_samples: int = 10_000
    min_gp_rows: int = 10
    max_seed: int = 2**32 - 1
    max_magnitude: float = 1e9
    min_positive: float = 1e-9
    max_name_length: int = 64


#: The limits in force.
LIMITS = ScenarioLimits()

_BIG, _SMALL = LIMITS.max_magnitude, LIMITS.min_positive
KERNELS = ("se", "matern52")  # the kernels of safestab.learning.GaussianProcessModel
INPUT_UNITS = ("newton", "normalized")
_NAME = re.compile(rf"[^\W][\w.-]{{0,{LIMITS.max_name_length - 1}}}")  # no '/', no leading '.'

Check = Callable[[str, Any, str], Any]


# -- messages ---------------------------------------------------------------------------


def _toml_type(value: Any) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, numbers.Integral):
        return "an integer"
    if isinstance(value, numbers.Real):
        return "a float"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, list | tuple):
        return "an array"
    if isinstance(value, datetime.date | datetime.time):
        return "a date/time"
    return f"a {type(value).__name__}"


def _show(value: Any) -> str:
    """The received value as a user wrote it in TOML, with its type where that helps."""
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        return repr(float(value))
    if isinstance(value, Mapping):
        return "a table"
    text = repr(value)
    if len(text) > 80:
        text = text[:77] + "..."
    return f"{text} ({_toml_type(value)})"


def _fail(source: str, path: str, expected: str, value: Any) -> ScenarioError:
    return ScenarioError(f"{source}: {path} must be {expected}, got {_show(value)}")


#: The message of a bad value, for the other tables' schemas (``[montecarlo]``).
fail = _fail


def _num(x: float) -> str:
    """1e9 -> '1e9', 1e-9 -> '1e-9', 0 -> '0'."""
    if x == 0:
        return "0"
    mant, exp = f"{x:.0e}".split("e")
    return f"{'-' if x < 0 else ''}1e{int(exp)}" if mant.lstrip("-") == "1" else f"{x:g}"


# -- field checks -----------------------------------------------------------------------


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def real(low: float, high: float = _BIG) -> Check:
    """A finite number in ``[low, high]`` (ints accepted), returned as float."""
    expected = f"a finite number in [{_num(low)}, {_num(high)}]"

    def check(path: str, value: Any, source: str) -> float:
        if not _is_real(value) or not math.isfinite(value) or not low <= value <= high:
            raise _fail(source, path, expected, value)
        return float(value)

    return check


def integer(low: int, high: int) -> Check:
    """An integer in ``[low, high]`` (floats refused, even integral ones)."""
    expected = f"an integer in [{low}, {high}]"

    def check(path: str, value: Any, source: str) -> int:
        if not isinstance(value, numbers.Integral) or isinstance(value, bool):
            raise _fail(source, path, expected, value)
        if not low <= int(value) <= high:
            raise _fail(source, path, expected, value)
        return int(value)

    return check


def choice(options: tuple[str, ...]) -> Check:
    """One of the given strings."""
    expected = "one of " + ", ".join(repr(o) for o in options)

    def check(path: str, value: Any, source: str) -> str:
        if not isinstance(value, str) or value not in options:
            raise _fail(source, path, expected, value)
        return value

    return check


_POS, _NONNEG, _SIGNED = real(_SMALL), real(0.0), real(-_BIG)


def _name(path: str, value: Any, source: str) -> str:
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise _fail(
            source,
            path,
            f"a string of 1 to {LIMITS.max_name_length} letters, digits, '_', '-' or '.', "
            "not starting with '.' or '-' (it is part of output file names)",
            value,
        )
    return value


def _input_limit(path: str, value: Any, source: str) -> float | None:
    if value is False or value is None:
        return None
    if not _is_real(value) or not math.isfinite(value) or not _SMALL <= value <= _BIG:
        raise _fail(
            source,
            path,
            f"a finite number in [{_num(_SMALL)}, {_num(_BIG)}] (the limit on |F| as a "
            "fraction of M g) or false (no limits)",
            value,
        )
    return float(value)


def _vector3(path: str, value: Any, source: str) -> tuple[float, ...]:
    expected = "an array of 3 finite numbers (v_f m/s, v_l m/s, D m)"
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise _fail(source, path, expected, value)
    return tuple(_SIGNED(f"{path}[{i}]", v, source) for i, v in enumerate(value))


def _profile(path: str, value: Any, source: str) -> tuple[tuple[float, float], ...]:
    if not isinstance(value, list | tuple):
        raise _fail(source, path, "an array of [end_time, acceleration] pairs", value)
    out: list[tuple[float, float]] = []
    for i, pair in enumerate(value):
        where = f"{path}[{i}]"
        if not isinstance(pair, list | tuple) or len(pair) != 2:
            raise _fail(source, where, "a pair [end_time s, acceleration m/s^2]", pair)
        end = _POS(f"{where}[0]", pair[0], source)
        if out and not end > out[-1][0]:
            raise _fail(
                source,
                f"{where}[0]",
                f"an end time after the previous one, {out[-1][0]!r} (end times must increase)",
                pair[0],
            )
        out.append((end, _SIGNED(f"{where}[1]", pair[1], source)))
    return tuple(out)


_DRAG = {"f0": _NONNEG, "f1": _NONNEG, "f2": _NONNEG}  # resistances: N, N s/m, N s^2/m^2
_ROWS = integer(LIMITS.min_gp_rows, LIMITS.max_n_samples)

#: Every key of a scenario file (table path) and its check. ``name`` is optional.
FIELDS: dict[str, Check] = {
    "name": _name,
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
    "controller.kappa": _NONNEG,
    "controller.rho": _NONNEG,
    "controller.phi": _NONNEG,
    "controller.varphi": _NONNEG,
    "controller.slack_weight": _POS,
    "controller.input_units": choice(INPUT_UNITS),
    "controller.input_limit": _input_limit,
    "simulation.t_final": _POS,
    "simulation.dt": _POS,
    "learning.n_samples": _ROWS,
    "learning.sample_rate": _POS,
    "learning.sample_horizon": _POS,
    "learning.noise_std": _NONNEG,
    "learning.gp_beta": _NONNEG,
    "learning.kernel": choice(KERNELS),
    "learning.x0_low": _vector3,
    "learning.x0_high": _vector3,
    "learning.excitation_limit": _NONNEG,
    "learning.hyper_subset": _ROWS,
    "learning.seed": integer(0, LIMITS.max_seed),
}
_OPTIONAL = {"name"}


# -- whole-file checks ------------------------------------------------------------------


def _tree() -> dict[str, Any]:
    """The nesting of :data:`FIELDS` as dicts; leaves are ``None``."""
    root: dict[str, Any] = {}
    for path in FIELDS:
        *tables, key = path.split(".")
        node = root
        for t in tables:
            node = node.setdefault(t, {})
        node[key] = None
    return root


def check_structure(doc: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Flatten a parsed TOML document to ``{"table.key": value}``, checking its shape.

    Raises
    ------
    ScenarioError
        For an unknown key or table (sub-tables too), a missing key, or a scalar where a
        table belongs.
    """
    flat: dict[str, Any] = {}

    def walk(node: Mapping[str, Any], spec: dict[str, Any], prefix: str) -> None:
        for key in node:
            if key not in spec:
                where = f"{prefix}{key}"
                known = ", ".join(sorted(spec))
                raise ScenarioError(
                    f"{source}: unknown key {where!r}"
                    + (f" in [{prefix[:-1]}]" if prefix else "")
                    + f"; expected one of {known}"
                )
        for key, sub in spec.items():
            path = f"{prefix}{key}"
            if key not in node:
                if path in _OPTIONAL:
                    continue
                what = "table" if isinstance(sub, dict) else "key"
                raise ScenarioError(
                    f"{source}: missing {what} {f'[{path}]' if what == 'table' else path}"
                )
            value = node[key]
            if isinstance(sub, dict):
                if not isinstance(value, Mapping):
                    raise _fail(source, path, "a table", value)
                walk(value, sub, f"{path}.")
            else:
                flat[path] = value

    walk(doc, _tree(), "")
    return flat


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
    lo, hi = v["learning.x0_low"], v["learning.x0_high"]
    for i, (a, b) in enumerate(zip(lo, hi, strict=True)):
        if a > b:
            raise ScenarioError(
                f"{source}: learning.x0_low[{i}] must be <= learning.x0_high[{i}] = {b!r}, "
                f"got {a!r}"
            )
    _count(source, "simulation.t_final / simulation.dt", "simulation steps",
           v["simulation.t_final"] / v["simulation.dt"])  # fmt: skip
    _count(source, "learning.sample_horizon * learning.sample_rate",
           "samples per excitation trajectory",
           v["learning.sample_horizon"] * v["learning.sample_rate"])  # fmt: skip
    return v


def _count(source: str, what: str, unit: str, ratio: float) -> None:
    n = round(ratio)
    if not 1 <= n <= LIMITS.max_steps:
        raise ScenarioError(
            f"{source}: {what} must give between 1 and {LIMITS.max_steps:,} {unit}, got {ratio:.6g}"
        )
