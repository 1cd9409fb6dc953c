"""Small numerical helpers shared by the formulas, the controllers and the learning code."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._validation import is_concrete

__all__ = ["safe_sqrt", "as_scalar", "inv_sqrt", "tied"]


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


def as_scalar(value: Any) -> Any:
    """A concrete parameter as a Python float; a traced one as a float64 JAX scalar."""
    if is_concrete(value):
        return float(np.asarray(value, dtype=float))
    return jnp.asarray(value, dtype=float)


def inv_sqrt(value: Any) -> Any:
    """``1/sqrt(value)``: in NumPy for a concrete value (bit for bit as before), else in JAX."""
    if is_concrete(value):
        return np.asarray(1.0 / np.sqrt(np.asarray(value, dtype=float)))
    return 1.0 / jnp.sqrt(jnp.asarray(value, dtype=float))


def tied(tree: Any, tie: Any) -> Any:
    """``tree``'s values, made to depend on the scalar ``tie`` (``tie == tie`` selects them).

    The values are unchanged (both sides of the selection are the value, whatever ``tie``
    is, NaN included); what changes is that under ``vmap`` they are batched wherever ``tie``
    is, so that a loop whose state starts from them (a scan's placeholders, a while loop's
    initial state) is batched from its first pass, and the loop's batching rule passes over
    its body once instead of two or three times.
    """
    return jax.tree_util.tree_map(lambda z: jnp.where(tie == tie, z, z), tree)
