"""Result types of the formulas: regions, compatibility cases, outputs and certificates."""

from __future__ import annotations

import dataclasses
from enum import IntEnum

import jax

__all__ = [
    "Region",
    "CompatibilityCase",
    "FormulaResult",
    "Compatibility",
    "KKTResiduals",
    "ConditionFlags",
]

Array = jax.Array


class Region(IntEnum):
    """Which case of the combined formula applied at a point (Theorem 1, eq. (8)).

    ``INCOMPATIBLE`` means no input satisfies both conditions (the QP is infeasible); the
    formula then returns the documented safety-first fallback.
    """

    INCOMPATIBLE = 0
    P1 = 1  #: only the CLF condition is active: u = -A / |b|^2 b
    P2 = 2  #: only the CBF condition is active: u = B / |d|^2 d
    P3 = 3  #: both are active: u = -lambda1 b + lambda2 d
    P4 = 4  #: neither is active: u = 0


class CompatibilityCase(IntEnum):
    """Why the CLF and CBF conditions are (positive values) or are not (negative) compatible.

    Lemma 1 of the paper assumes ``b != 0`` and ``d != 0``; the zero cases are added here.
    """

    NOT_PARALLEL = 1  #: Lemma 1 case (i): the two hyperplanes intersect
    PARALLEL_ORDERED = 2  #: b, d point the same way and the half-spaces overlap (v <= 0)
    ANTIPARALLEL = 3  #: b, d point opposite ways: both half-spaces contain a common ray
    B_ZERO = 4  #: b = 0 and A <= 0: the CLF condition holds for every input
    D_ZERO = 5  #: d = 0 and B <= 0: the CBF condition holds for every input
    INCOMPATIBLE_PARALLEL = -1  #: b, d point the same way and the half-spaces are disjoint
    INCOMPATIBLE_B_ZERO = -2  #: b = 0 and A > 0: no input satisfies the CLF condition
    INCOMPATIBLE_D_ZERO = -3  #: d = 0 and B > 0: no input satisfies the CBF condition


@dataclasses.dataclass(frozen=True)
class FormulaResult:
    """Output of :func:`clf_cbf` and :func:`clf_cbf_relaxed`.

    Unpacks as a pair: ``u, region = clf_cbf(...)``.

    Attributes
    ----------
    u : array of shape (..., m)
        The input.
    region : int array of shape (...,)
        A :class:`Region` value per point.
    multipliers : array of shape (..., 2)
        KKT multipliers ``(lambda1, lambda2)`` of the CLF and CBF constraints; at an
        ``INCOMPATIBLE`` point, those of the fallback problem.
    slack : array of shape (...,)
        The CLF slack ``chi`` (zero for :func:`clf_cbf`).
    """

    u: Array
    region: Array
    multipliers: Array
    slack: Array

    def __iter__(self):  # noqa: D105 - allows ``u, region = result``
        return iter((self.u, self.region))


jax.tree_util.register_dataclass(
    FormulaResult, data_fields=["u", "region", "multipliers", "slack"], meta_fields=[]
)


@dataclasses.dataclass(frozen=True)
class Compatibility:
    """Output of :func:`compatibility`.

    Attributes
    ----------
    compatible : bool array of shape (...,)
        Whether some input satisfies both conditions.
    case : int array of shape (...,)
        A :class:`CompatibilityCase` value per point.
    """

    compatible: Array
    case: Array


jax.tree_util.register_dataclass(Compatibility, data_fields=["compatible", "case"], meta_fields=[])


@dataclasses.dataclass(frozen=True)
class KKTResiduals:
    """Residuals of the KKT conditions of a formula's QP, per point (all >= 0).

    Attributes
    ----------
    clf_violation : array of shape (...,)
        ``max(0, b u + A - chi)``.
    cbf_violation : array of shape (...,)
        ``max(0, B - d u)``.
    dual_violation : array of shape (...,)
        ``max(0, -lambda1) + max(0, -lambda2)``.
    complementarity : array of shape (...,)
        ``|lambda1 (b u + A - chi)| + |lambda2 (d u - B)|``.
    stationarity : array of shape (...,)
        ``|u + lambda1 b - lambda2 d| + |slack_weight chi - lambda1|`` (second term relaxed only).
    """

    clf_violation: Array
    cbf_violation: Array
    dual_violation: Array
    complementarity: Array
    stationarity: Array


jax.tree_util.register_dataclass(
    KKTResiduals,
    data_fields=[
        "clf_violation",
        "cbf_violation",
        "dual_violation",
        "complementarity",
        "stationarity",
    ],
    meta_fields=[],
)


@dataclasses.dataclass(frozen=True)
class ConditionFlags:
    """Output of :func:`~safestab.formulas.conditions_satisfied`.

    Attributes
    ----------
    clf_satisfied : bool array of shape (...,)
        ``a + b.u + kappa zeta <= rtol (|a| + kappa zeta + sum_i |b_i u_i|)``.
    cbf_satisfied : bool array of shape (...,)
        ``c + d.u - rho Gamma >= -rtol (|c| + rho Gamma + sum_i |d_i u_i|)``.
    """

    clf_satisfied: Array
    cbf_satisfied: Array


jax.tree_util.register_dataclass(
    ConditionFlags, data_fields=["clf_satisfied", "cbf_satisfied"], meta_fields=[]
)
