"""Control-affine systems ``xdot = f(x) + g(x) u``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import as_float_array, over_batch
from ._params import ParamSpec, bind, make_spec, resolve, trace_shape
from ._validation import check_finite, is_concrete
from .errors import DimensionError, InputTypeError

__all__ = ["ControlAffineSystem"]


def _traced_array_shape(
    name: str, fn: Callable, n_states: int, spec: ParamSpec | None
) -> tuple[int, ...]:
    """Trace ``fn`` on one state (and params) and return its output shape (one real array).

    Raises
    ------
    InputTypeError
        If ``fn`` returns a list, tuple or other container, or a non-real dtype, or cannot be
        called as ``fn(x)`` (``fn(x, p)`` with params).
    """
    out = trace_shape(name, fn, n_states, spec)
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
    params : pytree, optional
        An example of run-time parameters (a dict, tuple or array of real numbers). When
        given, ``f`` and ``g`` take ``(x, p)`` and every controller step passes the current
        ``p`` (same structure and leaf shapes as the example; new values never recompile).

    Attributes
    ----------
    n_states : int
    n_inputs : int
        Input dimension ``m``, read from the shape of ``g``.
    params_spec : ParamSpec or None
        The declared parameters' structure (None without ``params``).

    Raises
    ------
    DimensionError
        If ``n_states`` is not a positive integer, or ``f`` or ``g`` returns the wrong shape
        (checked at construction by tracing them once, without evaluating numbers).
    ParameterError
        If ``params`` is not a pytree of real arrays.

    Notes
    -----
    ``f`` and ``g`` are written for one state; every method here also accepts a batch of
    states of shape (..., n), mapped with ``jax.vmap``.
    """

    def __init__(
        self,
        f: Callable[..., jax.Array],
        g: Callable[..., jax.Array],
        n_states: int,
        *,
        name: str = "system",
        params: Any = None,
    ) -> None:
        if not isinstance(n_states, int | np.integer) or n_states < 1:
            raise DimensionError(f"n_states must be a positive integer, got {n_states!r}")
        if not callable(f) or not callable(g):
            raise TypeError("f and g must be callables taking a state of shape (n,)")
        spec = make_spec(params, f"system {name!r}")
        f_shape = _traced_array_shape("f", f, int(n_states), spec)
        if f_shape != (n_states,):
            raise DimensionError(
                f"f must return shape (n_states,) = ({n_states},), got shape {f_shape}"
            )
        g_shape = _traced_array_shape("g", g, int(n_states), spec)
        if len(g_shape) != 2 or g_shape[0] != n_states or g_shape[1] < 1:
            raise DimensionError(
                f"g must return shape (n_states, n_inputs) = ({n_states}, m), got shape {g_shape}"
            )
        self.f = f
        self.g = g
        self.params_spec: ParamSpec | None = spec
        #: ``f`` and ``g`` as functions of ``(x, p)`` whether or not they take parameters.
        self.f_of = bind(f, spec is not None)
        self.g_of = bind(g, spec is not None)
        self.n_states = int(n_states)
        self.n_inputs = int(g_shape[1])
        self.name = name

    def __repr__(self) -> str:
        return (
            f"ControlAffineSystem(name={self.name!r}, n_states={self.n_states}, "
            f"n_inputs={self.n_inputs})"
        )

    def check_state(self, x: Any, name: str = "x") -> Any:
        """Return ``x`` as a float64 array after checking its last axis and finiteness.

        A JAX array (or a tracer) stays one; host data (NumPy, lists) is returned as NumPy.

        Raises
        ------
        DimensionError
            If the last axis is not ``n_states``.
        NonFiniteError
            If ``x`` contains NaN or inf.
        """
        return self._check_last_axis(x, self.n_states, name)

    def check_input(self, u: Any, name: str = "u") -> Any:
        """Return ``u`` as a float array after checking its last axis and finiteness."""
        return self._check_last_axis(u, self.n_inputs, name)

    @staticmethod
    def _check_last_axis(value: Any, size: int, name: str) -> Any:
        value = as_float_array(value)
        if value.ndim == 0 or value.shape[-1] != size:
            raise DimensionError(f"{name} must have shape (..., {size}), got shape {value.shape}")
        if is_concrete(value):
            check_finite(name, value)
        return value

    def drift(self, x: jax.Array, params: Any = None) -> jax.Array:
        """``f(x)``: shape (..., n) to (..., n) (``params`` when the system takes them)."""
        p = resolve(self.params_spec, params, f"system {self.name!r}")
        return over_batch(lambda s: self.f_of(s, p), x)

    def input_matrix(self, x: jax.Array, params: Any = None) -> jax.Array:
        """``g(x)``: shape (..., n) to (..., n, m) (``params`` when the system takes them)."""
        p = resolve(self.params_spec, params, f"system {self.name!r}")
        return over_batch(lambda s: self.g_of(s, p), x)

    def dynamics(self, x: jax.Array, u: jax.Array, params: Any = None) -> jax.Array:
        """``f(x) + g(x) u`` for ``x`` of shape (..., n) and ``u`` of shape (..., m)."""
        return self.drift(x, params) + jnp.einsum(
            "...ij,...j->...i", self.input_matrix(x, params), u
        )

    def with_disturbance(
        self, omega: Callable[[jax.Array], jax.Array], *, name: str | None = None
    ) -> ControlAffineSystem:
        """Return the system ``xdot = f(x) + g(x) u + omega(x)``, eq. (9).

        Parameters
        ----------
        omega : callable
            The unmodelled dynamics, a JAX function from shape (n,) to (n,) (a function of the
            state only, also for a system with run-time parameters).
        name : str, optional
        """
        f = self.f
        name = name or f"{self.name}+omega"
        if self.params_spec is None:
            return ControlAffineSystem(lambda x: f(x) + omega(x), self.g, self.n_states, name=name)
        return ControlAffineSystem(
            lambda x, p: f(x, p) + omega(x),
            self.g,
            self.n_states,
            name=name,
            params=self.params_spec.example,
        )
