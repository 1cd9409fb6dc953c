"""Collision avoidance in the plane, the paper's Fig. 2, with an unknown current (TOML presets).

State ``x = (x1, x2)``: position of a planar vehicle (a boat or a drone) relative to the goal,
m. The vehicle is commanded in velocity, ``u = (u1, u2)`` in m/s, and drifts with a current::

    true:     xdot = w(x) + k_true u        nominal:  xdot = k_nom u
    w(x)    = exp(-|x - (x1_c, 0)|^2 / (2 L^2)) (U, -W x2 / L)          (m/s)

a jet of speed ``U`` along +x1 centred on the x1 axis at ``x1_c`` with width ``L``, which also
draws water towards the axis (``W``). The model error is ``omega(x) = w(x)`` (m/s); the gain
mismatch ``k_true != k_nom`` is *not* part of ``omega`` (the paper's ``omega`` cannot depend
on ``u``): the GP sees it as input-dependent noise (docs/obstacle.md).

Certificates: CLF ``V = x^T P x`` (m^2, ``P = diag(P11, P22)``) with rate ``lam``; CBF
``h = |x - x_o|^2 - r^2`` (m^2) for a disc obstacle centred at ``x_o = (x1_o, 0)``, with rate
``beta``. The goal, the obstacle centre and the current's centre lie on the x1 axis and the
field is mirror-symmetric about it, so a trajectory started on the axis stays on it; there
``b = L_g V`` and ``d = L_g h`` are exactly parallel, which is where Lemma 1 can fail.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..certificates import CBF, CLF, LieTerms
from ..controllers import UniversalController
from ..errors import ParameterError, ScenarioError
from ..filters import SafetyFilter
from ..learning.input_gain import InputGain, with_input_gain
from ..systems import ControlAffineSystem
from ._mc_schema import MonteCarloSpec, check_montecarlo
from ._obstacle_schema import KIND, check_structure, check_values
from ._schema import LEARNING_KEYS, load_flat
from .trial_studies import ObstacleTrials

__all__ = ["ObstacleScenario", "load_obstacle_scenario", "PRESETS"]

PRESETS = ("obstacle",)

# dataclass field -> TOML key
_KEYS = {
    "gain_true": "vehicle.gain_true",
    "gain_nominal": "vehicle.gain_nominal",
    "current_speed": "current.speed",
    "current_inflow": "current.inflow",
    "current_x1": "current.x1",
    "current_width": "current.width",
    "obstacle_x1": "obstacle.x1",
    "radius": "obstacle.radius",
    "P": "certificates.P",
    "lam": "certificates.lam",
    "beta": "certificates.beta",
    **{
        k: f"controller.{k}"
        for k in (
            "kappa",
            "rho",
            "phi",
            "varphi",
            "slack_weight",
            "input_limit",
            "doa_fraction",
            "robust_clf_layer",
            "limit_method",
        )  # fmt: skip
    },
    "starts_x1": "starts.x1",
    "starts_n_x1": "starts.n_x1",
    "starts_x2_half_width": "starts.x2_half_width",
    "starts_n_x2": "starts.n_x2",
    "map_x1": "map.x1",
    "map_n_x1": "map.n_x1",
    "map_x2_half_width": "map.x2_half_width",
    "map_n_x2": "map.n_x2",
    **{k: f"simulation.{k}" for k in ("t_final", "dt", "ball_radius", "rest_speed")},
    **{
        k: f"learning.{k}"
        for k in (*LEARNING_KEYS, "beta_method", "delta", "n_inducing", "input_gain")
    },
}


def _symmetric(half_width: float, n: int) -> np.ndarray:
    """``n`` points from ``-half_width`` to ``half_width``; the middle one exactly 0 if n is odd."""
    if n == 1:
        return np.zeros(1)
    k = np.arange(n) - (n - 1) / 2
    return k * (half_width / ((n - 1) / 2))


@dataclasses.dataclass(frozen=True)
class ObstacleScenario:
    """All parameters of one obstacle study; built from TOML by :func:`load_obstacle_scenario`.

    Units: positions m, velocities and inputs m/s, times s; ``V`` and ``h`` in m^2, so
    ``lam``, ``beta`` in 1/s, ``phi``, ``varphi`` in 1/s^2, ``slack_weight`` in 1/m^2.
    Every field is checked when the object is made (loader, constructor or :meth:`replace`),
    with the bounds of docs/obstacle.md ("Scenario file").

    Raises
    ------
    ScenarioError
        If a field has the wrong type, is not finite or is out of range; the message names
        the TOML key (``learning.seed``), what was received and what was expected.
    """

    name: str
    gain_true: float
    gain_nominal: float
    current_speed: float  # m/s
    current_inflow: float  # m/s
    current_x1: float  # m
    current_width: float  # m
    obstacle_x1: float  # m
    radius: float  # m
    P: tuple[float, ...]  # diagonal of P
    lam: float  # 1/s
    beta: float  # 1/s
    kappa: float
    rho: float
    phi: float  # 1/s^2
    varphi: float  # 1/s^2
    slack_weight: float  # 1/m^2
    input_limit: float  # m/s per component
    doa_fraction: float
    starts_x1: tuple[float, ...]  # (low, high), m
    starts_n_x1: int
    starts_x2_half_width: float  # m
    starts_n_x2: int
    map_x1: tuple[float, ...]  # (low, high), m
    map_n_x1: int
    map_x2_half_width: float  # m
    map_n_x2: int
    t_final: float  # s
    dt: float  # s
    ball_radius: float  # m
    rest_speed: float  # m/s
    n_samples: int
    sample_rate: float  # Hz
    sample_horizon: float  # s
    noise_std: float  # m/s
    gp_beta: float
    delta: float
    kernel: str
    x0_low: tuple[float, ...]  # (x1, x2), m
    x0_high: tuple[float, ...]
    excitation_limit: float  # m/s
    hyper_subset: int
    n_inducing: int  # 0: exact GP in the controller
    seed: int
    #: The optional ``[montecarlo]`` table (trial distributions); ``None`` when absent.
    montecarlo: MonteCarloSpec | None = None
    #: ``learning.beta_method`` (optional): "chosen" uses ``gp_beta``; "conformal" calibrates
    #: beta by split conformal prediction on fresh trajectories and uses it instead
    #: (:func:`~safestab.scenarios.obstacle_study.calibrate_beta`, docs/obstacle.md).
    beta_method: str = "chosen"
    #: ``controller.robust_clf_layer`` (optional, m): the GP-robust controller's boundary layer
    #: on the CLF's robust term (:class:`~safestab.UniversalController`); 0: Lemma 3's term.
    robust_clf_layer: float = 0.0
    #: ``controller.limit_method`` (optional): how the runs with input limits keep them.
    #: "projection" clips the relaxed formula's input to the box (eq. (26), the paper's; it
    #: voids Theorem 1's guarantee); "filter" solves the same problem with the box as
    #: constraints (:class:`~safestab.SafetyFilter`: the exact QP optimum, docs/obstacle.md).
    limit_method: str = "projection"
    #: ``learning.input_gain`` (optional): "nominal" trusts the nominal gain; "learned"
    #: estimates the constant input-matrix error ``D`` (true ``k_true I = k_nom I + D``) with
    #: the GP (:func:`~safestab.learning.fit_input_gain`) and gives the GP-robust controller
    #: ``g + D`` (docs/obstacle.md).
    input_gain: str = "nominal"
    #: Not a file key: the estimated input-matrix error ``D`` (2 x 2, m/s per m/s) that
    #: :func:`~safestab.scenarios.obstacle_study.run_obstacle_study` sets after the fit when
    #: ``input_gain = "learned"``; :meth:`system` ``("learned")`` adds it to the nominal gain.
    learned_gain: tuple[tuple[float, ...], ...] | None = None

    def __post_init__(self) -> None:
        flat = {key: getattr(self, attr) for attr, key in _KEYS.items()}
        flat.update(name=self.name, kind=KIND)
        check_values(flat, f"scenario {self.name!r}")
        if self.learned_gain is not None:
            bad = ScenarioError(
                f"scenario {self.name!r}: learned_gain must be a finite 2 x 2 matrix, got "
                f"{self.learned_gain!r}"
            )
            try:
                d = np.asarray(self.learned_gain, dtype=float)
            except (TypeError, ValueError) as exc:
                raise bad from exc
            if d.shape != (2, 2) or not np.all(np.isfinite(d)):
                raise bad
            if self.input_gain != "learned":
                # a gain left over from a learned run would reach the GP-robust controller
                raise ScenarioError(
                    f"scenario {self.name!r}: learned_gain is set only with "
                    f"learning.input_gain = 'learned', got input_gain = {self.input_gain!r}"
                )
        if self.montecarlo is not None and not isinstance(self.montecarlo, MonteCarloSpec):
            raise ScenarioError(
                f"scenario {self.name!r}: montecarlo must be a MonteCarloSpec or None, got "
                f"{type(self.montecarlo).__name__}"
            )

    def with_learned_gain(self, gain: InputGain | None) -> ObstacleScenario:
        """A copy whose ``learned_gain`` is ``gain.matrix`` (itself when ``gain`` is None)."""
        if gain is None:
            return self
        return self.replace(learned_gain=tuple(map(tuple, np.asarray(gain.matrix).tolist())))

    def replace(self, **changes: Any) -> ObstacleScenario:
        """A copy with some fields changed, checked like a loaded file.

        Raises
        ------
        ScenarioError
            If a new value is invalid (the message names its TOML key).
        """
        return dataclasses.replace(self, **changes)

    # -- model ----------------------------------------------------------------------------

    @property
    def obstacle_center(self) -> np.ndarray:
        """``x_o = (x1_o, 0)``, m; shape (2,)."""
        return np.array([self.obstacle_x1, 0.0])

    def current(self, x: Any) -> Any:
        """The current ``w(x)`` in m/s, shape (..., 2), for positions of shape (..., 2)."""
        x = jnp.asarray(x, dtype=float)
        L = self.current_width
        r2 = (x[..., 0] - self.current_x1) ** 2 + x[..., 1] ** 2
        bump = jnp.exp(-r2 / (2 * L * L))
        return jnp.stack(
            [self.current_speed * bump, -self.current_inflow * x[..., 1] / L * bump], -1
        )

    def omega(self, x: Any) -> Any:
        """The model error ``omega(x) = f_true(x) - f_nominal(x) = w(x)``, m/s, (..., 2)."""
        return self.current(x)

    def gain(self, which: str = "true") -> float:
        """The input gain ``k`` of the ``"true"`` or ``"nominal"`` model."""
        if which not in ("true", "nominal"):
            raise ParameterError(f"which must be 'true' or 'nominal', got {which!r}")
        return self.gain_true if which == "true" else self.gain_nominal

    def system(self, which: str = "true") -> ControlAffineSystem:
        """The ``"true"`` model (current, true gain), the ``"nominal"`` one, or ``"learned"``.

        ``"nominal"``: no current, gain ``k_nom``. ``"learned"``: nominal, with input matrix
        ``k_nom I + learned_gain`` (the nominal one when no gain was learned), which the
        GP-robust controller uses.
        """
        if which not in ("true", "nominal", "learned"):
            raise ParameterError(f"which must be 'true', 'nominal' or 'learned', got {which!r}")
        if which == "learned":
            nominal = self.system("nominal")
            if self.learned_gain is None:
                return nominal
            return with_input_gain(nominal, np.asarray(self.learned_gain, dtype=float))
        k = self.gain(which)
        if which == "true":
            f = self.current
        else:

            def f(x):
                return jnp.zeros(2)

        return ControlAffineSystem(f, lambda x: k * jnp.eye(2), 2, name=f"obstacle-{which}")

    def model_family(self) -> ControlAffineSystem:
        """The ``"true"`` and ``"nominal"`` models as one system with run-time parameters.

        ``f(x, p) = p["current_scale"] w(x)`` and ``g(x, p) = p["gain"] I``: with
        :meth:`model_params` it is either model, to the last bit (``1 w = w`` and ``0 w = 0``
        exactly, up to the sign of a zero). The study's true-model and mismatched-model
        controllers are built on it, so that they are one program with different data
        (:func:`~safestab.simulate` reuses the first's compiled loop for the second) instead
        of two.
        """

        def f(x, p):
            return p["current_scale"] * self.current(x)

        def g(x, p):
            return p["gain"] * jnp.eye(2)

        example = {"current_scale": 1.0, "gain": 1.0}
        return ControlAffineSystem(f, g, 2, name="obstacle-model", params=example)

    def model_params(self, which: str) -> dict[str, float]:
        """The parameters of :meth:`model_family` that make it the ``which`` model."""
        return {"current_scale": 1.0 if which == "true" else 0.0, "gain": self.gain(which)}

    def V(self, x: Any) -> Any:
        """``V = x^T P x``, m^2, shape (...,)."""
        x = jnp.asarray(x, dtype=float)
        return self.P[0] * x[..., 0] ** 2 + self.P[1] * x[..., 1] ** 2

    def h(self, x: Any) -> Any:
        """``h = |x - x_o|^2 - r^2``, m^2, shape (...,)."""
        x = jnp.asarray(x, dtype=float)
        return (x[..., 0] - self.obstacle_x1) ** 2 + x[..., 1] ** 2 - self.radius**2

    def certificates(self) -> tuple[CLF, CBF]:
        """CLF ``x^T P x`` with rate ``lam`` and CBF ``|x - x_o|^2 - r^2`` with rate ``beta``."""
        return CLF(self.V, lam=self.lam), CBF(self.h, beta=self.beta)

    def hand_lie_terms(self, x: Any, which: str = "true") -> LieTerms:
        """The Lie terms written out by hand, for shape (..., 2) positions.

        ``a = 2 x^T P f + lam V``, ``b = 2 k P x``, ``c = 2 (x - x_o).f + beta h``,
        ``d = 2 k (x - x_o)``, with ``f = w(x)`` (true) or 0 (nominal).
        """
        x = jnp.asarray(x, dtype=float)
        k = self.gain(which)
        f = self.current(x) if which == "true" else jnp.zeros_like(x)
        Px = jnp.stack([self.P[0] * x[..., 0], self.P[1] * x[..., 1]], -1)
        e = x - jnp.asarray(self.obstacle_center)
        a = 2 * jnp.sum(Px * f, -1) + self.lam * self.V(x)
        c = 2 * jnp.sum(e * f, -1) + self.beta * self.h(x)
        return LieTerms(a, 2 * k * Px, c, 2 * k * e)

    def input_limits(self) -> tuple[list[float], list[float]]:
        """``(u_min, u_max)`` in m/s for the runs with input limits."""
        lim = self.input_limit
        return [-lim, -lim], [lim, lim]

    def limited_controller(
        self, system: ControlAffineSystem, clf: CLF, cbf: CBF, **options: Any
    ) -> UniversalController | SafetyFilter:
        """A controller with the input limits, kept as ``controller.limit_method`` says.

        ``options`` are the keyword arguments of both controllers and hold the box
        (``u_min``, ``u_max``). ``"filter"``: a :class:`~safestab.SafetyFilter` solving the
        relaxed problem with the box as constraints; ``"projection"``: a
        :class:`~safestab.UniversalController` projecting its input onto the box (eq. (26)).
        Used by the study and by its Monte Carlo trials alike.
        """
        if self.limit_method == "filter":
            return SafetyFilter(system, cbf, clfs=clf, **options)
        return UniversalController(system, clf, cbf, **options)

    def trial_study(self, spec: MonteCarloSpec | None = None) -> Any:
        """The Monte Carlo trial study of this scenario (:class:`~.trials.ObstacleTrials`).

        ``spec`` defaults to the scenario's ``[montecarlo]`` table, else the defaults; the
        compared controllers run with the input limits.
        """
        return ObstacleTrials(self, spec or self.montecarlo or MonteCarloSpec())

    # -- grids ----------------------------------------------------------------------------

    def start_states(self) -> np.ndarray:
        """The initial states: the start grid without the points where ``h <= 0``; (N, 2).

        The x2 values are symmetric about 0 (exactly 0 in the middle when ``n_x2`` is odd),
        so that an odd grid has starts on the axis through the goal and the obstacle.
        """
        x1 = np.linspace(self.starts_x1[0], self.starts_x1[1], self.starts_n_x1)
        x2 = _symmetric(self.starts_x2_half_width, self.starts_n_x2)
        grid = np.stack(np.meshgrid(x1, x2, indexing="ij"), -1).reshape(-1, 2)
        return grid[np.asarray(self.h(grid)) > 0]

    def map_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The compatibility-map grid axes: x1 of shape (n_x1,), x2 of shape (n_x2,), m."""
        return (
            np.linspace(self.map_x1[0], self.map_x1[1], self.map_n_x1),
            _symmetric(self.map_x2_half_width, self.map_n_x2),
        )

    def parallel_set(self, n: int = 2001) -> np.ndarray:
        """Points of the map region where ``b`` and ``d`` point the same way; (N, 2).

        With ``P = diag(p1, p2)`` and ``x_o = (x1_o, 0)``, ``P x = t (x - x_o)`` with
        ``t > 0`` holds on the x1 axis where ``x1`` and ``x1 - x1_o`` have the same sign, and
        (if ``p1 != p2``) on the line ``x1 = p2 x1_o / (p2 - p1)`` (``t = p2``). Lemma 1 can
        fail only there (docs/obstacle.md). Sampled with ``n`` points per line; the axis
        samples include the obstacle's back boundary point ``x1_o + sign(x1_o) r`` exactly.
        """
        lo, hi = self.map_x1
        xo, r = self.obstacle_x1, self.radius
        s = np.sign(xo)
        far = lo if s < 0 else hi  # the map's end behind the obstacle
        back = np.linspace(xo + s * r, far, n) if (far - xo) * s > r else np.empty(0)
        ahead = np.linspace(0.0, hi if s < 0 else lo, n // 4 + 2)[1:]  # beyond the goal
        pts = [np.stack([back, np.zeros_like(back)], -1), np.stack([ahead, 0 * ahead], -1)]
        p1, p2 = self.P
        if p1 != p2:
            x_line = p2 * xo / (p2 - p1)
            if lo <= x_line <= hi:
                x2 = np.linspace(-self.map_x2_half_width, self.map_x2_half_width, n)
                pts.append(np.stack([np.full_like(x2, x_line), x2], -1))
        return np.concatenate(pts, 0)


# -- TOML -------------------------------------------------------------------------------


def load_obstacle_scenario(
    name_or_path: str | Path, *, overrides: Mapping[str, Any] | None = None
) -> ObstacleScenario:
    """Load the preset ``"obstacle"`` or an obstacle scenario file (``kind = "obstacle"``).

    Every key is checked for type, finiteness and range here, before any work (the keys,
    units and bounds are listed in docs/obstacle.md).

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"table.key": value}`` set before the document is checked (``--set``).

    Raises
    ------
    ScenarioError
        If the file cannot be read or parsed, or a key or table is missing, unknown, of the
        wrong type, not finite or out of range; the message names the key.
    """
    flat, table, source = load_flat(
        name_or_path, PRESETS, __package__, check_structure, overrides,
        defaults={
            "learning.beta_method": "chosen", "learning.input_gain": "nominal",
            "controller.robust_clf_layer": 0.0, "controller.limit_method": "projection",
        },
    )  # fmt: skip
    v = check_values(flat, source)
    spec = (
        None
        if table is None
        else check_montecarlo(table, source, states=(2, "x1 m, x2 m"), subtables=("initial",))
    )
    return ObstacleScenario(
        name=v["name"], montecarlo=spec, **{attr: v[key] for attr, key in _KEYS.items()}
    )
