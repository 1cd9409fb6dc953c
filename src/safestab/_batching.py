"""Apply a per-point function over any number of leading batch axes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp


def over_batch(fn: Callable[[jax.Array], Any], x: jax.Array) -> Any:
    """Evaluate ``fn`` (defined on one state of shape (n,)) on ``x`` of shape (..., n).

    Leading axes are flattened, mapped with ``jax.vmap``, and restored on every output leaf.
    A single state (``x.ndim == 1``) is passed straight through.
    """
    if x.ndim == 1:
        return fn(x)
    batch = x.shape[:-1]
    flat = x.reshape((-1, x.shape[-1]))
    out = jax.vmap(fn)(flat)
    return jax.tree_util.tree_map(lambda leaf: leaf.reshape(batch + leaf.shape[1:]), out)


def as_float_array(x: Any) -> jax.Array:
    """Return ``x`` as a float64 JAX array."""
    return jnp.asarray(x, dtype=jnp.float64)
