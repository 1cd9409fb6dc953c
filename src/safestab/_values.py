"""Controllers as JAX values: their numeric parameters are pytree leaves.

A controller (:class:`~safestab.UniversalController`, :class:`~safestab.SafetyFilter`) is a
pytree whose leaves are its numeric parameters (``kappa``, ``rho``, constant ``phi`` and
``varphi``, ``slack_weight``, the limits, ``gp_beta``, ``H``) and whose static part is
everything else (the system, the certificates, the formula, the uncertainty model). So a
controller can be an argument of a user's ``jax.jit``, be ``vmap``-ped over its parameters,
and be differentiated with respect to them (``jax.grad`` of a closed-loop cost through
:func:`~safestab.simulate`).

``replace(**changes)`` builds a new controller with some arguments changed, with every check
of the constructor (checks that need numbers are skipped for traced values, as in the
formulas). Unflattening a pytree (what JAX does inside its transformations) sets the leaves
without checks, as JAX requires.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

__all__ = [
    "PytreeValue",
    "ControllerValue",
    "Template",
    "model_is_data",
    "register_model",
    "static_key",
]


def static_key(value: Any) -> Any:
    """A hashable stand-in for a static (non-leaf) constructor argument.

    Numbers, strings, ``None``, frozen dataclasses (the formula objects) and NumPy arrays by
    value, sequences (lists and tuples alike) element by element, anything else (a system, a
    certificate, a GP, a callable) by identity: the :class:`Template` that holds the key also
    holds the object, so the identity cannot be reused while the key exists.
    """
    if value is None or isinstance(value, bool | int | float | str):
        return (type(value).__name__, value)
    if isinstance(value, np.ndarray):
        # by value: a NumPy array can change in place, and a program compiled for its old
        # values (a filter's constant u_nom is a constant of the step) must not be reused
        return ("array", value.dtype.str, value.shape, value.tobytes())
    if isinstance(value, tuple | list):
        # a list and a tuple of the same elements alike: ``SafetyFilter(cbfs=[...])`` keeps
        # them as a tuple, which ``replace`` passes on (they were two tree structures)
        return ("sequence", tuple(static_key(v) for v in value))
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        if value.__dataclass_params__.frozen:  # type: ignore[attr-defined]
            try:
                return ("value", type(value), hash(value), value)
            except TypeError:  # a field that is not hashable: by identity below
                pass
    return ("id", id(value))


class Template:
    """The static part of a value's pytree: the object it was built as, and its key.

    Without a key (certificates, and subclasses defined outside safestab, whose state the
    constructor arguments may not show) it is compared by identity, so every copy of one
    object shares one tree structure. A controller's key is its class, its leaf names and
    its static constructor arguments (:func:`static_key`): two controllers built alike, or
    one and its :meth:`~ControllerValue.replace` with new numbers, have equal tree
    structures, so a user's ``jax.jit`` that takes them as arguments compiles once for both.
    Controllers are values: an attribute set after construction is not part of the key.
    """

    __slots__ = ("obj", "key", "_hash")

    def __init__(self, obj: Any, key: Any = None) -> None:
        self.obj = obj
        self.key = key
        # computed once: jit hashes the tree structure, and so this, at every call
        self._hash = id(obj) if key is None else hash(key)

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Template):
            return False
        if self.key is None or other.key is None:
            return other.obj is self.obj
        return self.key == other.key


def register_model(
    cls: type, arrays: Callable[[Any], dict[str, Any]], key: Callable[[Any], Any]
) -> None:
    """Register an uncertainty model class as a pytree whose leaves are its arrays.

    A fitted model (a GP's posterior, a cache) is then data: :func:`~safestab.simulate`
    passes its arrays to the compiled closed loop as arguments instead of baking them into
    the program as constants, so the loop compiles in the time its operations take (not its
    data's size), and the persistent compilation cache serves every model of the same shapes.

    Parameters
    ----------
    cls : type
    arrays : callable
        ``arrays(model)`` -> ``{attribute: pytree of arrays}``: what a model of these shapes
        needs to evaluate (empty before it is fitted).
    key : callable
        ``key(model)`` -> a hashable value naming everything else ``mean_std`` reads (kernel,
        dimensions, components): models with equal keys and array shapes share one
        compiled program. ``None`` compares by identity.

    Notes
    -----
    Unflattening copies the first model of that key (no constructor) and sets the arrays, as
    :class:`ControllerValue` does for a controller's parameters.
    """

    def flatten(model: Any) -> tuple[tuple[Any, ...], tuple[Template, tuple[str, ...]]]:
        parts = arrays(model)
        return tuple(parts.values()), (Template(model, key(model) if parts else None), tuple(parts))

    def unflatten(aux: tuple[Template, tuple[str, ...]], leaves: Any) -> Any:
        template, names = aux
        new = copy.copy(template.obj)
        for name, value in zip(names, leaves, strict=True):
            setattr(new, name, value)
        return new

    jax.tree_util.register_pytree_node(cls, flatten, unflatten)


def model_is_data(model: Any) -> bool:
    """Whether an uncertainty model is a pytree with array leaves (a registered, fitted one)."""
    if model is None or jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(model)):
        return False
    return bool(jax.tree_util.tree_leaves(model))


def _frozen(value: Any) -> Any:
    """A read-only copy of a NumPy array (the caller's array may change later); else as is."""
    if not isinstance(value, np.ndarray):
        return value
    frozen = np.array(value)
    frozen.flags.writeable = False
    return frozen


class PytreeValue:
    """Base of the values that are pytrees (controllers, filters and certificates).

    Each subclass is registered with JAX by its ``_flatten`` and ``_unflatten``.
    """

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        jax.tree_util.register_pytree_node(cls, cls._flatten, cls._unflatten)


class ControllerValue(PytreeValue):
    """Mixin: a controller whose numeric parameters are pytree leaves.

    Subclasses call :meth:`_remember` at the end of ``__init__`` with the constructor's
    arguments, list their parameters in :meth:`_leaf_names` (those present; read and written
    in their ``params`` dict or as attributes) and their certificates in ``_CHILDREN``;
    nothing jitted is kept on a value (the step is a module-level jitted function that takes
    the controller as its argument).
    """

    _init: type
    _kwargs: dict
    _template: Template

    def _remember(self, init: type, kwargs: dict) -> None:
        """Keep the constructor (``init``) and its arguments, for :meth:`replace`.

        The parameters and constructor arguments given as NumPy arrays are kept as read-only
        copies (a controller JAX rebuilds from NumPy leaves holds such copies too): a
        controller is a value: writing into a caller's array or into an array of
        :meth:`tunables` cannot change the controller's numbers behind the device copies an
        eager step keeps, so the input and the limits it reports always belong together.
        """
        self._init = init
        self._kwargs = {name: _frozen(value) for name, value in kwargs.items()}
        # the certificates as the value holds them (a filter's ``clfs=clf`` as the tuple
        # ``(clf,)``, which replace() passes on): one tree structure for both spellings
        self._kwargs.update({name: getattr(self, name) for name in self._CHILDREN})
        children = self._children()
        for name in self._leaf_names():
            self._set_leaf(name, _frozen(self._get_leaf(name)))
        if not type(self).__module__.startswith("safestab."):
            # a user's subclass may keep state its constructor arguments do not show
            self._template = Template(self)
            return
        leaves = self._leaf_names()
        # a fitted uncertainty model is a child (its arrays are leaves, its kind and shapes
        # its structure), not a static argument compared by identity
        statics = tuple(
            (name, static_key(value))
            for name, value in sorted(self._kwargs.items())
            if name not in leaves and not (name in self._DATA_KWARGS and name in children)
        )
        self._template = Template(self, (type(self), leaves, statics))

    #: Constructor arguments that are children when given as data (a pytree of arrays):
    #: their arrays are leaves, not part of the static key.
    _DATA_KWARGS: tuple[str, ...] = ("uncertainty",)

    # -- to be provided by subclasses ---------------------------------------------------
    def _leaf_names(self) -> tuple[str, ...]:
        raise NotImplementedError

    def _get_leaf(self, name: str) -> Any:
        """A parameter of the ``params`` dict, else the attribute of that name."""
        return self.params[name] if name in self.params else getattr(self, name)

    def _set_leaf(self, name: str, value: Any) -> None:
        if name in self.params:
            self.params[name] = value
        else:
            setattr(self, name, value)

    # -- public -------------------------------------------------------------------------
    def tunables(self) -> dict[str, Any]:
        """The numeric parameters that are pytree leaves, by name (see :meth:`replace`)."""
        return {name: self._get_leaf(name) for name in self._leaf_names()}

    def replace(self, **changes: Any) -> Any:
        """A new controller with some constructor arguments changed.

        The arguments are checked as by the constructor (values that JAX traces on their
        shapes and dtypes only). Any constructor argument can be changed (a new uncertainty
        model, say); the numeric ones may be traced, so
        ``jax.grad(lambda k: cost(ctrl.replace(kappa=k)))`` and ``jax.vmap`` over them work.
        """
        # the current leaves and certificates, not the constructor's arguments: a value that
        # JAX rebuilt (from a jitted function, a tree_map or a vmap) carries the arguments of
        # the controller its tree structure was first made from
        current = {**self.tunables(), **{name: getattr(self, name) for name in self._children()}}
        new = object.__new__(type(self))
        self._init.__init__(new, **{**self._kwargs, **current, **changes})
        return new

    # -- pytree -------------------------------------------------------------------------
    #: Attributes holding certificates (pytrees themselves: their rates are leaves too).
    _CHILDREN: tuple[str, ...] = ()

    def _children(self) -> tuple[str, ...]:
        """The attributes that are pytree children: ``_CHILDREN``, and the model.

        ``"uncertainty"`` is one where the model is data (a pytree of arrays: a fitted GP or
        cache), so its arrays are arguments of a compiled step or loop and another model of
        the same kind and shapes runs the same program.
        """
        model = getattr(self, "uncertainty", None)
        return self._CHILDREN + (("uncertainty",) if model_is_data(model) else ())

    def _flatten(self) -> tuple[tuple[Any, ...], tuple[Template, tuple[str, ...]]]:
        names = self._leaf_names() + self._children()
        return tuple(self._get_leaf(n) for n in names), (self._template, names)

    def on_device(self) -> Any:
        """The same value with its numeric leaves as device arrays; made once, kept on it.

        For the eager entry points (``step``): a jitted function takes a device array as it
        is, where it transfers a Python number or a NumPy leaf at every call (about 5 us
        each). The same tree structure and values, so the same compiled program.
        """
        cached = self.__dict__.get("_device_copy")
        if cached is None:
            leaves, treedef = jax.tree_util.tree_flatten(self)
            on = [v if isinstance(v, jax.Array) else jax.numpy.asarray(v) for v in leaves]
            if any(isinstance(v, jax.core.Tracer) for v in on):  # traced leaves, or a trace
                return self
            cached = treedef.unflatten(on)
            self.__dict__["_device_copy"] = cached
        return cached

    @classmethod
    def _unflatten(cls, aux: tuple[Template, tuple[str, ...]], leaves: Any) -> Any:
        template, names = aux
        new = copy.copy(template.obj)  # no constructor: JAX may pass placeholders as leaves
        new.__dict__.pop("_device_copy", None)  # the template's leaves, not these
        new.params = dict(template.obj.params)
        for name, value in zip(names, leaves, strict=True):
            new._set_leaf(name, _frozen(value))
        return new
