"""Input limits: projection onto a box (eq. (26)) and safety-first saturation of one input."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_finite, check_real
from ..errors import DimensionError
from ._checks import as_float, check_box, check_lie_terms, check_params
from ._kernels import margins, saturate_single

__all__ = ["project_box", "saturate_safety_first"]

Array = jax.Array


def project_box(u: Any, u_min: Any, u_max: Any) -> Array:
    """Project an input onto the box ``u_min <= u <= u_max``, eq. (26) ``QP_projection``.

    The QP ``min 1/2|u_proj - u|^2`` over a box separates per component, so its solution is the
    componentwise clip.

    Parameters
    ----------
    u : array of shape (..., m)
    u_min, u_max : arrays broadcastable to the shape of ``u`` (without enlarging it)
        Bounds with ``u_min <= u_max``.

    Returns
    -------
    array of shape (..., m)

    Raises
    ------
    InputTypeError
        If ``u`` or a bound is bool, complex or a string.
    DimensionError
        If ``u`` is a scalar or a bound does not fit the shape of ``u``.
    ParameterError
        If ``u_min > u_max`` anywhere.
    NonFiniteError
        If ``u`` or a bound contains NaN or inf.
    """
    check_real("u", u)
    if np.ndim(u) == 0:
        raise DimensionError("u must have shape (..., m), got a scalar")
    check_finite("u", u)
    check_box(u_min, u_max, tuple(np.shape(u)))
    return jnp.clip(*as_float(u, u_min, u_max))


@jax.jit
def _saturate_jit(u, c, d, rho, varphi, u_min, u_max):
    mg = margins(0.0, d, c, d, 0.0, rho, 0.0, varphi)
    return saturate_single(u, mg.B, d, u_min, u_max)


def saturate_safety_first(
    u: Any, c: Any, d: Any, *, rho: Any, varphi: Any, u_min: Any, u_max: Any
) -> tuple[Array, Array]:
    """Saturate a single input so that the CBF condition survives the input limits.

    Projects ``u`` onto the part of ``[u_min, u_max]`` where ``c + d u >= rho Gamma``. When
    that part is empty, returns the box input that comes closest (maximises ``d u``). This goes
    beyond the paper, whose projection (eq. (26)) may give up the CBF condition even when some
    admissible input keeps it.

    Parameters
    ----------
    u : array of shape (..., 1)
        The unconstrained input.
    c : array of shape (...,)
    d : array of shape (..., 1)
    rho, varphi : float or array broadcastable to (...,)
    u_min, u_max : arrays broadcastable to the shape of ``u``

    Returns
    -------
    u_sat : array of shape (..., 1)
    cbf_feasible : bool array of shape (...,)
        Whether some input in the box satisfies the CBF condition (then ``u_sat`` does).

    Raises
    ------
    DimensionError
        If the input dimension is not 1, or the shapes do not fit.
    InputTypeError, ParameterError, NonFiniteError
        As for :func:`project_box` and :func:`cbf_universal`.
    """
    check_real("u", u)
    check_real("d", d)
    if np.shape(u)[-1:] != (1,) or np.shape(d)[-1:] != (1,):
        raise DimensionError(
            "saturate_safety_first needs a single input: u and d must have shape (..., 1), "
            f"got u shape {np.shape(u)} and d shape {np.shape(d)}"
        )
    check_finite("u", u)
    batch = check_lie_terms(c, d, names=("c", "d"))
    if tuple(np.shape(u))[:-1] != batch:
        raise DimensionError(
            f"u must have shape {batch + (1,)} to match c and d, got shape {np.shape(u)}"
        )
    check_params(batch, rho=rho, varphi=varphi)
    check_box(u_min, u_max, tuple(np.shape(u)))
    return _saturate_jit(*as_float(u, c, d), rho, varphi, *as_float(u_min, u_max))
