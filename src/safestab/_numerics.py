"""Small numerical helpers shared by the formulas and the learning code."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["safe_sqrt"]


@jax.custom_jvp
def safe_sqrt(x: Any) -> Any:
    """``jnp.sqrt(x)`` whose derivative at ``x = 0`` is 0 instead of inf (or NaN).

    A standard deviation of exactly 0 (a component the GP does not learn, a point where the
    posterior variance rounds to 0) then has a finite derivative: 0, the value a variance
    that stays at its minimum 0 has.
    """
    return jnp.sqrt(x)


@safe_sqrt.defjvp
def _safe_sqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s = jnp.sqrt(x)
    return s, jnp.where(s > 0, dx / (2.0 * jnp.where(s > 0, s, 1.0)), 0.0)
