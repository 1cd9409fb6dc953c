"""Argument checks shared by the public functions.

Checks run only on concrete values. Inside ``jax.jit`` the arguments are tracers whose values
are unknown, so the checks are skipped there; the public entry points (formulas called
eagerly, controller and simulator constructors) validate before anything is traced.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .errors import DimensionError, InputTypeError, NonFiniteError, ParameterError


def is_concrete(*values: Any) -> bool:
    """Return True when no value is a JAX tracer (so its numbers can be inspected)."""
    return not any(isinstance(v, jax.core.Tracer) for v in values)


def traced_results(values: tuple, strict: bool, what: str) -> bool:
    """Whether any of ``values`` (a result's fields) is traced, so its checks cannot run.

    Under ``jit``, ``vmap`` or ``grad`` the statuses are the record of what happened: nothing
    can be raised on them, so ``strict=True`` is refused rather than silently ignored.

    Raises
    ------
    ParameterError
        If the value is traced and ``strict`` is True.
    """
    if is_concrete(*values):
        return False
    if strict:
        raise ParameterError(
            f"strict=True needs concrete results, but {what} runs under a JAX transformation "
            "(jit, vmap, grad): leave strict off and check the status field yourself"
        )
    return True


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


def check_real(name: str, value: Any) -> None:
    """Require a real number or array of real numbers (not bool, complex, string or object).

    Raises
    ------
    InputTypeError
        If ``value`` (or, for a JAX tracer, its dtype) is not integer or floating point.
    """
    dtype = getattr(value, "dtype", None)
    if dtype is None:
        if isinstance(value, bool):
            raise InputTypeError(f"{name} must be a real number or array, got a bool ({value!r})")
        try:
            dtype = np.asarray(value).dtype
        except (ValueError, TypeError):
            raise InputTypeError(
                f"{name} must be a real number or array, got {type(value).__name__}"
            ) from None
    kind = np.dtype(dtype).kind
    if kind not in "iuf":
        what = {"b": "bool", "c": "complex", "U": "string", "S": "bytes", "O": "object"}.get(
            kind, str(dtype)
        )
        raise InputTypeError(f"{name} must be a real number or array, got dtype {what}")


def check_no_broadcast_growth(
    names: tuple[str, ...], shapes: tuple[tuple[int, ...], ...]
) -> tuple[int, ...]:
    """Return the common batch shape, requiring it to be one of ``shapes``.

    Batch shapes may broadcast (a scalar ``a`` with a batch of ``b``), but not into a batch
    bigger than every argument's: ``a`` of shape (3, 1) with ``b`` of shape (3, 2) would
    otherwise silently give 3 x 3 results.

    Raises
    ------
    DimensionError
        If the shapes do not broadcast, or broadcast into a bigger batch.
    """
    check_same_batch(names, shapes)
    batch = tuple(np.broadcast_shapes(*shapes))
    if batch not in [tuple(s) for s in shapes]:
        desc = ", ".join(f"{n} {s}" for n, s in zip(names, shapes, strict=True))
        raise DimensionError(
            f"batch shapes broadcast into a bigger batch {batch} than any argument's: {desc}; "
            "give every argument the same batch shape (or a scalar)"
        )
    return batch


def check_fits_batch(name: str, value: Any, batch: tuple[int, ...], what: str = "batch") -> None:
    """Require ``value`` to broadcast to ``batch`` without enlarging it.

    Raises
    ------
    DimensionError
        If it does not.
    """
    shape = tuple(np.shape(value))
    try:
        ok = tuple(np.broadcast_shapes(batch, shape)) == tuple(batch)
    except ValueError:
        ok = False
    if not ok:
        raise DimensionError(
            f"{name} must be a scalar or broadcast to the {what} shape {tuple(batch)}, "
            f"got shape {shape}"
        )
