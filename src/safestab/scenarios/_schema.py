"""Shared machinery of the scenario-file schemas: reading, field checks, structure, limits.

Internal: :mod:`safestab.scenarios._acc_schema` and :mod:`safestab.scenarios._obstacle_schema`
declare their keys with the checks here; :mod:`safestab.scenarios.acc`,
:mod:`safestab.scenarios.obstacle` and :mod:`safestab.scenarios.loading` read files with
:func:`read_document`. Messages have one form: ``"<source>: <table.key> must be <expected>,
got <received>"``.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import numbers
import re
import tomllib
from collections.abc import Callable, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from ..errors import ScenarioError
from ..learning.kernels import KERNEL_NAMES

__all__ = [
    "LIMITS",
    "ScenarioLimits",
    "Check",
    "fail",
    "is_real",
    "num_text",
    "real",
    "integer",
    "choice",
    "name_field",
    "vector",
    "check_structure",
    "check_count",
    "read_document",
    "apply_overrides",
    "parse_override",
]


@dataclasses.dataclass(frozen=True)
class ScenarioLimits:
    """Bounds on scenario values that keep a run's size and arithmetic sane.

    Attributes
    ----------
    max_steps : int
        Most simulation steps ``round(t_final / dt)``, and most samples per excitation
        trajectory ``round(sample_horizon * sample_rate)``. A trajectory's history takes about
        70 bytes per step (0.2 GB for the ACC study's three runs at the limit); the
        GP-robust ACC run costs about 5 ms per step at ``Q = 2000`` on 2 cores
        (docs/acc.md), so the limit allows runs of an hour or more but not the absurd ones
        (``t_final = 1e12``).
    max_n_samples : int
        Most GP samples ``Q`` (and ``hyper_subset``). The exact GP keeps a ``Q x Q`` Cholesky
        factor per state component (3 for ACC, 0.8 GB each at ``Q = 10,000``): collecting
        10,000 samples and fitting the GP peaked at 8.3 GB resident memory (about 5 minutes
        on 2 cores); a larger ``n_samples`` is refused here rather than left to exhaust
        memory.
    min_gp_rows : int
        Fewest GP samples (and ``hyper_subset``): the GP fits ``n + 2`` hyperparameters
        per component (5 for ACC, 4 for the obstacle scenario) and needs more rows than
        that; 10 leaves a small margin.
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

_BIG = LIMITS.max_magnitude
_NAME = re.compile(rf"[^\W][\w.-]{{0,{LIMITS.max_name_length - 1}}}")  # no '/', no leading '.'

#: A field check: ``check(table.key, value, source) -> normalised value``.
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


def fail(source: str, path: str, expected: str, value: Any) -> ScenarioError:
    """The error for key ``path``: ``"<source>: <path> must be <expected>, got <value>"``."""
    return ScenarioError(f"{source}: {path} must be {expected}, got {_show(value)}")


def num_text(x: float) -> str:
    """1e9 -> '1e9', 1e-9 -> '1e-9', 0 -> '0'."""
    if x == 0:
        return "0"
    mant, exp = f"{x:.0e}".split("e")
    return f"{'-' if x < 0 else ''}1e{int(exp)}" if mant.lstrip("-") == "1" else f"{x:g}"


# -- field checks -----------------------------------------------------------------------


def is_real(value: Any) -> bool:
    """A real number that is not a boolean (TOML integers and floats)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def real(low: float, high: float = _BIG) -> Check:
    """A finite number in ``[low, high]`` (ints accepted), returned as float."""
    expected = f"a finite number in [{num_text(low)}, {num_text(high)}]"

    def check(path: str, value: Any, source: str) -> float:
        if not is_real(value) or not math.isfinite(value) or not low <= value <= high:
            raise fail(source, path, expected, value)
        return float(value)

    return check


def integer(low: int, high: int) -> Check:
    """An integer in ``[low, high]`` (floats refused, even integral ones)."""
    expected = f"an integer in [{low}, {high}]"

    def check(path: str, value: Any, source: str) -> int:
        if not isinstance(value, numbers.Integral) or isinstance(value, bool):
            raise fail(source, path, expected, value)
        if not low <= int(value) <= high:
            raise fail(source, path, expected, value)
        return int(value)

    return check


def choice(options: tuple[str, ...]) -> Check:
    """One of the given strings."""
    expected = "one of " + ", ".join(repr(o) for o in options)

    def check(path: str, value: Any, source: str) -> str:
        if not isinstance(value, str) or value not in options:
            raise fail(source, path, expected, value)
        return value

    return check


def name_field(path: str, value: Any, source: str) -> str:
    """A scenario name: it becomes part of output file names."""
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise fail(
            source,
            path,
            f"a string of 1 to {LIMITS.max_name_length} letters, digits, '_', '-' or '.', "
            "not starting with '.' or '-' (it is part of output file names)",
            value,
        )
    return value


def vector(size: int, what: str, element: Check) -> Check:
    """An array of ``size`` numbers, each checked by ``element``; returned as a tuple.

    ``what`` names the entries and their units for the message, e.g. ``"x1 m, x2 m"``.
    """
    expected = f"an array of {size} finite numbers ({what})"

    def check(path: str, value: Any, source: str) -> tuple[float, ...]:
        if not isinstance(value, list | tuple) or len(value) != size:
            raise fail(source, path, expected, value)
        return tuple(element(f"{path}[{i}]", v, source) for i, v in enumerate(value))

    return check


# -- whole-document checks ----------------------------------------------------------------


def _tree(fields: Mapping[str, Check]) -> dict[str, Any]:
    """The nesting of ``fields`` as dicts; leaves are ``None``."""
    root: dict[str, Any] = {}
    for path in fields:
        *tables, key = path.split(".")
        node = root
        for t in tables:
            node = node.setdefault(t, {})
        node[key] = None
    return root


def check_structure(
    doc: Mapping[str, Any], fields: Mapping[str, Check], optional: set[str], source: str
) -> dict[str, Any]:
    """Flatten a parsed TOML document to ``{"table.key": value}``, checking its shape.

    Parameters
    ----------
    doc : mapping
        The parsed document.
    fields : mapping of str to Check
        Every key (``"table.key"``) the document may hold.
    optional : set of str
        The keys that may be missing.
    source : str
        Where the document came from, for the messages.

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
                if path in optional:
                    continue
                what = "table" if isinstance(sub, dict) else "key"
                raise ScenarioError(
                    f"{source}: missing {what} {f'[{path}]' if what == 'table' else path}"
                )
            value = node[key]
            if isinstance(sub, dict):
                if not isinstance(value, Mapping):
                    raise fail(source, path, "a table", value)
                walk(value, sub, f"{path}.")
            else:
                flat[path] = value

    walk(doc, _tree(fields), "")
    return flat


def check_count(source: str, what: str, unit: str, ratio: float) -> None:
    """Check that ``round(ratio)`` (a step or sample count) is in ``[1, LIMITS.max_steps]``."""
    n = round(ratio)
    if not 1 <= n <= LIMITS.max_steps:
        raise ScenarioError(
            f"{source}: {what} must give between 1 and {LIMITS.max_steps:,} {unit}, got {ratio:.6g}"
        )


# -- what the scenarios that learn omega share -------------------------------------------

#: The ``[learning]`` keys of every scenario that learns ``omega`` (ACC, obstacle), in order;
#: a scenario's dataclass stores ``learning.k`` as its field ``k``.
LEARNING_KEYS = (
    "n_samples", "sample_rate", "sample_horizon", "noise_std", "gp_beta", "kernel", "x0_low",
    "x0_high", "excitation_limit", "hyper_subset", "seed",
)  # fmt: skip


def learning_fields(point: Check) -> dict[str, Check]:
    """The checks of :data:`LEARNING_KEYS`; ``point`` checks ``x0_low`` and ``x0_high``."""
    pos, nonneg = real(LIMITS.min_positive), real(0.0)
    rows = integer(LIMITS.min_gp_rows, LIMITS.max_n_samples)
    checks = {
        "n_samples": rows, "sample_rate": pos, "sample_horizon": pos, "noise_std": nonneg,
        "gp_beta": nonneg, "kernel": choice(KERNEL_NAMES), "x0_low": point, "x0_high": point,
        "excitation_limit": nonneg, "hyper_subset": rows, "seed": integer(0, LIMITS.max_seed),
    }  # fmt: skip
    return {f"learning.{k}": checks[k] for k in LEARNING_KEYS}


def check_learning_counts(v: Mapping[str, Any], source: str) -> None:
    """The cross-field checks every learning scenario shares.

    ``learning.x0_low <= learning.x0_high`` per coordinate, and step and sample counts in
    range (:func:`check_count`).
    """
    lo, hi = v["learning.x0_low"], v["learning.x0_high"]
    for i, (a, b) in enumerate(zip(lo, hi, strict=True)):
        if a > b:
            raise ScenarioError(
                f"{source}: learning.x0_low[{i}] must be <= learning.x0_high[{i}] = {b!r}, "
                f"got {a!r}"
            )
    check_count(
        source,
        "simulation.t_final / simulation.dt",
        "simulation steps",
        v["simulation.t_final"] / v["simulation.dt"],
    )
    check_count(
        source,
        "learning.sample_horizon * learning.sample_rate",
        "samples per excitation trajectory",
        v["learning.sample_horizon"] * v["learning.sample_rate"],
    )


def load_flat(
    name_or_path: str | Path,
    presets: tuple[str, ...],
    package: str,
    check_structure_of: Callable[[Mapping[str, Any], str], dict[str, Any]],
    overrides: Mapping[str, Any] | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> tuple[dict[str, Any], dict[str, Any] | None, str]:
    """The steps every scenario loader shares, up to the value checks.

    Read the preset or file (:func:`read_document`), apply ``overrides``, set aside the
    optional ``[montecarlo]`` table, check the structure, fill optional keys from
    ``defaults``, and name the scenario after the preset or the file's stem when the file
    has no ``name``.

    Returns
    -------
    (flat, montecarlo, source)
        ``{"table.key": value}`` to check, the raw ``[montecarlo]`` table or ``None``, and
        the source label for messages.

    Raises
    ------
    ScenarioError
        As :func:`read_document`, :func:`apply_overrides` and ``check_structure_of``, or for
        a stem that is not a valid name.
    """
    doc, name, source = read_document(name_or_path, presets, package)
    source = apply_overrides(doc, overrides or {}, source)
    table = doc.pop("montecarlo", None)  # optional; checked after the required tables
    flat = check_structure_of(doc, source)
    for key, value in (defaults or {}).items():
        flat.setdefault(key, value)
    if "name" not in flat:
        try:
            flat["name"] = name_field("name", name, source)
        except ScenarioError as exc:
            raise ScenarioError(
                f'{exc} (the file has no name key, so its stem was used; add name = "...")'
            ) from None
    return flat, table, source


# -- reading files ----------------------------------------------------------------------


def read_document(
    name_or_path: str | Path, presets: tuple[str, ...], package: str
) -> tuple[dict[str, Any], str, str]:
    """Read a preset (by name) or a TOML file (by path) and parse it.

    Parameters
    ----------
    name_or_path : str or Path
        A preset name from ``presets`` or a path.
    presets : tuple of str
        The preset names; preset ``p`` is the resource ``p.toml`` of ``package``.
    package : str
        The package holding the preset files.

    Returns
    -------
    doc : dict
        The parsed TOML document.
    name : str
        The preset name or the file's stem (the default scenario name).
    source : str
        ``"preset 'p'"`` or the path, for messages.

    Raises
    ------
    ScenarioError
        If the file does not exist, cannot be read, is not UTF-8 or is not valid TOML.
    """
    if str(name_or_path) in presets:
        name = str(name_or_path)
        data = resources.files(package).joinpath(f"{name}.toml").read_bytes()
        source = f"preset {name!r}"
    else:
        path = Path(name_or_path)
        if not path.is_file():
            other = resources.files(package).joinpath(f"{name_or_path}.toml")
            if str(name_or_path).isidentifier() and other.is_file():
                raise ScenarioError(
                    f"scenario {str(name_or_path)!r} is a preset of another kind; this command "
                    f"takes the presets {presets} or a TOML file of its kind"
                )
            raise ScenarioError(
                f"scenario {str(name_or_path)!r} is neither a preset {presets} nor a file"
            )
        name, source = path.stem, str(path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ScenarioError(f"{source}: cannot read the file ({exc.strerror})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ScenarioError(
            f"{source}: a scenario file must be UTF-8 text (TOML), got byte "
            f"{data[exc.start]:#04x} at offset {exc.start}, which is not UTF-8"
        ) from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: invalid TOML: {exc}") from None
    return doc, name, source


def parse_override(text: str) -> tuple[str, Any]:
    """Split ``"table.key=value"`` and parse the value as a TOML value.

    A value that is not valid TOML (``kernel=se``) is taken as a string, as if quoted.

    Raises
    ------
    ScenarioError
        If there is no ``=`` or the key is empty.
    """
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ScenarioError(f"--set must be KEY=VALUE with a table path as KEY, got {text!r}")
    try:
        parsed = tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value.strip()
    return key, parsed


def apply_overrides(doc: dict[str, Any], overrides: Mapping[str, Any], source: str) -> str:
    """Set ``doc[t1][t2]...[key] = value`` for each ``"t1.t2.key": value`` of ``overrides``.

    The document is changed in place; it is checked afterwards like a file, so an override
    of an unknown key is reported as an unknown key.

    Returns
    -------
    str
        The source label with the overrides named, for later messages.

    Raises
    ------
    ScenarioError
        If a table on the path is a value in the document.
    """
    for path, value in overrides.items():
        *tables, key = path.split(".")
        node = doc
        for i, t in enumerate(tables):
            sub = node.setdefault(t, {})
            if not isinstance(sub, dict):
                where = ".".join(tables[: i + 1])
                raise ScenarioError(
                    f"{source}: cannot set {path!r}: {where} is a value, not a table"
                )
            node = sub
        node[key] = value
    if overrides:
        return f"{source} with overrides {', '.join(overrides)}"
    return source
