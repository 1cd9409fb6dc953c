"""Argument checks of the public formulas (run eagerly, before anything is traced)."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from .._validation import (
    check_finite,
    check_fits_batch,
    check_no_broadcast_growth,
    check_real,
    check_scalar_range,
    is_concrete,
)
from ..errors import DimensionError, NonFiniteError, NumericalError, ParameterError

_TINY = float(np.finfo(float).tiny)

__all__ = [
    "check_lie_terms",
    "check_params",
    "check_box",
    "check_max_iter",
    "as_float",
    "check_output_finite",
]


#: ``check_lie_terms``'s default for an absent CBF pair (``None`` given by a caller is checked,
#: and refused, like any other non-array).
ABSENT: Any = object()


def check_lie_terms(
    a: Any, b: Any, c: Any = ABSENT, d: Any = ABSENT, names: tuple[str, ...] = ("a", "b", "c", "d")
) -> tuple[int, ...]:
    """Check the Lie terms and return their common batch shape.

    ``names`` are used in messages (``("c", "d")`` when only the CBF pair is passed as
    ``a, b``).

    Raises
    ------
    InputTypeError
        If a term is bool, complex, a string or not an array.
    DimensionError
        If ``b`` or ``d`` is a scalar, their last axes differ, or the batch shapes do not
        broadcast or broadcast into a bigger batch.
    NonFiniteError
        If a term contains NaN or inf.
    """
    pairs = [(names[0], a, names[1], b)]
    with_cbf = c is not ABSENT or d is not ABSENT
    if with_cbf:
        pairs.append((names[2], c, names[3], d))
    arg_names: list[str] = []
    shapes: list[tuple[int, ...]] = []
    for sname, s, vname, v in pairs:
        check_real(sname, s)
        check_real(vname, v)
        vshape = np.shape(v)
        if len(vshape) == 0:
            raise DimensionError(f"{vname} must have shape (..., m), got a scalar")
        arg_names += [sname, vname]
        shapes += [tuple(np.shape(s)), tuple(vshape[:-1])]
    if with_cbf and np.shape(b)[-1] != np.shape(d)[-1]:
        raise DimensionError(
            f"{names[1]} and {names[3]} must have the same last axis (the input dimension m), "
            f"got {names[1]} shape {np.shape(b)} and {names[3]} shape {np.shape(d)}"
        )
    batch = check_no_broadcast_growth(tuple(arg_names), tuple(shapes))
    for sname, s, vname, v in pairs:
        check_finite(sname, s)
        check_finite(vname, v)
    return batch


def check_params(batch: tuple[int, ...] | None = None, **params: Any) -> None:
    """Check formula parameters: real, finite, in range, and (given ``batch``) shaped to fit.

    ``slack_weight`` must be > 0, ``parallel_rtol`` in [0, 1], every other parameter >= 0.

    Raises
    ------
    InputTypeError, NonFiniteError, ParameterError, DimensionError
    """
    for name, value in params.items():
        check_real(name, value)
        if name == "slack_weight":
            check_scalar_range(name, value, lower=0.0, strict_lower=True)
            if is_concrete(value) and np.any(np.asarray(value, float) < _TINY):
                raise ParameterError(
                    f"slack_weight must be >= {_TINY!r} (the smallest normal float64; XLA "
                    f"flushes smaller numbers to zero), got {np.min(np.asarray(value, float))!r}"
                )
        elif name == "parallel_rtol":
            check_scalar_range(name, value, lower=0.0, upper=1.0)
            if np.ndim(value) != 0:
                raise DimensionError(f"parallel_rtol must be a scalar, got shape {np.shape(value)}")
        else:
            check_scalar_range(name, value, lower=0.0)
        if batch is not None:
            check_fits_batch(name, value, batch)


def check_box(u_min: Any, u_max: Any, shape: tuple[int, ...] | None = None) -> None:
    """Check input bounds: real, no NaN, ``u_min <= u_max``, and (given) fitting ``shape``.

    An entry may be infinite on its own side (``u_min = -inf``, ``u_max = +inf``: no bound
    there), never on the other (``u_min = +inf`` or ``u_max = -inf`` leaves no input).

    Raises
    ------
    InputTypeError, NonFiniteError, ParameterError, DimensionError
    """
    for name, value, wrong in (("u_min", u_min, np.inf), ("u_max", u_max, -np.inf)):
        check_real(name, value)
        if is_concrete(value):
            arr = np.asarray(value, dtype=float)
            if np.any(np.isnan(arr)) or np.any(arr == wrong):
                raise NonFiniteError(
                    f"{name} must be a number, or {'-' if wrong > 0 else '+'}inf where there is "
                    f"no bound; got {arr.tolist()}"
                )
        if shape is not None:
            check_fits_batch(name, value, shape, what="input u")
    if is_concrete(u_min, u_max):
        lo, hi = np.asarray(u_min, float), np.asarray(u_max, float)
        try:
            bad = lo > hi
        except ValueError:
            raise DimensionError(
                f"u_min and u_max must broadcast, got shapes {lo.shape} and {hi.shape}"
            ) from None
        if np.any(bad):
            raise ParameterError(
                f"u_min must be <= u_max elementwise, got u_min={lo.tolist()} "
                f"and u_max={hi.tolist()}"
            )


def as_float(*xs: Any) -> tuple[Any, ...]:
    """Return the arguments as float64 JAX arrays."""
    return tuple(jnp.asarray(x, dtype=float) for x in xs)


def check_output_finite(function: str, **outputs: Any) -> None:
    """Raise if a formula produced NaN or inf from finite input (its exact value overflows).

    Raises
    ------
    NumericalError
        Naming the output and the remedy (rescale the problem).

    Under a JAX transformation (``jit``, ``vmap``, ``grad``) the values are unknown and
    nothing is checked: the outputs are returned as computed (see docs/jax.md).
    """
    if not is_concrete(*outputs.values()):
        return
    for name, value in outputs.items():
        arr = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise NumericalError(
                f"{function}: the exact {name} is not representable in float64 (it overflows "
                f"at {int(np.sum(~np.isfinite(arr)))} entries) although every input is finite; "
                "rescale the problem (units of a, b, c, d or of the input)"
            )


def check_max_iter(max_iter: Any) -> int | None:
    """Check an iteration bound (None, or an integer >= 1) and return it as an int or None.

    Raises
    ------
    ParameterError
        If it is not None and not an integer >= 1.
    """
    if max_iter is None:
        return None
    if isinstance(max_iter, bool) or not isinstance(max_iter, int | np.integer) or max_iter < 1:
        raise ParameterError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    return int(max_iter)
