"""The optional ``[montecarlo]`` table of an ACC scenario file: keys, defaults, checks.

Internal: :mod:`safestab.scenarios.acc` checks the table with :func:`check_montecarlo` when a
file is loaded, and :class:`MonteCarloSpec` checks itself when made. Messages have the form
of the rest of the file (``"<source>: montecarlo.<key> must be <expected>, got <received>"``);
docs/montecarlo.md lists every key.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ..controller_names import CONTROLLERS, current_name
from ..errors import ScenarioError
from ._schema import LIMITS, choice, fail, integer, real

__all__ = ["CONTROLLERS", "MC_FIELDS", "MonteCarloSpec", "check_controllers", "check_montecarlo"]

#: Most trials one study may ask for, and most data sets (each a GP fit).
MAX_TRIALS, MAX_DATASETS, MAX_SEGMENTS = 100_000_000, 10_000, 1000
_BIG, _SMALL = LIMITS.max_magnitude, LIMITS.min_positive


def check_controllers(path: str, value: Any, source: str) -> tuple[str, ...]:
    """The controllers ``value`` (names from :data:`CONTROLLERS`), or a ScenarioError.

    An old name (:data:`~safestab.controller_names.RENAMED`) is read as its current name, with
    a DeprecationWarning.
    """
    expected = "a non-empty array of distinct names from " + ", ".join(map(repr, CONTROLLERS))
    if not isinstance(value, list | tuple) or not value:
        raise fail(source, path, expected, value)
    value = [current_name(name, f"{source}: {path}[{i}]") for i, name in enumerate(value)]
    for i, name in enumerate(value):
        if not isinstance(name, str) or name not in CONTROLLERS:
            raise fail(source, f"{path}[{i}]", "one of " + ", ".join(map(repr, CONTROLLERS)), name)
    if len(set(value)) != len(value):
        raise fail(source, path, expected + " (a name appears twice)", value)
    return tuple(value)


def _vector_or_none(path: str, value: Any, source: str) -> tuple[float, ...] | None:
    """A non-empty array of finite numbers (its length is the scenario's: :func:`check_values`)."""
    if value is None:
        return None
    if not isinstance(value, list | tuple) or not value:
        raise fail(source, path, "an array of finite numbers, one per state", value)
    check = real(-_BIG)
    return tuple(check(f"{path}[{i}]", v, source) for i, v in enumerate(value))


def _boolean(path: str, value: Any, source: str) -> bool:
    if not isinstance(value, bool):
        raise fail(source, path, "true or false", value)
    return value


def _optional_real(low: float, high: float = _BIG):
    check = real(low, high)

    def run(path: str, value: Any, source: str) -> float | None:
        return None if value is None else check(path, value, source)

    return run


#: Every key of the table (``montecarlo.`` prefix omitted), its check and its default.
#: ``None`` defaults are filled from the scenario (documented in :class:`MonteCarloSpec`).
MC_FIELDS: dict[str, tuple[Any, Any]] = {
    "trials": (integer(1, MAX_TRIALS), 1000),
    "datasets": (integer(1, MAX_DATASETS), 1),
    "hyperparameters": (choice(("refit", "reuse")), "reuse"),
    "noise_std": (_optional_real(0.0), None),
    "controllers": (check_controllers, CONTROLLERS[:5]),
    "gp": (choice(("fast", "exact")), "fast"),
    "n_inducing": (integer(1, 1024), 32),
    "chunk_size": (integer(1, 1_000_000), 1000),
    "delta": (real(_SMALL, 1.0 - 1e-12), 0.01),
    "rkhs_norm": (real(0.0), 1.0),
    "price_metrics": (_boolean, False),
    "substeps": (integer(1, 1000), 1),
    "ddh_bound": (_optional_real(0.0), None),
    "initial.distribution": (choice(("fixed", "box", "normal")), "fixed"),
    "initial.low": (_vector_or_none, None),
    "initial.high": (_vector_or_none, None),
    "initial.mean": (_vector_or_none, None),
    "initial.std": (_vector_or_none, None),
    "lead.kind": (choice(("fixed", "random")), "fixed"),
    "lead.segments": (integer(1, MAX_SEGMENTS), 6),
    "lead.duration_min": (real(_SMALL), 5.0),
    "lead.duration_max": (real(_SMALL), 15.0),
    "lead.decel_max": (real(0.0, 10.0), 0.3),
    "lead.accel_max": (real(0.0, 10.0), 0.3),
}
_NEEDS = {"box": ("initial.low", "initial.high"), "normal": ("initial.mean", "initial.std")}


@dataclasses.dataclass(frozen=True)
class MonteCarloSpec:
    """The trial distributions and settings of a Monte Carlo study (``[montecarlo]``).

    Every field is checked when the object is made; the names are the TOML keys with ``.``
    replaced by ``_`` (``initial.low`` -> ``initial_low``).

    Attributes
    ----------
    trials : int
        Default number of trials ``N`` (the command line's ``--trials`` overrides it).
    datasets : int
        ``K``, independent data sets: each a fresh ``collect_data`` and GP.
    hyperparameters : {"reuse", "refit"}
        ``"reuse"``: the first data set's fitted hyperparameters, conditioned on each further
        data set; ``"refit"``: fitted again for every data set.
    noise_std : float or None
        Measurement noise on the GP targets, m/s^2; ``None`` takes ``learning.noise_std``.
    controllers : tuple of str
        Names from :data:`CONTROLLERS`.
    gp : {"fast", "exact"}
        The GP through the inducing-point cache (batched as matrix products) or the exact
        posterior (cost grows with ``Q``).
    n_inducing : int
        Inducing inputs per component of the fast cache.
    chunk_size : int
        Trials per compiled batch (bounds memory); results do not depend on it.
    delta, rkhs_norm : float
        Lemma 2's ``delta`` per component and the assumed bound on ``||omega_i||_k``.
    price_metrics : bool
        Also record, per trial and controller, the input's distance from the true-model
        controller's input at the same state and the time to converge
        (:data:`~safestab.montecarlo.loop.RECORD_FIELDS` ``mean_input_gap``,
        ``settle_time``; -1 when off). Off by default: one more controller step per step.
    substeps : int
        RK4 steps per hold interval of ``simulation.dt`` (default 1): with more, each trial
        also records the least ``h`` between the samples (``min_h_between``), and a trial is
        safe only if it stays >= 0 there too.
    ddh_bound : float or None
        The sampled-data margin's bound ``M`` on ``-d^2h/dt^2`` (docs/deployed.md): every
        compared controller then runs with ``sample_time = simulation.dt`` and this
        ``ddh_bound``. None (default): no margin.
    initial_distribution : {"fixed", "box", "normal"}
        The scenario's own initial state, a uniform box ``[initial_low, initial_high]``, or
        independent normals ``N(initial_mean, initial_std^2)`` per component.
    lead_kind : {"fixed", "random"}
        The scenario's lead profile, or ``lead_segments`` random segments with durations
        uniform in ``[lead_duration_min, lead_duration_max]`` s and accelerations uniform in
        ``[-lead_decel_max g, lead_accel_max g]`` (the paper's ``a_L`` bounds, fractions of g).
    """

    trials: int = 1000
    datasets: int = 1
    hyperparameters: str = "reuse"
    noise_std: float | None = None
    controllers: tuple[str, ...] = CONTROLLERS[:5]
    gp: str = "fast"
    n_inducing: int = 32
    chunk_size: int = 1000
    delta: float = 0.01
    rkhs_norm: float = 1.0
    price_metrics: bool = False
    substeps: int = 1
    ddh_bound: float | None = None
    initial_distribution: str = "fixed"
    initial_low: tuple[float, ...] | None = None
    initial_high: tuple[float, ...] | None = None
    initial_mean: tuple[float, ...] | None = None
    initial_std: tuple[float, ...] | None = None
    lead_kind: str = "fixed"
    lead_segments: int = 6
    lead_duration_min: float = 5.0
    lead_duration_max: float = 15.0
    lead_decel_max: float = 0.3
    lead_accel_max: float = 0.3

    def __post_init__(self) -> None:
        flat = {key: getattr(self, key.replace(".", "_")) for key in MC_FIELDS}
        check_values(flat, "montecarlo spec")

    def replace(self, **changes: Any) -> MonteCarloSpec:
        """A copy with some fields changed, checked like a loaded table."""
        return dataclasses.replace(self, **changes)


def check_values(
    flat: Mapping[str, Any], source: str, states: tuple[int, str] | None = None
) -> dict[str, Any]:
    """Check every present key of the table and the conditions between keys.

    ``states = (n, labels)``, where the scenario is known, asks each ``initial.*`` vector
    for ``n`` entries (``labels`` names them in the message).

    Raises
    ------
    ScenarioError
        Naming the key (``montecarlo.<key>``), what was received and what was expected.
    """
    out = {}
    for key, (check, _) in MC_FIELDS.items():
        if key in flat:
            out[key] = check(f"montecarlo.{key}", flat[key], source)
    n, labels = states if states is not None else (None, "")
    count = "finite numbers" if n is None else f"{n} finite numbers"
    for key in ("initial.low", "initial.high", "initial.mean", "initial.std"):
        if n is not None and out.get(key) is not None and len(out[key]) != n:
            raise fail(source, f"montecarlo.{key}", f"an array of {count} ({labels})", flat[key])
    if out.get("initial.std") is not None and min(out["initial.std"]) < 0:
        expected = f"an array of {count} >= 0 (standard deviations)"
        raise fail(source, "montecarlo.initial.std", expected, flat["initial.std"])
    dist = out.get("initial.distribution", "fixed")
    for key in _NEEDS.get(dist, ()):
        if out.get(key) is None:
            raise ScenarioError(
                f"{source}: montecarlo.{key} is required with initial.distribution = {dist!r}"
            )
    pairs = (("initial.low", "initial.high"), ("initial.mean", "initial.std"))
    for a_key, b_key in pairs:
        a, b = out.get(a_key), out.get(b_key)
        if a is not None and b is not None and len(a) != len(b):
            raise ScenarioError(
                f"{source}: montecarlo.{a_key} and montecarlo.{b_key} must have the same length "
                f"(one entry per state), got {len(a)} and {len(b)}"
            )
    if dist == "box":
        for i, (a, b) in enumerate(zip(out["initial.low"], out["initial.high"], strict=True)):
            if a > b:
                raise ScenarioError(
                    f"{source}: montecarlo.initial.low[{i}] must be <= "
                    f"montecarlo.initial.high[{i}] = {b!r}, got {a!r}"
                )
    lo, hi = out.get("lead.duration_min", 5.0), out.get("lead.duration_max", 15.0)
    if lo > hi:
        raise ScenarioError(
            f"{source}: montecarlo.lead.duration_min must be <= montecarlo.lead.duration_max "
            f"= {hi!r}, got {lo!r}"
        )
    return out


def check_montecarlo(
    table: Any,
    source: str,
    states: tuple[int, str] = (3, "v_f m/s, v_l m/s, D m"),
    subtables: tuple[str, ...] = ("initial", "lead"),
) -> MonteCarloSpec:
    """Check a parsed ``[montecarlo]`` table and build the spec (missing keys take defaults).

    ``states = (n, labels)``: the scenario's state dimension and the names of its components
    (the ``initial.*`` vectors have ``n`` entries); ``subtables``: the sub-tables the scenario
    takes (the obstacle has no ``lead``). The defaults are the ACC's.

    Raises
    ------
    ScenarioError
        For an unknown key or sub-table, a scalar where a table belongs, or a bad value.
    """
    if not isinstance(table, Mapping):
        raise fail(source, "montecarlo", "a table", table)
    flat: dict[str, Any] = {}
    fields = {k for k in MC_FIELDS if "." not in k or k.split(".")[0] in subtables}
    for key, value in table.items():
        if key in subtables:
            if not isinstance(value, Mapping):
                raise fail(source, f"montecarlo.{key}", "a table", value)
            for sub, v in value.items():
                if f"{key}.{sub}" not in MC_FIELDS:
                    known = sorted(k.split(".")[1] for k in MC_FIELDS if k.startswith(key + "."))
                    raise ScenarioError(
                        f"{source}: unknown key {sub!r} in [montecarlo.{key}]; expected one of "
                        + ", ".join(known)
                    )
                flat[f"{key}.{sub}"] = v
        elif key in fields:
            flat[key] = value
        else:
            known = sorted({k.split(".")[0] for k in fields})
            raise ScenarioError(
                f"{source}: unknown key {key!r} in [montecarlo]; expected one of "
                + ", ".join(known)
            )
    values = check_values(flat, source, states)
    return MonteCarloSpec(**{k.replace(".", "_"): v for k, v in values.items()})
