"""Single-certificate formulas: Sontag's CLF formula, eq. (3), and the CBF formula, eq. (6).

The checked public functions; each solves through its formula object
(:class:`~safestab.formulas.problem.SontagFormula`, :class:`~.problem.CBFFormula`).
"""

from __future__ import annotations

from typing import Any

import jax

from ._checks import as_float, check_lie_terms, check_output_finite, check_params
from ._kernels import margins
from .problem import CBFFormula, Problem, SontagFormula
from .results import FormulaResult

__all__ = ["zeta", "clf_sontag", "cbf_universal"]

Array = jax.Array


def zeta(a: Any, b: Any, phi: Any) -> Array:
    """Return ``sqrt(a^2 + phi |b|^4)``, the CLF margin function (also ``Gamma`` for c, d).

    Computed as ``hypot(a, (phi^(1/4) |b|)^2)``, which does not overflow for large ``a``
    or ``b`` unless the result itself does.

    Parameters
    ----------
    a : array of shape (...,)
    b : array of shape (..., m)
    phi : float or array broadcastable to (...,), >= 0

    Returns
    -------
    array of shape (...,)

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, ParameterError
        As for :func:`clf_sontag`.
    NumericalError
        If the exact value overflows float64 (``sqrt(phi) |b|^2`` above 1.8e308, say).
    """
    batch = check_lie_terms(a, b)
    check_params(batch, phi=phi)
    a, b = as_float(a, b)
    out = margins(a, b, a, b, 0.0, 0.0, phi, 0.0).zeta
    check_output_finite("zeta", zeta=out)
    return out


@jax.jit
def _clf_sontag_jit(a, b, kappa, phi):
    # the CBF side is unused: c = 0 and d = b only give the margins' CBF half valid shapes
    problem = Problem(a, b, 0.0, b, kappa=kappa, rho=0.0, phi=phi, varphi=0.0)
    return SontagFormula().solve(problem)


def clf_sontag(a: Any, b: Any, *, kappa: Any, phi: Any) -> FormulaResult:
    """Sontag-type universal formula for a CLF, eq. (3) ``CLF_Sontag_Law``.

    ``u = -(a + kappa zeta) / |b|^2 b`` where ``b != 0`` and ``u = 0`` where ``b = 0``, with
    ``zeta = sqrt(a^2 + phi |b|^4)``.

    Parameters
    ----------
    a : array of shape (...,)
        ``L_f V + lambda V``.
    b : array of shape (..., m)
        ``L_g V``.
    kappa : float or array broadcastable to the batch shape (...,)
        Convergence-speed parameter, >= 0.
    phi : float or array broadcastable to (...,)
        Weight of ``|b|^4`` in ``zeta``, >= 0.

    Returns
    -------
    FormulaResult
        ``u`` of shape (..., m); ``region`` is ``P1`` (the formula's one region: the CLF row
        active; ``P4`` where ``b = 0``), ``multipliers[..., 0] = lambda_1`` with
        ``u = -lambda_1 b``, the CBF multiplier and the slack 0. The same result kind as
        :func:`clf_cbf` and every formula object's ``solve``.

    Raises
    ------
    InputTypeError
        If a term or parameter is bool, complex or a string.
    DimensionError
        If ``b`` is a scalar, the batch shapes do not broadcast (or broadcast into a bigger
        batch), or a parameter does not fit the batch.
    NonFiniteError
        If an input contains NaN or inf.
    ParameterError
        If ``kappa`` or ``phi`` is negative.
    NumericalError
        If the exact input overflows float64 (rescale the problem).

    Notes
    -----
    As printed, the formula makes the CLF condition ``a + b u <= -kappa zeta`` hold with
    equality. For ``kappa >= 1`` the bracket ``a + kappa zeta`` is never negative, and the input
    is the least-norm one; for ``kappa < 1`` and ``a < 0`` the bracket can be negative and the
    formula then *spends* input to reach the boundary, unlike the QP solution (which is 0 there,
    region P4 of :func:`clf_cbf`). Where ``b = 0`` the condition holds only if ``a <= 0``.
    The bracket is computed without cancellation and the division as ``(A/|b|) (b/|b|)``, so
    neither ``|b|^2`` nor ``kappa^2`` can overflow an intermediate.
    """
    batch = check_lie_terms(a, b)
    check_params(batch, kappa=kappa, phi=phi)
    result = _clf_sontag_jit(*as_float(a, b), kappa, phi)
    check_output_finite("clf_sontag", u=result.u)
    return result


@jax.jit
def _cbf_universal_jit(c, d, rho, varphi):
    # the CLF side is unused: a = 0 and b = d only give the margins' CLF half valid shapes
    problem = Problem(0.0, d, c, d, kappa=0.0, rho=rho, phi=0.0, varphi=varphi)
    return CBFFormula().solve(problem)


def cbf_universal(c: Any, d: Any, *, rho: Any, varphi: Any) -> FormulaResult:
    """Universal formula for a CBF, eq. (6) ``CBF_Universal_Law``.

    ``u = (rho Gamma - c) / |d|^2 d`` where ``d != 0`` and ``u = 0`` where ``d = 0``, with
    ``Gamma = sqrt(c^2 + varphi |d|^4)``.

    Parameters
    ----------
    c : array of shape (...,)
        ``L_f h + beta h``.
    d : array of shape (..., m)
        ``L_g h``.
    rho : float or array broadcastable to (...,)
        Conservatism parameter, >= 0.
    varphi : float or array broadcastable to (...,)
        Weight of ``|d|^4`` in ``Gamma``, >= 0.

    Returns
    -------
    FormulaResult
        ``u`` of shape (..., m); ``region`` ``P2`` (``P4`` where ``d = 0``),
        ``multipliers[..., 1] = lambda_2`` with ``u = lambda_2 d``, the CLF multiplier and the
        slack 0.

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, ParameterError, NumericalError
        As for :func:`clf_sontag`.

    Notes
    -----
    The CBF condition ``c + d u >= rho Gamma`` holds with equality where ``d != 0``. Where
    ``d = 0`` it holds only if ``c >= rho Gamma``.
    """
    batch = check_lie_terms(c, d, names=("c", "d"))
    check_params(batch, rho=rho, varphi=varphi)
    result = _cbf_universal_jit(*as_float(c, d), rho, varphi)
    check_output_finite("cbf_universal", u=result.u)
    return result
