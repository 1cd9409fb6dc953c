"""Adaptive cruise control, the paper's Section IV (eq. (27), Table I), with TOML presets.

State ``x = (v_f, v_l, D)``: follower speed (m/s), lead speed (m/s), gap distance (m).
Dynamics::

    v_f' = (-F_r(v_f) + F) / M,   F_r(v) = f0 + f1 v + f2 v^2   (N)
    v_l' = a_L(t)                                                (m/s^2, exogenous)
    D'   = v_l - v_f

Input ``F``: wheel force in newtons (``input_units = "newton"``), or ``F / (M g)``
(``"normalized"``, dimensionless). CLF ``V = (v_f - v_d)^2`` with rate ``lam``; CBF
``h = D - tau v_f`` (m) with rate ``beta``. The lead acceleration is known to the simulator
but not part of ``f``: it does not enter ``a, b, c, d`` because neither ``V`` nor ``h``
depends on ``v_l``. With ``certificates.barrier = "braking"`` the CBF is the braking-distance
barrier of :mod:`~safestab.scenarios.acc_braking`, which does depend on ``v_l``: the
controllers then act on the model with the lead braking as hard as it may
(:meth:`ACCScenario.controller_system`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp

from ..certificates import CBF, CLF, LieTerms
from ..errors import ParameterError, ScenarioError
from ..systems import ControlAffineSystem
from ._acc_schema import LIMITS, ScenarioLimits, check_structure, check_values
from ._mc_schema import MonteCarloSpec, check_montecarlo
from ._schema import LEARNING_KEYS, load_flat
from .acc_braking import braking_barrier, braking_lie_terms, check_lead_bound, worst_lead
from .trial_studies import ACCTrials

__all__ = [
    "ACCScenario", "MonteCarloSpec", "load_scenario", "PRESETS", "LIMITS", "ScenarioLimits",
]  # fmt: skip

PRESETS = ("paper", "stress", "stress-ood", "paper-limited", "stress-limited")


@dataclasses.dataclass(frozen=True)
class Drag:
    """Rolling and aerodynamic resistance ``F_r = f0 + f1 v + f2 v^2`` (N, N s/m, N s^2/m^2)."""

    f0: float
    f1: float
    f2: float


@dataclasses.dataclass(frozen=True)
class ACCScenario:
    """All parameters of one ACC study; built from a TOML file by :func:`load_scenario`.

    Units: masses kg, speeds m/s, distances m, times s, forces N. Every field is checked
    when the object is made (by the loader, the constructor or :meth:`replace`), with the
    bounds of docs/acc.md ("Scenario files") and :data:`LIMITS`.

    Raises
    ------
    ScenarioError
        If a field has the wrong type, is not finite or is out of range; the message names
        the key with its table path as in the TOML file (``learning.seed``), what was
        received and what was expected.
    """

    name: str
    mass: float  # kg
    gravity: float  # m/s^2
    drag_true: Drag
    drag_nominal: Drag
    v_f0: float  # m/s
    v_l0: float  # m/s
    D0: float  # m
    lead_profile: tuple[tuple[float, float], ...]  # (end time s, acceleration m/s^2)
    v_d: float  # m/s
    tau: float  # s
    lam: float  # 1/s
    beta: float  # 1/s
    kappa: float
    rho: float
    phi: float
    varphi: float
    slack_weight: float
    input_units: str  # "newton" | "normalized"
    input_limit: float | None  # fraction of M g, or None for no limits
    t_final: float  # s
    dt: float  # s
    n_samples: int
    sample_rate: float  # Hz
    sample_horizon: float  # s
    noise_std: float  # m/s^2
    gp_beta: float
    kernel: str
    x0_low: tuple[float, ...]  # (v_f, v_l, D)
    x0_high: tuple[float, ...]
    excitation_limit: float  # fraction of M g spanned by the excitation
    hyper_subset: int  # rows used to fit GP hyperparameters (then conditioned on all)
    seed: int
    #: ``learning.n_inducing`` (optional): 0 (the default) puts the exact GP in the
    #: GP-robust controller; ``M > 0`` its FastGP cache of at most ``M`` inducing inputs
    #: per component, whose band contains the exact band (docs/learning.md).
    n_inducing: int = 0
    #: ``certificates.barrier`` (optional): ``"headway"`` (the paper's ``D - tau v_f``, the
    #: default) or ``"braking"`` (valid under ``input_limit``; docs/acc.md).
    barrier: str = "headway"
    #: ``certificates.lead_decel``: the lead's largest deceleration (fraction of g) that the
    #: braking barrier is valid for; None with the headway barrier.
    lead_decel: float | None = None
    #: The optional ``[montecarlo]`` table (trial distributions); ``None`` when absent.
    montecarlo: MonteCarloSpec | None = None

    def __post_init__(self) -> None:
        check_values(_flatten(self), f"scenario {self.name!r}")
        if self.montecarlo is not None and not isinstance(self.montecarlo, MonteCarloSpec):
            raise ScenarioError(
                f"scenario {self.name!r}: montecarlo must be a MonteCarloSpec or None, got "
                f"{type(self.montecarlo).__name__}"
            )
        check_lead_bound(self, self.montecarlo, f"scenario {self.name!r}", ScenarioError)

    def replace(self, **changes: Any) -> ACCScenario:
        """A copy with some fields changed, checked like a loaded file.

        Parameters
        ----------
        **changes
            Field names and new values, e.g. ``seed=3, n_samples=200, t_final=5.0``.

        Raises
        ------
        ScenarioError
            If a new value is invalid (the message names its TOML key).
        """
        return dataclasses.replace(self, **changes)

    # -- model ------------------------------------------------------------------------

    @property
    def input_scale(self) -> float:
        """Newtons per input unit: 1 for ``"newton"``, ``M g`` for ``"normalized"``."""
        return 1.0 if self.input_units == "newton" else self.mass * self.gravity

    def _drag(self, which: str) -> Drag:
        if which not in ("true", "nominal"):
            raise ParameterError(f"which must be 'true' or 'nominal', got {which!r}")
        return self.drag_true if which == "true" else self.drag_nominal

    def system(self, which: str = "true") -> ControlAffineSystem:
        """The ACC model with the ``"true"`` or ``"nominal"`` drag coefficients.

        Raises
        ------
        ParameterError
            If ``which`` is neither.
        """
        p = self.model_params(which)
        return ControlAffineSystem(
            lambda x: self._drift(x, p), lambda x: self._input_matrix(), 3, name=f"acc-{which}"
        )

    def _drift(self, x: Any, p: Any) -> Any:
        """``f(x)`` with the drag coefficients ``p`` (``{"f0", "f1", "f2"}``): both models'."""
        fr = p["f0"] + p["f1"] * x[0] + p["f2"] * x[0] ** 2
        return jnp.array([-fr / self.mass, 0.0, x[1] - x[0]])

    def _input_matrix(self) -> Any:
        """``g``, (3, 1): the input acts on the follower's acceleration only."""
        return jnp.array([[self.input_scale / self.mass], [0.0], [0.0]])

    def model_family(self) -> ControlAffineSystem:
        """The ``"true"`` and ``"nominal"`` models as one system with run-time parameters.

        The drag coefficients are the parameters (``{"f0", "f1", "f2"}``; :meth:`system`
        binds them, with the same function): with :meth:`model_params` it is either model, to
        the last bit. The study's true-model and mismatched-model controllers are built on
        it, so that they are one program with other data (:func:`~safestab.simulate` reuses the
        first's compiled loop for the second) instead of two.
        """
        example = {"f0": 1.0, "f1": 1.0, "f2": 1.0}
        return ControlAffineSystem(
            self._drift, lambda x, p: self._input_matrix(), 3, name="acc-model", params=example
        )

    def model_params(self, which: str) -> dict[str, float]:
        """The parameters of :meth:`model_family` that make it the ``which`` model.

        Raises
        ------
        ParameterError
            If ``which`` is neither ``"true"`` nor ``"nominal"``.
        """
        drag = self._drag(which)
        return {"f0": drag.f0, "f1": drag.f1, "f2": drag.f2}

    def certificates(self) -> tuple[CLF, CBF]:
        """CLF ``(v_f - v_d)^2`` and CBF ``D - tau v_f`` (or the braking-distance barrier)."""
        v_d, tau = self.v_d, self.tau
        clf = CLF(lambda x: (x[0] - v_d) ** 2, lam=self.lam)
        if self.barrier == "braking":
            g = self.gravity
            h = braking_barrier(tau, self.input_limit * g, self.lead_decel * g)
            return clf, CBF(h, beta=self.beta)
        return clf, CBF(lambda x: x[2] - tau * x[0], beta=self.beta)

    def controller_system(self, system: ControlAffineSystem) -> ControlAffineSystem:
        """The model a controller acts on: ``system`` itself, or with the worst lead.

        With the braking barrier, ``h`` depends on ``v_l`` and the lead's acceleration, which
        no controller knows, moves it: the controllers' model adds ``(0, -lead_decel g, 0)``
        (the lead braking as hard as it may), so their condition holds for every admissible
        lead (docs/acc.md). The plant and the data collection keep ``system``.
        """
        if self.barrier != "braking":
            return system
        return system.with_disturbance(
            worst_lead(self.lead_decel * self.gravity), name=f"{system.name}+worst-lead"
        )

    def hand_lie_terms(self, x: Any, which: str = "true") -> LieTerms:
        """The Lie terms written out by hand (with the corrections listed in docs/acc.md).

        ``a = -2 (v_f - v_d) F_r/M + lam V``, ``b = 2 (v_f - v_d) k/M``,
        ``c = v_l - v_f + tau F_r/M + beta h``, ``d = -tau k/M`` with ``k`` the input scale.
        The paper prints an extra factor ``F_r`` in ``b`` and writes ``b, d`` as 3-vectors.
        With the braking barrier, ``c`` and ``d`` are those of the worst-lead model
        (:func:`~safestab.scenarios.acc_braking.braking_lie_terms`).
        """
        drag = self._drag(which)
        x = jnp.asarray(x, dtype=float)
        vf, vl, D = x[..., 0], x[..., 1], x[..., 2]
        fr = drag.f0 + drag.f1 * vf + drag.f2 * vf**2
        M, k = self.mass, self.input_scale
        V = (vf - self.v_d) ** 2
        h = D - self.tau * vf
        a = -2 * (vf - self.v_d) * fr / M + self.lam * V
        b = (2 * (vf - self.v_d) * k / M)[..., None]
        c = vl - vf + self.tau * fr / M + self.beta * h
        d = jnp.broadcast_to(-self.tau * k / M, vf.shape)[..., None]
        if self.barrier == "braking":
            c, d = braking_lie_terms(self, x, drag)
            d = d[..., None]
        return LieTerms(a, b, c, d)

    def lead_acceleration(self, t: Any) -> Any:
        """``a_L(t)`` from the piecewise-constant profile, m/s^2 (0 after the last segment)."""
        t = jnp.asarray(t, dtype=float)
        out = jnp.zeros_like(t)
        start = 0.0
        for end, acc in self.lead_profile:
            # the paper's first segment is t <= 8 s; later ones are (start, end]
            inside = (t > start) & (t <= end) if start > 0 else (t <= end)
            out = jnp.where(inside, acc, out)
            start = end
        return out

    def exogenous(self, t: Any) -> Any:
        """The known term ``e(t) = (0, a_L(t), 0)`` of the true dynamics."""
        return jnp.array([0.0, 1.0, 0.0]) * self.lead_acceleration(t)

    def omega(self, x: Any) -> Any:
        """The true model error ``omega(x) = f_true(x) - f_nominal(x)`` (m/s^2 in v_f)."""
        x = jnp.asarray(x, dtype=float)
        vf = x[..., 0]
        dt, dn = self.drag_true, self.drag_nominal
        d0, d1, d2 = dt.f0 - dn.f0, dt.f1 - dn.f1, dt.f2 - dn.f2
        w = -(d0 + d1 * vf + d2 * vf**2) / self.mass
        return jnp.stack([w, jnp.zeros_like(w), jnp.zeros_like(w)], -1)

    def trial_study(self, spec: MonteCarloSpec | None = None) -> Any:
        """The Monte Carlo trial study of this scenario (:class:`~.trials.ACCTrials`).

        ``spec`` defaults to the scenario's ``[montecarlo]`` table, else the defaults.
        """
        return ACCTrials(self, spec or self.montecarlo or MonteCarloSpec())

    @property
    def x0(self) -> tuple[float, float, float]:
        """Initial state ``(v_f, v_l, D)``."""
        return (self.v_f0, self.v_l0, self.D0)

    def input_limits(self) -> tuple[list[float], list[float]] | tuple[None, None]:
        """``(u_min, u_max)`` in input units, or ``(None, None)``."""
        if self.input_limit is None:
            return None, None
        lim = self.input_limit * self.mass * self.gravity / self.input_scale
        return [-lim], [lim]


# -- TOML -------------------------------------------------------------------------------

# dataclass field -> TOML key, for the fields stored as they are in the file
_KEYS = {
    "mass": "vehicle.mass",
    "gravity": "vehicle.gravity",
    "v_f0": "initial.v_f",
    "v_l0": "initial.v_l",
    "D0": "initial.D",
    "lead_profile": "lead.profile",
    **{k: f"certificates.{k}" for k in ("v_d", "tau", "lam", "beta", "barrier", "lead_decel")},
    **{
        k: f"controller.{k}"
        for k in ("kappa", "rho", "phi", "varphi", "slack_weight", "input_units", "input_limit")
    },
    **{k: f"simulation.{k}" for k in ("t_final", "dt")},
    **{k: f"learning.{k}" for k in (*LEARNING_KEYS, "n_inducing")},
}


def _flatten(sc: ACCScenario) -> dict[str, Any]:
    """The scenario as ``{"table.key": value}``, the form the schema checks."""
    flat = {key: getattr(sc, attr) for attr, key in _KEYS.items()}
    flat["name"] = sc.name
    for which in ("true", "nominal"):
        drag = getattr(sc, f"drag_{which}")
        for k in ("f0", "f1", "f2"):
            flat[f"drag.{which}.{k}"] = getattr(drag, k)
    return flat


def _build(v: dict[str, Any], montecarlo: MonteCarloSpec | None = None) -> ACCScenario:
    fields = {attr: v[key] for attr, key in _KEYS.items()}
    drag = {
        which: Drag(*(v[f"drag.{which}.{k}"] for k in ("f0", "f1", "f2")))
        for which in ("true", "nominal")
    }
    return ACCScenario(
        name=v["name"],
        drag_true=drag["true"],
        drag_nominal=drag["nominal"],
        montecarlo=montecarlo,
        **fields,
    )


def load_scenario(
    name_or_path: str | Path, *, overrides: Mapping[str, Any] | None = None
) -> ACCScenario:
    """Load a preset by name (:data:`PRESETS`) or a TOML file by path.

    Every key is checked for type, finiteness and range here, before any data collection,
    GP fit or simulation (bounds in docs/acc.md, "Scenario files", and :data:`LIMITS`).
    ``name`` is optional and defaults to the preset name or the file's stem; ``kind``
    is optional and must be ``"acc"`` when present.

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"table.key": value}`` set in the document before it is checked (the command
        line's ``--set``); checked exactly like the file's own values.

    Raises
    ------
    ScenarioError
        If the file does not exist, cannot be read, is not UTF-8, is not valid TOML, or a key
        or table is missing, unknown (sub-tables included), of the wrong type, not finite or
        out of range. The message names the file and the key with its table path, what was
        received and what was expected.
    """
    flat, table, source = load_flat(
        name_or_path, PRESETS, __package__, check_structure, overrides,
        defaults={"learning.n_inducing": 0, "certificates.barrier": "headway",
                  "certificates.lead_decel": None},
    )  # fmt: skip
    values = check_values(flat, source)
    spec = None if table is None else check_montecarlo(table, source)
    return _build(values, spec)
