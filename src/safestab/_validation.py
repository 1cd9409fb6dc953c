"""Argument checks shared by the public functions.

Checks run only on concrete values. Inside ``jax.jit`` the arguments are tracers whose values
are unknown, so the checks are skipped there; the public entry points (formulas called
eagerly, controller and simulator constructors) validate before anything is traced.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .errors import DimensionError, NonFiniteError, ParameterError


def is_concrete(*values: Any) -> bool:
    """Return True when no value is a JAX tracer (so its numbers can be inspected)."""
    return not any(isinstance(v, jax.core.Tracer) for v in values)


def _describe(value: np.ndarray) -> str:
    if value.size == 1:
        return repr(float(value.reshape(())))
    bad = value[~np.isfinite(value)] if not np.all(np.isfinite(value)) else value
    return f"an array of shape {value.shape} containing {float(bad.reshape(-1)[0])!r}"


def check_finite(name: str, value: Any) -> None:
    """Raise `NonFiniteError` if a concrete `value` contains NaN or inf."""
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{name} must be finite, got {_describe(arr)}")


def check_scalar_range(
    name: str,
    value: Any,
    *,
    lower: float | None = None,
    strict_lower: bool = False,
    upper: float | None = None,
    strict_upper: bool = False,
) -> None:
    """Check a concrete scalar or array parameter is finite and inside a range.

    Raises
    ------
    NonFiniteError
        If the value contains NaN or inf.
    ParameterError
        If some entry is outside the range.
    """
    if not is_concrete(value):
        return
    check_finite(name, value)
    arr = np.asarray(value, dtype=float)
    if lower is not None:
        bad = arr <= lower if strict_lower else arr < lower
        if np.any(bad):
            op = ">" if strict_lower else ">="
            raise ParameterError(f"{name} must be {op} {lower}, got {_describe(arr[bad])}")
    if upper is not None:
        bad = arr >= upper if strict_upper else arr > upper
        if np.any(bad):
            op = "<" if strict_upper else "<="
            raise ParameterError(f"{name} must be {op} {upper}, got {_describe(arr[bad])}")


def check_vector_last_axis(name: str, value: Any, size: int | None = None) -> None:
    """Require at least one axis, and a last axis of `size` when given."""
    shape = np.shape(value)
    if len(shape) == 0:
        raise DimensionError(
            f"{name} must have shape (..., m) with at least one axis, got a scalar"
        )
    if size is not None and shape[-1] != size:
        raise DimensionError(f"{name} must have shape (..., {size}), got shape {shape}")


def check_same_batch(names: tuple[str, ...], shapes: tuple[tuple[int, ...], ...]) -> None:
    """Require batch shapes to broadcast together, naming the arguments when they do not."""
    try:
        np.broadcast_shapes(*shapes)
    except ValueError:
        desc = ", ".join(f"{n} {s}" for n, s in zip(names, shapes, strict=True))
        raise DimensionError(f"batch shapes do not broadcast: {desc}") from None
