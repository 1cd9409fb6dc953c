"""Run-time parameters: a pytree declared by example and checked per call.

Convention (one rule for every object): an object given ``params=example`` calls its user
functions as ``fn(x, p)``; without it, as ``fn(x)``. ``example`` is any JAX pytree (a dict, a
tuple, a NamedTuple, a single array) whose leaves are real numbers or arrays; it fixes the
structure and the leaf shapes that every later ``p`` must have. The values of ``p`` may change
from call to call without recompiling: ``p`` is an argument of the jitted step, never a
constant baked into it.

Internal: the public objects (systems, certificates, controllers, filters, ``simulate``) use
these helpers; users never need them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._validation import check_finite, check_real, is_concrete
from .errors import DimensionError, InputTypeError, ParameterError


def _leaf_name(name: str, path: tuple) -> str:
    return name + jax.tree_util.keystr(path)


class ParamSpec:
    """The structure and leaf shapes of a params pytree, from an example.

    Parameters
    ----------
    example : pytree
        Leaves real numbers or arrays (converted to float64).
    owner : str
        The object that declared it, for messages (``"the system"``, ``"CBF h"``).

    Raises
    ------
    ParameterError
        If the example has no leaves or is a callable.
    InputTypeError
        If a leaf is bool, complex, a string or an object.
    NonFiniteError
        If a leaf contains NaN or inf.
    """

    def __init__(self, example: Any, owner: str) -> None:
        if callable(example) and not hasattr(example, "shape"):
            raise ParameterError(
                f"params of {owner} must be an example pytree of arrays (a dict, tuple or "
                f"array), got a callable {example!r}"
            )
        leaves, treedef = jax.tree_util.tree_flatten_with_path(example)
        if not leaves:
            raise ParameterError(
                f"params of {owner} must be a pytree with at least one array leaf, got {example!r}"
            )
        values = []
        for path, leaf in leaves:
            leaf_name = _leaf_name("params", path)
            check_real(leaf_name, leaf)
            check_finite(leaf_name, leaf)
            values.append(np.asarray(leaf, dtype=float))
        self.owner = owner
        self.treedef: Any = jax.tree_util.tree_structure(example)
        self.paths = tuple(path for path, _ in leaves)
        self.shapes = tuple(v.shape for v in values)
        #: The example itself, leaves as float64 NumPy arrays (used for probes).
        self.example = jax.tree_util.tree_unflatten(self.treedef, values)

    def describe(self) -> str:
        """``params['a']: (2,), params['b']: ()`` for messages."""
        return ", ".join(
            f"{_leaf_name('params', p)}: {s}" for p, s in zip(self.paths, self.shapes, strict=True)
        )

    def same_as(self, other: ParamSpec) -> bool:
        """Same tree structure and same leaf shapes."""
        return self.treedef == other.treedef and self.shapes == other.shapes

    def abstract(self) -> Any:
        """The pytree of ``jax.ShapeDtypeStruct`` (float64) for tracing."""
        leaves = [jax.ShapeDtypeStruct(s, jnp.float64) for s in self.shapes]
        return jax.tree_util.tree_unflatten(self.treedef, leaves)

    def check(self, value: Any, name: str = "params") -> Any:
        """Return ``value`` with float64 leaves after checking it against the example.

        Raises
        ------
        ParameterError
            If the tree structure differs (names both structures).
        InputTypeError
            If a leaf is not real.
        DimensionError
            If a leaf's shape differs (names the leaf).
        NonFiniteError
            If a concrete leaf contains NaN or inf.
        """
        if callable(value) and not hasattr(value, "shape"):
            raise InputTypeError(
                f"{name} must be a pytree like the declared example ({self.describe()}), "
                f"got a callable {value!r}"
            )
        leaves, treedef = jax.tree_util.tree_flatten_with_path(value)
        if treedef != self.treedef:
            raise ParameterError(
                f"{name} must have the structure of the params example declared by "
                f"{self.owner} ({self.treedef}), got {treedef}"
            )
        out = []
        for (path, leaf), shape in zip(leaves, self.shapes, strict=True):
            leaf_name = _leaf_name(name, path)
            check_real(leaf_name, leaf)
            arr = jnp.asarray(leaf, dtype=jnp.float64)
            if arr.shape != shape:
                raise DimensionError(
                    f"{leaf_name} must have shape {shape} (as in the params example of "
                    f"{self.owner}), got shape {arr.shape}"
                )
            if is_concrete(arr):
                check_finite(leaf_name, arr)
            out.append(arr)
        return jax.tree_util.tree_unflatten(treedef, out)


def make_spec(example: Any, owner: str) -> ParamSpec | None:
    """``None`` for ``example is None``, else a :class:`ParamSpec`."""
    return None if example is None else ParamSpec(example, owner)


def merge_specs(specs: Sequence[ParamSpec | None]) -> ParamSpec | None:
    """The one params structure shared by several objects (``None`` when none takes any).

    Raises
    ------
    ParameterError
        If two objects declared different structures or leaf shapes (names both).
    """
    found = [s for s in specs if s is not None]
    if not found:
        return None
    first = found[0]
    for other in found[1:]:
        if not first.same_as(other):
            raise ParameterError(
                f"one params pytree reaches every function, but {first.owner} declared "
                f"{{{first.describe()}}} ({first.treedef}) and {other.owner} declared "
                f"{{{other.describe()}}} ({other.treedef}); give them the same example"
            )
    return first


def resolve(spec: ParamSpec | None, value: Any, owner: str, name: str = "params") -> Any:
    """Check a call's ``params`` against the spec of ``owner``.

    Returns ``None`` when neither is given, else the checked pytree.

    Raises
    ------
    ParameterError
        If params are given to an object that takes none, or missing where it takes some;
        and as :meth:`ParamSpec.check`.
    """
    if spec is None:
        if value is not None:
            raise ParameterError(
                f"{name} was given, but {owner} takes no run-time parameters (declare them "
                "with params=example on the system, a certificate or the controller)"
            )
        return None
    if value is None:
        raise ParameterError(
            f"{owner} takes run-time parameters ({spec.describe()}, declared by {spec.owner}); "
            f"give {name}=..."
        )
    return spec.check(value, name)


def bind(fn: Callable, takes_params: bool) -> Callable[[jax.Array, Any], Any]:
    """``fn`` as a function of ``(x, p)``: ``fn(x, p)`` or ``fn(x)`` (``p`` ignored)."""
    if takes_params:
        return fn
    return lambda x, p: fn(x)


def trace_shape(name: str, fn: Callable, n_states: int, spec: ParamSpec | None) -> Any:
    """``jax.eval_shape`` of ``fn`` on a state (and params when ``spec`` is given).

    Raises
    ------
    InputTypeError
        If ``fn`` cannot be called with that many arguments (``(x)`` without a params
        example, ``(x, p)`` with one), saying which signature was expected.
    """
    probe: tuple = (jax.ShapeDtypeStruct((n_states,), jnp.float64),)
    if spec is not None:
        probe += (spec.abstract(),)
    try:
        return jax.eval_shape(fn, *probe)
    except TypeError as err:
        if "positional argument" not in str(err):
            raise
        expected = (
            f"{name}(x, p), since params were declared by {spec.owner}"
            if spec is not None
            else f"{name}(x) (declare params=example to make it take (x, p))"
        )
        raise InputTypeError(f"{name} must be callable as {expected}; calling it failed: {err}")
