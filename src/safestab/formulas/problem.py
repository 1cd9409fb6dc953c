"""The formulas as values: a frozen problem of terms and parameters, and one ``solve`` each.

A :class:`Problem` holds the Lie terms ``(a, b, c, d)`` of one call (batched over leading
axes) and the parameters the formulas read: ``kappa``, ``rho``, ``phi``, ``varphi``, the CLF
slack weight, a CBF margin, input limits, a nominal input and an objective weight. A formula
object holds only its settings (a tolerance, an iteration bound) and maps a problem to its
result with :meth:`Formula.solve`:

==========================  ====================================================  ==========
formula                     solves                                                result
==========================  ====================================================  ==========
:class:`SontagFormula`      Sontag's CLF formula, eq. (3)                         FormulaResult
:class:`CBFFormula`         the CBF formula, eq. (6)                              FormulaResult
:class:`CombinedFormula`    the CLF-CBF QP, Theorem 1                             FormulaResult
:class:`RelaxedFormula`     the relaxed QP with slack weight, Theorem 3           FormulaResult
:class:`MultiFormula`       several CLFs and CBFs, limits inside, ``u_nom``, H    MultiResult
==========================  ====================================================  ==========

Both are pytrees (the problem's fields are leaves, a formula's settings static), so a
controller holding a formula stays a JAX value, and ``solve`` is unchecked and jittable: the
checked public functions (:func:`~safestab.formulas.clf_cbf` and the others) check their
arguments and solve the same way.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp

from .._numerics import inv_sqrt
from ..errors import ParameterError
from ._dual_active_set import UNIT_DOUBLE, UNIT_FLOAT
from ._kernels import (
    DEFAULT_PARALLEL_RTOL,
    Margins,
    cbf_only,
    kkt,
    margins,
    solve_two,
    sontag,
)
from .multi import MultiResult, multi_kernel
from .results import FormulaResult, KKTResiduals, Region

__all__ = [
    "Problem",
    "Formula",
    "SontagFormula",
    "CBFFormula",
    "CombinedFormula",
    "RelaxedFormula",
    "MultiFormula",
    "register_formula",
]

#: The unit roundoff of each precision a step may be evaluated in.
UNITS = {"double": UNIT_DOUBLE, "float": UNIT_FLOAT}


@dataclasses.dataclass(frozen=True)
class Problem:
    """The Lie terms and parameters of one formula call, batched over leading axes.

    Attributes
    ----------
    a, b, c, d : arrays
        One CLF and one CBF: shapes (...,), (..., m), (...,), (..., m). Several rows
        (:class:`MultiFormula`): (..., p), (..., p, m), (..., k), (..., k, m).
    kappa, rho, phi, varphi : float or array
        As for :func:`~safestab.formulas.clf_cbf` (broadcast against the batch).
    slack_weight : float or array, optional
        The CLF slack weight (Theorem 3's ``m``): used by :class:`RelaxedFormula` and, for
        soft CLF rows, :class:`MultiFormula`.
    cbf_margin : float, optional
        A tightening of the CBF condition, ``c + d.u >= rho Gamma + cbf_margin``, in the
        units of ``dh/dt`` (single pair).
    u_min, u_max : arrays of shape (..., m), optional
        Input limits inside the problem (:class:`MultiFormula`).
    u_nom : array of shape (..., m), optional
        Nominal input of the objective ``1/2 |u - u_nom|_H^2`` (:class:`MultiFormula`).
    H : array of shape (..., m, m), optional
        Objective weight (:class:`MultiFormula`).
    """

    a: Any
    b: Any
    c: Any
    d: Any
    kappa: Any = 0.0
    rho: Any = 0.0
    phi: Any = 0.0
    varphi: Any = 0.0
    slack_weight: Any = None
    cbf_margin: Any = None
    u_min: Any = None
    u_max: Any = None
    u_nom: Any = None
    H: Any = None

    def replace(self, **changes: Any) -> Problem:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def margins(self) -> Margins:
        """The single pair's margins ``A``, ``B`` (with the CBF margin), ``zeta``, ``Gamma``."""
        mg = margins(self.a, self.b, self.c, self.d, self.kappa, self.rho, self.phi, self.varphi)
        if self.cbf_margin is not None:
            mg = mg._replace(B=mg.B + self.cbf_margin)
        return mg


jax.tree_util.register_dataclass(
    Problem, data_fields=[f.name for f in dataclasses.fields(Problem)], meta_fields=[]
)


#: The problem's optional fields (None when absent): each formula names those it reads.
_OPTIONAL = tuple(f.name for f in dataclasses.fields(Problem) if f.default is None)


class Formula:
    """A closed form over a :class:`Problem`; subclasses hold only static settings."""

    #: The problem's optional fields this formula reads (others must be None).
    uses: ClassVar[tuple[str, ...]] = ()

    def solve(self, problem: Problem) -> Any:
        """The formula's result for ``problem`` (unchecked, jittable)."""
        raise NotImplementedError

    def _check_fields(self, problem: Problem) -> None:
        extra = [f for f in _OPTIONAL if getattr(problem, f) is not None and f not in self.uses]
        if extra:
            raise ParameterError(
                f"{type(self).__name__} does not use {', '.join(extra)}; "
                f"it reads {', '.join(self.uses) or 'none of the optional fields'}"
            )


def register_formula(cls: type) -> type:
    """A frozen dataclass formula as a pytree without leaves (its settings are static)."""
    fields = [f.name for f in dataclasses.fields(cls)]
    jax.tree_util.register_dataclass(cls, data_fields=[], meta_fields=fields)
    return cls


def _one_condition(u: Any, margin: Any, norm: Any, region: int, which: int) -> FormulaResult:
    """The result of a one-condition formula: ``u = margin / |v|^2 v`` up to the sign.

    ``which``: the multiplier's index (0 for the CLF, 1 for the CBF); ``region`` where
    ``|v| > 0``, P4 elsewhere.
    """
    on = norm > 0
    lam = jnp.where(on, margin / jnp.where(on, norm, 1.0) ** 2, 0.0)
    pair = [jnp.zeros_like(lam), jnp.zeros_like(lam)]
    pair[which] = lam
    return FormulaResult(
        u=u,
        region=jnp.where(on, region, Region.P4).astype(jnp.int32),
        multipliers=jnp.stack(pair, -1),
        slack=jnp.zeros_like(margin),
    )


def _residuals(problem: Problem, result: FormulaResult, slack_weight: Any) -> KKTResiduals:
    mg = problem.margins()
    r = kkt(problem.b, problem.d, mg.A, mg.B, result.u, result.multipliers, result.slack,
            slack_weight)  # fmt: skip
    return KKTResiduals(*r)


def _result(sol: Any) -> FormulaResult:
    return FormulaResult(u=sol.u, region=sol.region, multipliers=sol.multipliers, slack=sol.slack)


@register_formula
@dataclasses.dataclass(frozen=True)
class SontagFormula(Formula):
    """Sontag's CLF formula, eq. (3): ``u = -A / |b|^2 b`` (region P1; P4 where ``b = 0``).

    The result's multipliers are ``(A / |b|^2, 0)`` (``u = -lambda1 b``), its slack 0.
    """

    uses: ClassVar[tuple[str, ...]] = ("cbf_margin",)

    def solve(self, problem: Problem) -> FormulaResult:
        """Sontag's input for ``problem`` (the CBF side is not used)."""
        self._check_fields(problem)
        mg = problem.margins()
        return _one_condition(sontag(mg.A, problem.b, mg.nb), mg.A, mg.nb, Region.P1, 0)


@register_formula
@dataclasses.dataclass(frozen=True)
class CBFFormula(Formula):
    """The CBF formula, eq. (6): ``u = B / |d|^2 d`` (region P2; P4 where ``d = 0``).

    The result's multipliers are ``(0, B / |d|^2)``, its slack 0.
    """

    uses: ClassVar[tuple[str, ...]] = ("cbf_margin",)

    def solve(self, problem: Problem) -> FormulaResult:
        """The CBF formula's input for ``problem`` (the CLF side is not used)."""
        self._check_fields(problem)
        mg = problem.margins()
        return _one_condition(cbf_only(mg.B, problem.d, mg.nd), mg.B, mg.nd, Region.P2, 1)


@register_formula
@dataclasses.dataclass(frozen=True)
class CombinedFormula(Formula):
    """The combined CLF-CBF formula, Theorem 1 (the exact QP optimum, with its fallback).

    Attributes
    ----------
    parallel_rtol : float
        Tolerance of the parallel test (see :func:`~safestab.formulas.clf_cbf`).
    """

    parallel_rtol: float = DEFAULT_PARALLEL_RTOL
    uses: ClassVar[tuple[str, ...]] = ("cbf_margin",)

    def solve(self, problem: Problem) -> FormulaResult:
        """The QP optimum for ``problem``; region ``INCOMPATIBLE`` where none exists."""
        return _result(self.solution(problem))

    def residuals(self, problem: Problem, result: FormulaResult) -> KKTResiduals:
        """The KKT residuals of ``result`` for this QP: all 0 (to rounding) certify it optimal.

        Unchecked; :func:`~safestab.formulas.kkt_residuals` is the checked form that takes the
        terms instead of the problem.
        """
        self._check_fields(problem)
        return _residuals(problem, result, None)

    def solution(self, problem: Problem) -> Any:
        """The two-constraint solution with the compatibility case (``.case``) of Lemma 1."""
        self._check_fields(problem)
        mg = problem.margins()
        return solve_two(
            mg.A, mg.B, problem.b, problem.d, mg.nb, mg.nd, parallel_rtol=self.parallel_rtol
        )


@register_formula
@dataclasses.dataclass(frozen=True)
class RelaxedFormula(Formula):
    """The relaxed formula, Theorem 3: the CLF condition softened by a slack of weight m.

    The weight is the problem's ``slack_weight`` (a pytree leaf of the controller, so it can
    be tuned by gradient).
    """

    uses: ClassVar[tuple[str, ...]] = ("slack_weight", "cbf_margin")

    def solve(self, problem: Problem) -> FormulaResult:
        """The relaxed QP's optimum for ``problem`` (always feasible)."""
        self._check_fields(problem)
        if problem.slack_weight is None:
            raise ParameterError("RelaxedFormula needs the problem's slack_weight")
        mg = problem.margins()
        s = inv_sqrt(problem.slack_weight)  # 1 / sqrt(m)
        return _result(solve_two(mg.A, mg.B, problem.b, problem.d, mg.nb, mg.nd, inv_sqrt_slack=s))

    def residuals(self, problem: Problem, result: FormulaResult) -> KKTResiduals:
        """The KKT residuals of ``result`` for the relaxed QP (its slack included)."""
        self._check_fields(problem)
        return _residuals(problem, result, problem.slack_weight)


@register_formula
@dataclasses.dataclass(frozen=True)
class MultiFormula(Formula):
    """Several CLFs and CBFs, limits inside the problem, a nominal input and a weight.

    The exact optimum by the dual active-set method of
    :func:`~safestab.formulas.clf_cbf_multi`, with its fallbacks (``MultiStatus``).

    Attributes
    ----------
    max_iter : int, optional
        Iteration bound of the active-set solver per phase (default from the problem's size).
    precision : {"double", "float"}
        The precision the step is evaluated in: it scales the solver's tolerances and its
        certificate to that precision's rounding (``"float"`` for a step exported in float;
        the JAX step still computes in float64, with float's tolerances).
    """

    max_iter: int | None = None
    precision: str = "double"
    uses: ClassVar[tuple[str, ...]] = (
        "slack_weight", "u_min", "u_max", "u_nom", "H", "cbf_margin",
    )  # fmt: skip

    def __post_init__(self) -> None:
        if self.precision not in UNITS:
            raise ParameterError(
                f"precision must be one of {sorted(UNITS)}, got {self.precision!r}"
            )

    @property
    def unit(self) -> float:
        """The unit roundoff of :attr:`precision`."""
        return UNITS[self.precision]

    def solve(self, problem: Problem) -> MultiResult:
        """The optimum for ``problem`` (rows on the axis before the input's)."""
        self._check_fields(problem)
        if (problem.u_min is None) != (problem.u_max is None):
            raise ParameterError("give both u_min and u_max, or neither")
        sw = problem.slack_weight
        inv = None if sw is None or problem.b.shape[-2] == 0 else inv_sqrt(sw)  # no CLF row
        return multi_kernel(
            problem.a, problem.b, problem.c, problem.d,
            problem.kappa, problem.rho, problem.phi, problem.varphi,
            inv, problem.u_min, problem.u_max, problem.u_nom, problem.H,
            max_iter=self.max_iter, unit=self.unit, cbf_margin=problem.cbf_margin,
        )  # fmt: skip
