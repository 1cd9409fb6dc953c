"""Certificates of a formula's output: its KKT residuals and the two condition flags."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .._validation import check_finite, check_real
from ..errors import DimensionError, InputTypeError
from ._checks import as_float, check_lie_terms, check_params
from ._kernels import SATISFIED_RTOL, condition_flags, kkt, margins
from .results import ConditionFlags, FormulaResult, KKTResiduals

__all__ = ["kkt_residuals", "conditions_satisfied"]


@jax.jit
def _kkt_jit(a, b, c, d, u, lam, chi, kappa, rho, phi, varphi, slack_weight):
    mg = margins(a, b, c, d, kappa, rho, phi, varphi)
    return KKTResiduals(*kkt(b, d, mg.A, mg.B, u, lam, chi, slack_weight))


@jax.jit
def _kkt_hard_jit(a, b, c, d, u, lam, chi, kappa, rho, phi, varphi):
    mg = margins(a, b, c, d, kappa, rho, phi, varphi)
    return KKTResiduals(*kkt(b, d, mg.A, mg.B, u, lam, chi, None))


def _check_u(u: Any, batch: tuple[int, ...], m: int) -> None:
    check_real("u", u)
    check_finite("u", u)
    if tuple(np.shape(u)) != batch + (m,):
        raise DimensionError(f"u must have shape {batch + (m,)}, got shape {np.shape(u)}")


def kkt_residuals(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    result: FormulaResult,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    slack_weight: Any = None,
) -> KKTResiduals:
    """KKT residuals of ``result`` for the QP behind :func:`clf_cbf` or the relaxed formula.

    A point where all residuals vanish (to rounding) is certified optimal without any solver:
    the QP is strictly convex, so the KKT conditions are sufficient. With the problem as a
    value, ``CombinedFormula().residuals(problem, result)`` (or ``RelaxedFormula``'s) gives the
    same residuals, unchecked, without passing the terms again
    (:mod:`safestab.formulas.problem`).

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi
        As for :func:`clf_cbf`.
    result : FormulaResult
        The output to check, with ``u`` of shape (..., m), multipliers (..., 2), slack (...,).
    slack_weight : float, optional
        Given for the relaxed problem; ``None`` for the hard one.

    Returns
    -------
    KKTResiduals

    Raises
    ------
    InputTypeError
        If ``result`` is not a :class:`FormulaResult`, or a term is not real.
    DimensionError, NonFiniteError, ParameterError
        As for :func:`clf_cbf`, and if the result's arrays do not fit the terms' shapes.
    """
    if not isinstance(result, FormulaResult):
        raise InputTypeError(
            f"result must be a FormulaResult (from clf_cbf or clf_cbf_relaxed), "
            f"got {type(result).__name__}"
        )
    batch = check_lie_terms(a, b, c, d)
    params = {"kappa": kappa, "rho": rho, "phi": phi, "varphi": varphi}
    if slack_weight is not None:
        params["slack_weight"] = slack_weight
    check_params(batch, **params)
    m = np.shape(b)[-1]
    _check_u(result.u, batch, m)
    for name, value, shape in (
        ("result.multipliers", result.multipliers, batch + (2,)),
        ("result.slack", result.slack, batch),
    ):
        check_finite(name, value)
        if tuple(np.shape(value)) != shape:
            raise DimensionError(f"{name} must have shape {shape}, got shape {np.shape(value)}")
    args = (*as_float(a, b, c, d, result.u, result.multipliers, result.slack),)
    if slack_weight is None:
        return _kkt_hard_jit(*args, kappa, rho, phi, varphi)
    return _kkt_jit(*args, kappa, rho, phi, varphi, slack_weight)


@jax.jit
def _flags_jit(a, b, c, d, u, kappa, rho, phi, varphi, rtol):
    mg = margins(a, b, c, d, kappa, rho, phi, varphi)
    clf_ok, cbf_ok = condition_flags(a, b, c, d, u, mg, kappa, rho, rtol)
    return ConditionFlags(clf_satisfied=clf_ok, cbf_satisfied=cbf_ok)


def conditions_satisfied(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    u: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    rtol: float = SATISFIED_RTOL,
) -> ConditionFlags:
    """Whether ``u`` satisfies the CLF condition (2) and the CBF condition (5).

    The controllers' ``clf_satisfied`` and ``cbf_satisfied`` flags, on raw Lie terms. Each
    condition is judged against its own magnitudes, never against intermediate terms of a
    formula::

        clf_satisfied:  a + b.u + kappa zeta <=  rtol (|a| + kappa zeta + sum_i |b_i u_i|)
        cbf_satisfied:  c + d.u - rho Gamma  >= -rtol (|c| + rho Gamma + sum_i |d_i u_i|)

    The right-hand sides bound the rounding of evaluating the condition in float64 (times
    ``rtol / eps``, about 450 by default), so a flag that says True means the condition holds
    up to that rounding.

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi
        As for :func:`clf_cbf`.
    u : array of shape (..., m)
    rtol : float, optional
        Relative tolerance (default :data:`SATISFIED_RTOL`).

    Returns
    -------
    ConditionFlags

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, ParameterError
        As for :func:`clf_cbf`, and if ``u`` does not have shape (..., m).
    """
    batch = check_lie_terms(a, b, c, d)
    check_params(batch, kappa=kappa, rho=rho, phi=phi, varphi=varphi, parallel_rtol=rtol)
    _check_u(u, batch, np.shape(b)[-1])
    return _flags_jit(*as_float(a, b, c, d, u), kappa, rho, phi, varphi, rtol)
