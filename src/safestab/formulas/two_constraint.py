"""The combined CLF-CBF formula (Theorem 1) and its relaxed version (Theorem 3)."""

from __future__ import annotations

from typing import Any

import jax

from ._checks import as_float, check_lie_terms, check_output_finite, check_params
from ._kernels import DEFAULT_PARALLEL_RTOL
from .problem import CombinedFormula, Problem, RelaxedFormula
from .results import FormulaResult

__all__ = ["clf_cbf", "clf_cbf_relaxed"]


@jax.jit
def _clf_cbf_jit(a, b, c, d, kappa, rho, phi, varphi, parallel_rtol):
    return CombinedFormula(parallel_rtol).solve(Problem(a, b, c, d, kappa, rho, phi, varphi))


@jax.jit
def _clf_cbf_relaxed_jit(a, b, c, d, kappa, rho, phi, varphi, slack_weight):
    problem = Problem(a, b, c, d, kappa, rho, phi, varphi, slack_weight=slack_weight)
    return RelaxedFormula().solve(problem)


def _check_result(function: str, res: FormulaResult) -> None:
    check_output_finite(function, u=res.u, slack=res.slack, multipliers=res.multipliers)


def clf_cbf(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    parallel_rtol: float = DEFAULT_PARALLEL_RTOL,
) -> FormulaResult:
    """Combined CLF-CBF universal formula, Theorem 1, eq. (8) ``QP_Control_Law_relaxed``.

    Returns the exact minimiser of ``1/2 |u|^2`` subject to ``a + b u <= -kappa zeta`` and
    ``c + d u >= rho Gamma``, by cases:

    ======  ==============================  ===============================================
    region  condition                       u
    ======  ==============================  ===============================================
    P4      A <= 0 and B <= 0               0
    P1      A >= 0 and v <= 0               -A / |b|^2 b
    P2      B >= 0 and w <= 0               B / |d|^2 d
    P3      otherwise, b, d not parallel    B / |d|^2 d - w / (|b|^2|d|^2 - (b.d)^2) b_perp
    ======  ==============================  ===============================================

    with ``A = a + kappa zeta``, ``B = rho Gamma - c``, ``v = A b.d + B |b|^2``,
    ``w = A |d|^2 + B b.d`` and ``b_perp = |d|^2 b - (b.d) d`` (the part of ``b`` orthogonal
    to ``d``, times ``|d|^2``); the first matching row wins. P3 is the paper's
    ``-lambda1 b + lambda2 d`` with ``lambda1 = w/det``, ``lambda2 = v/det``, written in an
    orthogonal basis so that it does not cancel when ``b`` and ``d`` are nearly parallel.

    Parameters
    ----------
    a, c : arrays of shape (...,)
        ``L_f V + lambda V`` and ``L_f h + beta h``.
    b, d : arrays of shape (..., m)
        ``L_g V`` and ``L_g h``.
    kappa, rho : float or array broadcastable to the batch shape (...,)
        >= 0.
    phi, varphi : float or array broadcastable to (...,)
        >= 0.
    parallel_rtol : float, optional
        Relative tolerance of the parallel test (see :data:`DEFAULT_PARALLEL_RTOL`).

    Returns
    -------
    FormulaResult
        ``u`` of shape (..., m), ``region`` of shape (...,), multipliers and a zero slack.
        Unpacks as ``u, region``.

    Raises
    ------
    InputTypeError
        If a term or parameter is bool, complex or a string.
    DimensionError
        If ``b`` and ``d`` differ in their last axis, the batch shapes do not broadcast (or
        broadcast into a bigger batch than any argument's), or a parameter does not fit.
    NonFiniteError
        If an input contains NaN or inf.
    ParameterError
        If a parameter is negative.
    NumericalError
        If the exact input overflows float64 (rescale the problem).

    Notes
    -----
    Where no input satisfies both conditions (``b`` and ``d`` parallel, pointing the same way,
    with disjoint half-spaces; ``b = 0`` with ``A > 0``; or ``d = 0`` with ``B > 0``) the
    region is ``INCOMPATIBLE`` and ``u`` is the safety-first fallback: the least-norm input
    meeting the CBF condition alone, ``max(B, 0) / |d|^2 d`` (the limit of
    :func:`clf_cbf_relaxed` as the slack becomes free); if ``d = 0`` as well, the least-norm
    input meeting the CLF condition alone. The region is ``INCOMPATIBLE`` exactly where
    :func:`compatibility` says ``compatible=False``: both come from one decision procedure.

    Corrections to the paper (derived in ``docs/theory.md``): the printed definitions of the
    P3 weights are garbled; anti-parallel ``b, d`` are always compatible (P1 or P2 or P3 then
    applies); and the P3 input is computed in the stable orthogonal form above, whose relative
    error is a small multiple of the problem's own condition number times the machine epsilon.
    """
    batch = check_lie_terms(a, b, c, d)
    check_params(batch, kappa=kappa, rho=rho, phi=phi, varphi=varphi, parallel_rtol=parallel_rtol)
    res = _clf_cbf_jit(*as_float(a, b, c, d), kappa, rho, phi, varphi, parallel_rtol)
    _check_result("clf_cbf", res)
    return res


def clf_cbf_relaxed(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    slack_weight: Any,
) -> FormulaResult:
    """Relaxed CLF-CBF formula for the incompatible case, Theorem 3, eq. (22).

    Returns the exact minimiser of ``1/2 |u|^2 + 1/2 slack_weight chi^2`` subject to
    ``a + b u <= -kappa zeta + chi`` and ``c + d u >= rho Gamma``: the table of
    :func:`clf_cbf` applied to the slack-augmented rows ``(b, -1/sqrt(slack_weight))`` and
    ``(d, 0)`` in the variable ``(u, sqrt(slack_weight) chi)``, i.e. with ``|b|^2`` replaced by
    ``|b|^2 + 1/slack_weight`` and ``det = (|b|^2 + 1/slack_weight) |d|^2 - (b.d)^2``. The slack
    is ``chi = lambda1 / slack_weight``.

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi
        As for :func:`clf_cbf`.
    slack_weight : float or array broadcastable to (...,)
        Weight ``m`` of the slack, > 0 (the paper's ``m``; larger means closer to the hard
        CLF constraint).

    Returns
    -------
    FormulaResult
        With ``slack`` holding ``chi``. Unpacks as ``u, region``.

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, NumericalError
        As for :func:`clf_cbf`.
    ParameterError
        If a parameter is negative or ``slack_weight <= 0``.

    Notes
    -----
    Corrections to the printed theorem (derived in ``docs/theory.md``): the right-hand side of
    the multiplier system is ``rho Gamma - c`` (printed ``Gamma - rho c``);
    ``v_bar = A b.d + B (1/m + |b|^2)``; and the objective weight is ``1/2 m chi^2`` (the
    proof writes ``1/m chi^2``, which does not give the printed ``1/m + |b|^2``). The only
    infeasible case left is ``d = 0`` with ``B > 0``, where the CLF-only solution is returned
    with region ``INCOMPATIBLE``. With one input ``b`` and ``d`` are always parallel; the
    augmented rows are not, and the orthogonal form gives ``u = B/d`` exactly in P3, where the
    printed ``-lambda1 b + lambda2 d`` loses every digit for large slack weights. The slack
    enters as ``1/sqrt(slack_weight)``, so weights down to the smallest float64 stay finite.
    """
    batch = check_lie_terms(a, b, c, d)
    check_params(batch, kappa=kappa, rho=rho, phi=phi, varphi=varphi, slack_weight=slack_weight)
    res = _clf_cbf_relaxed_jit(*as_float(a, b, c, d), kappa, rho, phi, varphi, slack_weight)
    _check_result("clf_cbf_relaxed", res)
    return res
