"""The smooth closed-form safety filters around a nominal input, for one barrier.

Cohen, Ong, Bahati and Ames, "Characterizing smooth safety filters via the implicit function
theorem" (IEEE L-CSS, 2023) describe a family of filters of one CBF

    u = u_nom + lambda(c', |d|^2) d,      c' = c + d.u_nom - |d|^2 / epsilon,

with ``c = L_f h + alpha(h)``, ``d = L_g h`` and ``c'`` the CBF condition at the nominal input
(``epsilon > 0``: the input-to-state-safe variant, which asks ``c + d.u >= |d|^2 / epsilon``
more; ``epsilon = inf`` for none). Each ``lambda`` makes ``c + d.u = c' + lambda |d|^2 >= 0``:

* ``ExplicitFilter``: ``lambda = max(0, -c') / |d|^2``, the CBF-QP's exact optimum (the
  minimal change of ``u_nom``), not smooth where ``c' = 0``;
* ``SontagFilter(sigma)``: ``lambda = (-c' + sqrt(c'^2 + sigma |d|^4)) / |d|^2``;
* ``HalfSontagFilter(sigma)``: half of Sontag's;
* ``SoftplusFilter(sigma)``: ``lambda = sigma log(1 + exp(-c' / (sigma |d|^2)))``;

each 0 where ``d = 0``. The smooth ones approach the QP as ``sigma -> 0`` and are smooth in
the state; ``sigma`` has the source's meaning (its ``sqrt(a^2 + sigma b^2)`` with ``a = c'``
and ``b = |d|^2``). They are what a :class:`~safestab.SafetyFilter` with one CBF, no CLF and
no limits takes as ``formula=``; its default, the exact QP of
:func:`~safestab.formulas.clf_cbf_multi`, remains the only choice for several rows.

The paper's own CBF formula, eq. (6), is ``u = (rho Gamma - c) / |d|^2 d`` with ``Gamma =
sqrt(c^2 + varphi |d|^4)``: Sontag's form on the raw ``c`` (no nominal input), which
``UniversalController(system, None, cbf, formula="cbf")`` computes. A ``SafetyFilter`` with
``rho > 0`` solves the QP with the tightened condition ``c + d.u >= rho Gamma(c, d)``, Gamma
taken on the raw ``c``, not on ``c'``: not a member of this family.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import jax.numpy as jnp

from ..errors import ParameterError
from .multi import MultiResult, MultiStatus
from .problem import Formula, Problem, register_formula

__all__ = [
    "SmoothFilter",
    "ExplicitFilter",
    "SontagFilter",
    "HalfSontagFilter",
    "SoftplusFilter",
]


def _check(name: str, value: float, *, positive: bool, allow_inf: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {value!r}") from None
    if math.isnan(v) or (math.isinf(v) and not allow_inf) or (v <= 0 if positive else v < 0):
        want = "> 0" if positive else ">= 0"
        raise ParameterError(f"{name} must be a {'' if allow_inf else 'finite '}number {want}, "
                             f"got {value!r}")  # fmt: skip
    return v


@dataclasses.dataclass(frozen=True)
class SmoothFilter(Formula):
    """Base of the one-barrier filters ``u = u_nom + lambda(c', |d|^2) d`` (module notes).

    Attributes
    ----------
    epsilon : float
        ``> 0``: the input-to-state-safe variant, ``c' = c + d.u_nom - |d|^2 / epsilon``;
        ``inf`` (default): none.
    """

    epsilon: float = dataclasses.field(default=math.inf, kw_only=True)
    uses: ClassVar[tuple[str, ...]] = ("u_nom",)

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "epsilon", _check("epsilon", self.epsilon, positive=True, allow_inf=True)
        )

    def lam(self, a: Any, bb: Any) -> Any:
        """``lambda(c', |d|^2)`` for ``|d|^2 > 0`` (``bb`` replaced by 1 where it is 0)."""
        raise NotImplementedError

    def solve(self, problem: Problem) -> MultiResult:
        """The filter's input for ``problem`` (one CBF row; ``u_nom`` 0 where not given)."""
        self._check_fields(problem)
        c, d = problem.c[..., 0], problem.d[..., 0, :]
        u_nom = jnp.zeros_like(d) if problem.u_nom is None else problem.u_nom
        bb = jnp.sum(d * d, -1)
        on = bb > 0
        safe_bb = jnp.where(on, bb, 1.0)
        a = c + jnp.sum(d * u_nom, -1)
        if not math.isinf(self.epsilon):
            a = a - bb / self.epsilon
        lam = jnp.where(on, self.lam(a, safe_bb), 0.0)
        u = u_nom + lam[..., None] * d
        zeros = jnp.zeros(lam.shape + (0,))
        return MultiResult(
            u=u,
            status=jnp.full(lam.shape, MultiStatus.SOLVED, jnp.int32),
            active=(lam > 0)[..., None],
            multipliers=lam[..., None],
            slack=zeros,
        )


@register_formula
@dataclasses.dataclass(frozen=True)
class ExplicitFilter(SmoothFilter):
    """``lambda = max(0, -c') / |d|^2``: the CBF-QP's optimum in closed form."""

    def lam(self, a: Any, bb: Any) -> Any:
        """The QP's multiplier."""
        return jnp.maximum(-a, 0.0) / bb


@dataclasses.dataclass(frozen=True)
class _Smoothed(SmoothFilter):
    """A smooth law: its smoothing parameter ``sigma > 0`` (the QP as ``sigma -> 0``)."""

    sigma: float = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "sigma", _check("sigma", self.sigma, positive=True))


@register_formula
@dataclasses.dataclass(frozen=True)
class SontagFilter(_Smoothed):
    """``lambda = (-c' + sqrt(c'^2 + sigma |d|^4)) / |d|^2`` (``sigma > 0``)."""

    def lam(self, a: Any, bb: Any) -> Any:
        """Sontag's multiplier, written without cancellation where ``c' > 0``."""
        root = jnp.sqrt(a * a + self.sigma * bb * bb)
        # -a + root = sigma bb^2 / (a + root) where a > 0 (no cancellation)
        return jnp.where(a > 0, self.sigma * bb / (a + root), (root - a) / bb)


@register_formula
@dataclasses.dataclass(frozen=True)
class HalfSontagFilter(SontagFilter):
    """Half of Sontag's multiplier (``sigma > 0``)."""

    def lam(self, a: Any, bb: Any) -> Any:
        """Half Sontag's multiplier."""
        return 0.5 * super().lam(a, bb)


@register_formula
@dataclasses.dataclass(frozen=True)
class SoftplusFilter(_Smoothed):
    """``lambda = sigma log(1 + exp(-c' / (sigma |d|^2)))`` (``sigma > 0``)."""

    def lam(self, a: Any, bb: Any) -> Any:
        """The softplus multiplier, by ``logaddexp`` (no overflow for large ``-c'``)."""
        return self.sigma * jnp.logaddexp(0.0, -a / (self.sigma * bb))
