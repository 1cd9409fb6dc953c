"""A swarm of robots swapping places: the safety filter with a barrier per pair.

``N`` single integrators in the plane, ``p_i' = u_i`` (positions in m, inputs in m/s), start
evenly on a circle of radius ``arena_radius`` and go to the antipodal point, so that every
path crosses the centre. The nominal input is ``u_nom,i = gain (goal_i - p_i)`` (a
proportional go-to-goal controller, 1/s), the limits ``|u_i,x|, |u_i,y| <= speed_limit``.
Each pair keeps ``h_ij = |p_i - p_j|^2 - safety_distance^2 >= 0`` (m^2) with the linear rate
``beta`` (1/s): ``2 (p_i - p_j).(u_i - u_j) >= -beta h_ij``.

Two filters, both exact (:func:`~safestab.formulas.clf_cbf_multi`'s dual active-set solver):

* **centralized**: one QP over all ``2N`` inputs with the ``N(N-1)/2`` pair barriers and the
  limits, ``min |u - u_nom|^2``;
* **decentralized**: each robot solves its own QP over its 2 inputs with ``N - 1`` barriers,
  taking half of each pair's budget, ``2 (p_i - p_j).u_i >= -beta h_ij / 2`` (the usual
  split: when both robots of a pair keep their halves, the pair's condition holds).

A small seeded perturbation of the start angles (``start_jitter``, rad) breaks the exact
symmetry of the swap, in which a symmetric deadlock at the centre is an equilibrium.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..controller_names import read_renamed
from ..errors import ScenarioError
from ..formulas.multi import multi_kernel
from ..simulation import closed_loop
from ._schema import (
    LIMITS,
    Check,
    check_count,
    check_structure,
    choice,
    integer,
    load_flat,
    name_field,
    real,
)

__all__ = [
    "FIELDS", "SwarmScenario", "SwarmRun", "PRESETS", "check_values", "load_swarm_scenario",
    "simulate_swarm", "pair_terms", "MODES", "UNFILTERED", "RENAMED_MODES", "check_mode",
    "current_mode", "swarm_closed_loop",
]  # fmt: skip

PRESETS = ("swarm",)


@dataclasses.dataclass(frozen=True)
class SwarmScenario:
    """Parameters of the swarm study (units in the field comments)."""

    name: str = "swarm"
    n_robots: int = 12  #: N, robots
    arena_radius: float = 4.0  #: m, radius of the start circle
    safety_distance: float = 0.6  #: m, least distance between two robots' centres
    speed_limit: float = 1.0  #: m/s, per axis
    gain: float = 1.0  #: 1/s, nominal go-to-goal gain
    beta: float = 2.0  #: 1/s, barrier rate
    t_final: float = 16.0  #: s
    dt: float = 0.02  #: s, control period (zero-order hold: exact for integrators)
    start_jitter: float = 0.02  #: rad, seeded perturbation of the start angles
    goal_tolerance: float = 0.05  #: m, a robot within this of its goal has arrived
    seed: int = 0

    def __post_init__(self) -> None:
        check_values(
            {"name": self.name, **{f"swarm.{f.name}": getattr(self, f.name) for f in
                                   dataclasses.fields(self) if f.name != "name"}},
            f"scenario {self.name!r}",
        )  # fmt: skip

    def replace(self, **changes: Any) -> SwarmScenario:
        """A copy with some fields changed (checked again); unknown names are an error."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise ScenarioError(f"swarm: unknown parameter(s) {unknown}; known: {sorted(names)}")
        return dataclasses.replace(self, **changes)

    def starts_and_goals(self, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Start and goal positions, each of shape (N, 2), m.

        The start angles are evenly spaced, each perturbed by a uniform draw in
        ``[-start_jitter, start_jitter]`` from ``seed`` (default: the scenario's); each goal
        is the antipode of its robot's perturbed start.
        """
        rng = np.random.default_rng(self.seed if seed is None else seed)
        angles = 2 * np.pi * np.arange(self.n_robots) / self.n_robots
        angles = angles + rng.uniform(-self.start_jitter, self.start_jitter, self.n_robots)
        start = self.arena_radius * np.stack([np.cos(angles), np.sin(angles)], -1)
        return start, -start


_POS = real(LIMITS.min_positive)

#: Every key of a swarm scenario file and its type check (the conditions that involve
#: several keys are :func:`check_values`'). ``name`` and ``kind`` are optional.
FIELDS: dict[str, Check] = {
    "name": name_field,
    "kind": choice(("swarm",)),
    # every pair is a barrier row: the centralized filter has N (N - 1) / 2 rows over 2 N inputs
    "swarm.n_robots": integer(2, 200),
    **{
        f"swarm.{key}": _POS
        for key in (
            "arena_radius",
            "safety_distance",
            "speed_limit",
            "gain",
            "beta",
            "t_final",
            "dt",
            "goal_tolerance",
        )
    },  # fmt: skip
    "swarm.start_jitter": real(0.0),
    "swarm.seed": integer(0, LIMITS.max_seed),
}


def check_values(flat: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Check every key of :data:`FIELDS` present in ``flat`` and the cross-field conditions.

    Parameters
    ----------
    flat : mapping
        ``{"swarm.key": value}`` (and optionally ``name``, ``kind``).
    source : str
        Where the values came from (a file, a scenario), for the messages.

    Returns
    -------
    dict
        The values normalised (floats as float).

    Raises
    ------
    ScenarioError
        Naming the key, what was received and what was expected: a value of the wrong type,
        not finite or out of range, a step count ``round(t_final / dt)`` outside
        ``[1, LIMITS.max_steps]``, or robots on the start circle no farther apart than the
        safety distance.
    """
    v = {path: check(path, flat[path], source) for path, check in FIELDS.items() if path in flat}
    check_count(source, "swarm.t_final / swarm.dt", "simulation steps",
                v["swarm.t_final"] / v["swarm.dt"])  # fmt: skip
    n, radius, distance = v["swarm.n_robots"], v["swarm.arena_radius"], v["swarm.safety_distance"]
    spacing = 2 * radius * np.sin(np.pi / n)
    if spacing <= distance * 1.05:
        raise ScenarioError(
            f"{source}: {n} robots on a circle of radius {radius} m are {spacing:.3f} m apart, "
            f"not more than the safety distance {distance} m (5 % margin): enlarge "
            "swarm.arena_radius or reduce swarm.n_robots"
        )
    return v


def load_swarm_scenario(
    name_or_path: str | Path, *, overrides: Mapping[str, Any] | None = None
) -> SwarmScenario:
    """Load the preset ``"swarm"`` or a swarm scenario file (``kind = "swarm"``).

    The file has one table, ``[swarm]``, whose keys are :class:`SwarmScenario`'s fields
    (docs/swarm.md); every key is required and checked here, before any work.

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"swarm.key": value}`` set before the document is checked (``--set``).

    Returns
    -------
    SwarmScenario

    Raises
    ------
    ScenarioError
        If the file cannot be read or parsed, a key or table is missing or unknown, or a
        value is of the wrong type, not finite or out of range; the message names the key.
    """
    optional = {"name", "kind"}
    flat, table, source = load_flat(
        name_or_path, PRESETS, __package__,
        lambda doc, src: check_structure(doc, FIELDS, optional, src), overrides,
    )  # fmt: skip
    if table is not None:
        raise ScenarioError(f"{source}: a swarm scenario has no [montecarlo] table")
    v = check_values(flat, source)  # with the file's name in the messages
    fields = {path.split(".", 1)[1]: value for path, value in v.items() if "." in path}
    return SwarmScenario(name=v["name"], **fields)


def pair_terms(pos: Any, beta: float, safety_distance: float) -> tuple[Any, Any, Any]:
    """Pair barriers at positions ``pos`` (N, 2): ``h`` (P,), ``c = beta h`` (P,), ``d`` (P, 2N).

    Pairs in the order of ``numpy.triu_indices(N, 1)``.
    """
    n = pos.shape[0]
    i, j = np.triu_indices(n, 1)
    diff = pos[i] - pos[j]  # (P, 2)
    h = jnp.sum(diff**2, -1) - safety_distance**2
    rows = jnp.arange(len(i))
    d = jnp.zeros((len(i), n, 2))
    d = d.at[rows, i].set(2 * diff).at[rows, j].set(-2 * diff)
    return h, beta * h, d.reshape(len(i), 2 * n)


def _centralized(sc: SwarmScenario, pos, u_nom):
    n = sc.n_robots
    _, c, d = pair_terms(pos, sc.beta, sc.safety_distance)
    lim = jnp.full(2 * n, sc.speed_limit)
    res = multi_kernel(
        jnp.zeros(0), jnp.zeros((0, 2 * n)), c, d, 0.0, 0.0, 0.0, 0.0, None, -lim, lim,
        u_nom.reshape(-1), None,
    )  # fmt: skip
    return res.u.reshape(n, 2), jnp.full(n, res.status)


def _decentralized(sc: SwarmScenario, pos, u_nom):
    n = sc.n_robots
    others = np.array([[j for j in range(n) if j != i] for i in range(n)])  # (N, N-1)
    diff = pos[:, None, :] - pos[others]  # (N, N-1, 2)
    h = jnp.sum(diff**2, -1) - sc.safety_distance**2
    lim = jnp.full((n, 2), sc.speed_limit)
    res = multi_kernel(
        jnp.zeros((n, 0)), jnp.zeros((n, 0, 2)), sc.beta * h / 2, 2 * diff, 0.0, 0.0, 0.0, 0.0,
        None, -lim, lim, u_nom, None,
    )  # fmt: skip
    return res.u, res.status


@dataclasses.dataclass(frozen=True)
class SwarmRun:
    """One closed-loop run of the swarm.

    ``t`` (T+1,) s, positions ``p`` (T+1, N, 2) m, inputs ``u`` and nominal inputs ``u_nom``
    (T, N, 2) m/s, solver statuses (T, N) (a :class:`~safestab.formulas.MultiStatus`, per
    robot; the centralized status is repeated).
    """

    mode: str
    t: np.ndarray
    p: np.ndarray
    u: np.ndarray
    u_nom: np.ndarray
    status: np.ndarray

    def min_distance(self) -> np.ndarray:
        """Least distance between two robots at each time, (T+1,) m."""
        i, j = np.triu_indices(self.p.shape[1], 1)
        return np.min(np.linalg.norm(self.p[:, i] - self.p[:, j], axis=-1), axis=-1)


#: The mode without a filter: the nominal go-to-goal input clipped to the limits.
UNFILTERED = "unfiltered"
MODES = ("centralized", "decentralized", UNFILTERED)
#: Old mode names, read for one release (with a DeprecationWarning): old -> current.
RENAMED_MODES = {"nominal": UNFILTERED}


def current_mode(mode: Any, name: str = "mode") -> Any:
    """``mode``, or its current name if it is an old one (with a DeprecationWarning)."""
    # the warning points at the caller of check_mode (or of the plan that reads --controllers)
    return read_renamed(mode, RENAMED_MODES, "swarm mode", name, stacklevel=5)


def check_mode(mode: str, name: str = "mode") -> str:
    """``mode`` if it is one of :data:`MODES`.

    Raises
    ------
    ScenarioError
        Naming ``name``, what was received and the modes.
    """
    mode = current_mode(mode, name)
    if mode not in MODES:
        raise ScenarioError(
            f"{name} must be one of {', '.join(repr(m) for m in MODES)}, got {mode!r}"
        )
    return mode


def swarm_closed_loop(sc: SwarmScenario, mode: str, recorder: Any) -> Any:
    """The swarm's closed loop under ``mode``, as ``run(start, goal) -> recorded``.

    One ``lax.scan`` (:func:`~safestab.simulation.closed_loop`) of ``round(t_final / dt)``
    steps; jittable and ``vmap``-able over ``start`` and ``goal``, each of shape (N, 2), m.
    The recorder's ``update`` sees the positions at ``t_k`` and the step's output
    ``{"u", "u_nom", "status"}`` (the input held over ``[t_k, t_k + dt]``), and the goal as
    the run's data.

    Parameters
    ----------
    sc : SwarmScenario
    mode : {"centralized", "decentralized", "unfiltered"}
        ``"unfiltered"`` applies the nominal input clipped to the limits (no filter); the
        old name ``"nominal"`` is read for one release.
    recorder : Recorder

    Returns
    -------
    callable

    Raises
    ------
    ScenarioError
        For an unknown ``mode``.
    """
    mode = check_mode(mode)

    def step(t, pos, goal):
        u_nom = sc.gain * (goal - pos)
        if mode == "centralized":
            u, status = _centralized(sc, pos, u_nom)
        elif mode == "decentralized":
            u, status = _decentralized(sc, pos, u_nom)
        else:
            u = jnp.clip(u_nom, -sc.speed_limit, sc.speed_limit)
            status = jnp.zeros(sc.n_robots, jnp.int32)
        return {"u": u, "u_nom": u_nom, "status": status}

    def rhs(t, pos, out, goal):
        return out["u"]  # p_i' = u_i, held over the step (RK4 is exact for it)

    steps = int(round(sc.t_final / sc.dt))
    return closed_loop(step, rhs, recorder, n_steps=steps, dt=sc.dt)


def simulate_swarm(sc: SwarmScenario, mode: str = "centralized") -> SwarmRun:
    """Run the swarm from its starts for ``t_final`` with the filter ``mode``.

    Parameters
    ----------
    sc : SwarmScenario
    mode : {"centralized", "decentralized", "unfiltered"}
        ``"unfiltered"`` applies the nominal input clipped to the limits (no filter); the
        old name ``"nominal"`` is read for one release.

    Returns
    -------
    SwarmRun

    Raises
    ------
    ScenarioError
        For an unknown ``mode``.
    """
    mode = check_mode(mode)
    run = swarm_closed_loop(sc, mode, _SwarmRecorder())
    start, goal = sc.starts_and_goals()
    p, u, u_nom, status = jax.jit(run)(jnp.asarray(start), jnp.asarray(goal))
    t = sc.dt * np.arange(p.shape[0])
    return SwarmRun(mode, t, np.asarray(p), np.asarray(u), np.asarray(u_nom), np.asarray(status))


class _SwarmRecorder:
    """The swarm's history: positions at t_0 .. t_K, inputs and statuses at t_0 .. t_{K-1}."""

    def init(self, x0: Any, data: Any) -> None:
        return None

    def update(self, state, k, t, pos, out, data):
        return None, (pos, out["u"], out["u_nom"], out["status"])

    def finish(self, state, ys, pos_final, out_final, t_final, data):
        p, u, u_nom, status = ys
        return jnp.concatenate([p, pos_final[None]], 0), u, u_nom, status
