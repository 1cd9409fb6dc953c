"""Apply a per-point function over any number of leading batch axes; run items in threads."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


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


def device_array(x: Any, dtype: Any = None) -> jax.Array:
    """``x`` as a JAX array (of ``dtype`` if given), without compiling a program for it.

    ``jnp.asarray`` of host data compiles (and caches) a small conversion program per shape
    and dtype; ``jax.device_put`` of a numpy array compiles nothing. Host data (numpy arrays,
    lists, numbers) goes by the latter; a JAX array or a tracer by ``jnp.asarray``.
    """
    if isinstance(x, jax.Array):  # tracers included
        return jnp.asarray(x, dtype=dtype)
    return jax.device_put(np.asarray(x, dtype=dtype))


def as_float_array(x: Any) -> Any:
    """``x`` as a float64 array: a JAX array (or tracer) stays one, host data becomes NumPy.

    Host data stays on the host: a jitted function it is passed to moves it to the device in
    its own C++ dispatch, which costs far less than a ``jax.device_put`` from Python (an
    eager ``step`` of a filter spent about as long moving its one state as XLA spent on the
    step).
    """
    if isinstance(x, jax.Array):  # tracers included
        return jnp.asarray(x, dtype=jnp.float64)
    return np.asarray(x, dtype=np.float64)


def in_threads(fn: Callable[[Any], Any], items: Any, workers: int, done: Callable) -> list:
    """``[fn(i) for i in items]``, ``workers`` at once in threads; ``done(count)`` as each ends.

    JAX releases the GIL while it compiles and runs, so independent programs (Monte Carlo
    chunks, a study's closed loops) share the cores. Results come back in the order of
    ``items``; the first exception raised by ``fn`` is raised here, once the items already
    running have finished (those not started are dropped).
    """
    items = list(items)
    if workers == 1 or len(items) <= 1:
        out = []
        for k, item in enumerate(items):
            out.append(fn(item))
            done(k + 1)
        return out
    results: list[Any] = [None] * len(items)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(fn, item): k for k, item in enumerate(items)}
        try:
            for count, fut in enumerate(as_completed(futures), 1):
                results[futures[fut]] = fut.result()
                done(count)
        except BaseException:  # an error or an interrupt: the items not started are dropped
            for fut in futures:
                fut.cancel()
            raise
    return results


def cpu_count() -> int:
    """The CPUs this process may run on (its affinity where the platform tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1
