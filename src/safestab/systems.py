"""Control-affine systems ``xdot = f(x) + g(x) u``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import as_float_array, over_batch
from ._validation import check_finite, is_concrete
from .errors import DimensionError, InputTypeError

__all__ = ["ControlAffineSystem"]


def _traced_array_shape(name: str, fn: Callable, probe: jax.ShapeDtypeStruct) -> tuple[int, ...]:
    """Trace ``fn`` on ``probe`` and return its output shape, requiring one real array.

    Raises
    ------
    InputTypeError
        If ``fn`` returns a list, tuple or other container, or a non-real dtype.
    """
    out = jax.eval_shape(fn, probe)
    if not isinstance(out, jax.ShapeDtypeStruct):
        raise InputTypeError(
            f"{name} must return one JAX array (use jnp.array([...]) or jnp.stack), "
            f"got {type(out).__name__}"
        )
    if np.dtype(out.dtype).kind not in "iuf":
        raise InputTypeError(f"{name} must return a real array, got dtype {out.dtype}")
    return tuple(out.shape)


class ControlAffineSystem:
    """A control-affine system ``xdot = f(x) + g(x) u``, eq. (1).

    Parameters
    ----------
    f : callable
        Drift, a JAX function from a state of shape (n,) to shape (n,).
    g : callable
        Input matrix, a JAX function from a state of shape (n,) to shape (n, m).
    n_states : int
        State dimension ``n``.
    name : str, optional
        Used in messages and plots.

    Attributes
    ----------
    n_states : int
    n_inputs : int
        Input dimension ``m``, read from the shape of ``g``.

    Raises
    ------
    DimensionError
        If ``n_states`` is not a positive integer, or ``f`` or ``g`` returns the wrong shape
        (checked at construction by tracing them once, without evaluating numbers).

    Notes
    -----
    ``f`` and ``g`` are written for one state; every method here also accepts a batch of
    states of shape (..., n), mapped with ``jax.vmap``.
    """

    def __init__(
        self,
        f: Callable[[jax.Array], jax.Array],
        g: Callable[[jax.Array], jax.Array],
        n_states: int,
        *,
        name: str = "system",
    ) -> None:
        if not isinstance(n_states, int | np.integer) or n_states < 1:
            raise DimensionError(f"n_states must be a positive integer, got {n_states!r}")
        if not callable(f) or not callable(g):
            raise TypeError("f and g must be callables taking a state of shape (n,)")
        probe = jax.ShapeDtypeStruct((int(n_states),), jnp.float64)
        f_shape = _traced_array_shape("f", f, probe)
        if f_shape != (n_states,):
            raise DimensionError(
                f"f must return shape (n_states,) = ({n_states},), got shape {f_shape}"
            )
        g_shape = _traced_array_shape("g", g, probe)
        if len(g_shape) != 2 or g_shape[0] != n_states or g_shape[1] < 1:
            raise DimensionError(
                f"g must return shape (n_states, n_inputs) = ({n_states}, m), got shape {g_shape}"
            )
        self.f = f
        self.g = g
        self.n_states = int(n_states)
        self.n_inputs = int(g_shape[1])
        self.name = name

    def __repr__(self) -> str:
        return (
            f"ControlAffineSystem(name={self.name!r}, n_states={self.n_states}, "
            f"n_inputs={self.n_inputs})"
        )

    def check_state(self, x: Any, name: str = "x") -> jax.Array:
        """Return ``x`` as a float array after checking its last axis and finiteness.

        Raises
        ------
        DimensionError
            If the last axis is not ``n_states``.
        NonFiniteError
            If ``x`` contains NaN or inf.
        """
        return self._check_last_axis(x, self.n_states, name)

    def check_input(self, u: Any, name: str = "u") -> jax.Array:
        """Return ``u`` as a float array after checking its last axis and finiteness."""
        return self._check_last_axis(u, self.n_inputs, name)

    @staticmethod
    def _check_last_axis(value: Any, size: int, name: str) -> jax.Array:
        value = as_float_array(value)
        if value.ndim == 0 or value.shape[-1] != size:
            raise DimensionError(f"{name} must have shape (..., {size}), got shape {value.shape}")
        if is_concrete(value):
            check_finite(name, value)
        return value

    def drift(self, x: jax.Array) -> jax.Array:
        """``f(x)``: shape (..., n) to (..., n)."""
        return over_batch(self.f, x)

    def input_matrix(self, x: jax.Array) -> jax.Array:
        """``g(x)``: shape (..., n) to (..., n, m)."""
        return over_batch(self.g, x)

    def dynamics(self, x: jax.Array, u: jax.Array) -> jax.Array:
        """``f(x) + g(x) u`` for ``x`` of shape (..., n) and ``u`` of shape (..., m)."""
        return self.drift(x) + jnp.einsum("...ij,...j->...i", self.input_matrix(x), u)

    def with_disturbance(
        self, omega: Callable[[jax.Array], jax.Array], *, name: str | None = None
    ) -> ControlAffineSystem:
        """Return the system ``xdot = f(x) + g(x) u + omega(x)``, eq. (9).

        Parameters
        ----------
        omega : callable
            The unmodelled dynamics, a JAX function from shape (n,) to (n,).
        name : str, optional
        """
        f = self.f
        return ControlAffineSystem(
            lambda x: f(x) + omega(x), self.g, self.n_states, name=name or f"{self.name}+omega"
        )
