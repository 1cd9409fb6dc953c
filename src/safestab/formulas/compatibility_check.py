"""Compatibility of the CLF and CBF conditions, Lemma 1 (corrected)."""

from __future__ import annotations

from typing import Any

import jax

from ._checks import as_float, check_lie_terms, check_params
from ._kernels import DEFAULT_PARALLEL_RTOL, margins, solve_two
from .results import Compatibility

__all__ = ["compatibility"]


@jax.jit
def _compatibility_jit(a, b, c, d, kappa, rho, phi, varphi, parallel_rtol):
    mg = margins(a, b, c, d, kappa, rho, phi, varphi)
    sol = solve_two(mg.A, mg.B, b, d, mg.nb, mg.nd, parallel_rtol=parallel_rtol)
    return Compatibility(compatible=sol.case > 0, case=sol.case)


def compatibility(
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
) -> Compatibility:
    """Whether the CLF and CBF conditions can hold together, Lemma 1, eq. (7).

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi, parallel_rtol
        As for :func:`clf_cbf`.

    Returns
    -------
    Compatibility
        ``compatible`` (bool, shape (...,)) and ``case`` (a :class:`CompatibilityCase`).

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, ParameterError
        As for :func:`clf_cbf`.

    Notes
    -----
    Correction to Lemma 1: when ``b`` and ``d`` point the same way (``d = t b``, ``t > 0``)
    the conditions ``b u <= -A`` and ``b u >= B / t`` are compatible iff ``t A + B <= 0``,
    i.e. ``v = A b.d + B |b|^2 <= 0`` (``v`` and ``w`` then have the same sign). The lemma as
    printed asks for ``v >= 0`` or ``w >= 0``, the opposite inequality, and its absolute value
    in the parallel test also counts anti-parallel vectors, which are always compatible. The
    parallel test uses the relative tolerance ``parallel_rtol``. Lemma 1 assumes ``b, d != 0``;
    the zero cases are decided directly (``b = 0``: compatible iff ``A <= 0``, and so on).

    The verdict comes from the same decision procedure as :func:`clf_cbf` (one kernel), so
    ``compatible`` is False exactly where ``clf_cbf`` returns region ``INCOMPATIBLE``.
    """
    batch = check_lie_terms(a, b, c, d)
    check_params(batch, kappa=kappa, rho=rho, phi=phi, varphi=varphi, parallel_rtol=parallel_rtol)
    return _compatibility_jit(*as_float(a, b, c, d), kappa, rho, phi, varphi, parallel_rtol)
