"""Control Lyapunov and control barrier functions, and their Lie terms by autodiff.

For a system ``xdot = f(x) + g(x) u``:

* CLF ``V`` with rate ``lam``: ``a = L_f V + lam V`` and ``b = L_g V`` (Definition 1);
* CBF ``h`` with rate ``beta``: ``c = L_f h + beta h`` and ``d = L_g h`` (Definition 2).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import over_batch
from ._numerics import as_scalar
from ._params import ParamSpec, bind, make_spec, merge_specs, resolve, trace_shape
from ._validation import check_real, check_scalar_range, is_concrete
from ._values import PytreeValue, Template
from .errors import DimensionError, NonFiniteError, ParameterError, RelativeDegreeError
from .systems import ControlAffineSystem

__all__ = [
    "CLF",
    "CBF",
    "LieTerms",
    "lie_terms",
    "high_order_cbf",
    "check_actuated",
    "RELATIVE_DEGREE_RTOL",
]

#: ``L_g h`` counts as zero for a relative-degree-2 barrier when
#: ``|L_g h| <= RELATIVE_DEGREE_RTOL (|grad h| |g|)``: rounding of the product, with room.
RELATIVE_DEGREE_RTOL = 1e-12


class LieTerms(NamedTuple):
    """The four terms every formula works on.

    Attributes
    ----------
    a : array of shape (...,)
        ``L_f V + lam V``.
    b : array of shape (..., m)
        ``L_g V``.
    c : array of shape (...,)
        ``L_f h + beta h``.
    d : array of shape (..., m)
        ``L_g h``.
    """

    a: jax.Array
    b: jax.Array
    c: jax.Array
    d: jax.Array


#: Points where a class-K function is checked: 0 and +-10^k for k in -6..3 (the values a
#: certificate takes in practice): zero at 0, strictly increasing for |h| <= 1 and
#: non-decreasing beyond. Enough to catch a sign error, an offset or a decreasing function;
#: not a proof of monotonicity everywhere.
_CLASS_K_PROBE = np.concatenate([-np.logspace(3, -6, 46), [0.0], np.logspace(-6, 3, 46)])


def _check_class_k(name: str, fn: Any) -> None:
    """Check an extended class-K function on the probe grid.

    Raises
    ------
    ParameterError
        If it is not callable-to-scalar, ``fn(0) != 0``, or it is not strictly increasing.
    """
    if not callable(fn):
        raise TypeError(f"{name} must be a callable from a scalar to a scalar")
    out = jax.vmap(fn)(jnp.asarray(_CLASS_K_PROBE))
    if np.shape(out) != _CLASS_K_PROBE.shape:
        raise DimensionError(f"{name} must map a scalar to a scalar, got shape {np.shape(out)[1:]}")
    if not is_concrete(out):  # built under jit or grad (a traced gain): shapes only
        return
    values = np.asarray(out, dtype=float)
    zero = float(values[_CLASS_K_PROBE.size // 2])
    if zero != 0.0:
        raise ParameterError(
            f"{name} must be an extended class-K function with {name}(0) = 0, "
            f"got {name}(0) = {zero!r}"
        )
    # strictly increasing near 0; far out only non-decreasing (tanh saturates in float64)
    steps = np.diff(values)
    near = np.abs(_CLASS_K_PROBE[1:]) <= 1.0
    bad = np.where(near, steps <= 0, steps < 0) | ~np.isfinite(steps)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ParameterError(
            f"{name} must be strictly increasing (extended class-K), but {name}"
            f"({_CLASS_K_PROBE[i]:.3g}) = {values[i]!r} >= {name}({_CLASS_K_PROBE[i + 1]:.3g}) = "
            f"{values[i + 1]!r}"
        )


class _Certificate(PytreeValue):
    """A scalar function of the state with a gradient (autodiff unless given)."""

    _kind = "certificate"
    _fn_name = "fn"
    _rate_name = "rate"
    _class_k_name = "class_k"

    def __init__(
        self,
        fn: Callable[[jax.Array], jax.Array],
        rate: float | None,
        grad: Callable[[jax.Array], jax.Array] | None = None,
        class_k: Callable[[jax.Array], jax.Array] | None = None,
        params: Any = None,
    ) -> None:
        if not callable(fn):
            raise TypeError(f"{self._fn_name} must be a callable taking a state of shape (n,)")
        spec = make_spec(params, f"{self._kind} {self._fn_name}")
        if grad is not None and not callable(grad):
            raise TypeError("grad must be None or a callable returning shape (n,)")
        if (rate is None) == (class_k is None):
            raise ParameterError(
                f"give exactly one of {self._rate_name} (a linear rate) and "
                f"{self._class_k_name} (a class-K function)"
            )
        if rate is not None:
            self._check_rate(rate)
        else:
            _check_class_k(self._class_k_name, class_k)
        self.fn = fn
        self.rate = as_scalar(rate) if rate is not None else None
        self._template = Template(self)
        self.class_k = class_k
        self.grad = grad if grad is not None else jax.grad(fn)
        self.hand_gradient = grad is not None
        #: The declared run-time parameters (None: ``fn`` and ``grad`` take the state only).
        self.params_spec: ParamSpec | None = spec
        #: ``fn`` and ``grad`` as functions of ``(x, p)`` whether or not they take parameters.
        self.fn_of = bind(fn, spec is not None)
        self.grad_of = bind(self.grad, spec is not None)
        #: 1 for a plain certificate; 2 for :func:`high_order_cbf` (whose ``base`` is ``h``)
        self.relative_degree = 1
        self.base: Callable | None = None
        #: gradient of ``base`` as a function of ``(x, p)`` (high-order CBFs only)
        self.base_grad: Callable | None = None

    def _check_rate(self, rate: Any) -> None:
        """A linear rate: a real, finite scalar >= 0 (traced: its dtype and shape only)."""
        check_real(self._rate_name, rate)
        if np.ndim(rate) != 0:
            raise DimensionError(
                f"{self._rate_name} must be a scalar, got an array of shape {np.shape(rate)}"
            )
        check_scalar_range(self._rate_name, rate, lower=0.0)

    def replace(self, **changes: Any) -> Any:
        """A copy with a new linear rate (``lam`` of a CLF, ``beta`` of a CBF), checked.

        The rate may be a value that JAX traces: ``jax.grad`` of a closed-loop cost with
        respect to a CBF's ``beta`` goes through ``ctrl.replace(cbf=cbf.replace(beta=b))``.
        A certificate is a pytree whose one leaf is its linear rate (none for a class-K
        function).

        Raises
        ------
        ParameterError
            If another argument is named, or the certificate has a class-K function instead
            of a linear rate, or the rate is negative.
        """
        unknown = set(changes) - {self._rate_name}
        if unknown:
            raise ParameterError(
                f"{type(self).__name__}.replace changes only {self._rate_name}, "
                f"got {sorted(unknown)}"
            )
        if self.rate is None:
            raise ParameterError(
                f"this {type(self).__name__} has a class-K function {self._class_k_name}, "
                f"not a linear {self._rate_name}: build a new one instead"
            )
        rate = changes[self._rate_name]
        self._check_rate(rate)
        new = copy.copy(self)
        new.rate = as_scalar(rate)
        return new

    def _flatten(self) -> tuple[tuple[Any, ...], tuple[Template, bool]]:
        has_rate = self.rate is not None
        return ((self.rate,) if has_rate else ()), (self._template, has_rate)

    @classmethod
    def _unflatten(cls, aux: tuple[Template, bool], leaves: Any) -> Any:
        template, has_rate = aux
        new = copy.copy(template.obj)  # no constructor: JAX may pass placeholders as leaves
        if has_rate:
            (new.rate,) = leaves
        return new

    def rate_term(self, value: jax.Array) -> jax.Array:
        """``rate * value`` (the paper's linear choice) or ``class_k(value)``."""
        if self.class_k is not None:
            return self.class_k(value)
        return self.rate * value

    def check(self, n_states: int) -> None:
        """Check shapes against a state dimension by tracing once.

        Raises
        ------
        DimensionError
            If the function is not scalar-valued or the gradient has the wrong shape.
        """
        spec = self.params_spec
        out = trace_shape(self._fn_name, self.fn, n_states, spec)
        shape = getattr(out, "shape", None)
        if not isinstance(out, jax.ShapeDtypeStruct) or shape != ():
            got = f"shape {shape}" if shape is not None else type(out).__name__
            raise DimensionError(f"{self._fn_name} must return a scalar, got {got}")
        gshape = getattr(
            trace_shape(f"grad of {self._fn_name}", self.grad, n_states, spec), "shape", None
        )
        if gshape != (n_states,):
            raise DimensionError(
                f"grad of {self._fn_name} must return shape ({n_states},), got {gshape}"
            )

    def relative_degree_holds(
        self, system: ControlAffineSystem, x: jax.Array, p: Any = None
    ) -> jax.Array:
        """Whether ``L_g`` of the base constraint is zero at one state (True for degree 1).

        For :func:`high_order_cbf`: ``|L_g h| <= RELATIVE_DEGREE_RTOL (|grad h| |g|)``.
        ``p``: the run-time parameters (unchecked), when the system or ``h`` takes them.
        """
        if self.relative_degree == 1 or self.base_grad is None:
            return jnp.asarray(True)
        gh, g = self.base_grad(x, p), system.g_of(x, p)
        return jnp.all(jnp.abs(gh @ g) <= RELATIVE_DEGREE_RTOL * (jnp.abs(gh) @ jnp.abs(g)))

    def value(self, x: jax.Array, params: Any = None) -> jax.Array:
        """The function's value: shape (..., n) to (...,) (``params`` if it takes them)."""
        p = resolve(self.params_spec, params, f"{self._kind} {self._fn_name}")
        return over_batch(lambda s: self.fn_of(s, p), x)

    def gradient(self, x: jax.Array, params: Any = None) -> jax.Array:
        """The gradient: shape (..., n) to (..., n) (``params`` if it takes them)."""
        p = resolve(self.params_spec, params, f"{self._kind} {self._fn_name}")
        return over_batch(lambda s: self.grad_of(s, p), x)

    def lie_point(
        self, system: ControlAffineSystem, x: jax.Array, p: Any = None
    ) -> tuple[jax.Array, jax.Array]:
        """``(L_f + rate) value`` and ``L_g value`` at one state, unchecked and jittable.

        ``p``: the run-time parameters (unchecked), passed to whichever of ``f``, ``g`` and
        the certificate take them.
        """
        grad = self.grad_of(x, p)
        return (
            grad @ system.f_of(x, p) + self.rate_term(self.fn_of(x, p)),
            grad @ system.g_of(x, p),
        )

    def lie(
        self, system: ControlAffineSystem, x: jax.Array, params: Any = None
    ) -> tuple[jax.Array, jax.Array]:
        """``(L_f + rate) value`` of shape (...,) and ``L_g value`` of shape (..., m)."""
        spec = merge_specs([system.params_spec, self.params_spec])
        p = resolve(spec, params, f"the {self._kind} with its system")
        return over_batch(lambda s: self.lie_point(system, s, p), x)


class CLF(_Certificate):
    """A control Lyapunov function ``V`` with rate ``lam`` (Definition 1).

    Parameters
    ----------
    V : callable
        A JAX function from a state of shape (n,) to a scalar; positive definite.
    lam : float, optional
        The rate ``lambda >= 0`` in ``a = L_f V + lambda V``.
    grad : callable, optional
        A hand-written gradient, shape (n,) to (n,); autodiff is used when omitted.
    gamma : callable, optional
        Instead of ``lam``: an extended class-K function (``gamma(0) = 0``, strictly
        increasing), scalar to scalar, giving ``a = L_f V + gamma(V)``.
    params : pytree, optional
        An example of run-time parameters; when given, ``V`` (and ``grad``) take ``(x, p)``
        (a moving set-point, say). Controllers pass the ``p`` of each call.

    Raises
    ------
    ParameterError
        If ``lam < 0``, both or neither of ``lam`` and ``gamma`` are given, or ``gamma`` is not
        an extended class-K function on a probe grid.
    NonFiniteError
        If ``lam`` is NaN or inf.
    DimensionError
        If ``lam`` is not a scalar.
    """

    _kind = "CLF"
    _fn_name = "V"
    _rate_name = "lam"
    _class_k_name = "gamma"

    def __init__(
        self,
        V: Callable,
        lam: float | None = None,
        grad: Callable | None = None,
        *,
        gamma: Callable | None = None,
        params: Any = None,
    ) -> None:
        super().__init__(V, lam, grad, gamma, params)

    @property
    def V(self) -> Callable:
        """The function ``V``."""
        return self.fn

    @property
    def lam(self) -> float | None:
        """The rate ``lambda`` (None when a class-K ``gamma`` is used)."""
        return self.rate

    @property
    def gamma(self) -> Callable | None:
        """The class-K function ``gamma`` (None for the linear rate)."""
        return self.class_k


class CBF(_Certificate):
    """A control barrier function ``h`` with rate ``beta`` (Definition 2).

    Parameters
    ----------
    h : callable
        A JAX function from a state of shape (n,) to a scalar; the safe set is ``h >= 0``.
    beta : float, optional
        The rate ``beta >= 0`` in ``c = L_f h + beta h``.
    grad : callable, optional
        A hand-written gradient; autodiff is used when omitted.
    alpha : callable, optional
        Instead of ``beta``: an extended class-K function (``alpha(0) = 0``, strictly
        increasing), scalar to scalar, giving ``c = L_f h + alpha(h)``.
    params : pytree, optional
        An example of run-time parameters; when given, ``h`` (and ``grad``) take ``(x, p)``
        (a moving obstacle, say). Controllers pass the ``p`` of each call.

    Raises
    ------
    ParameterError
        If ``beta < 0``, both or neither of ``beta`` and ``alpha`` are given, or ``alpha`` is
        not an extended class-K function on a probe grid.
    NonFiniteError
        If ``beta`` is NaN or inf.
    DimensionError
        If ``beta`` is not a scalar.
    """

    _kind = "CBF"
    _fn_name = "h"
    _rate_name = "beta"
    _class_k_name = "alpha"

    def __init__(
        self,
        h: Callable,
        beta: float | None = None,
        grad: Callable | None = None,
        *,
        alpha: Callable | None = None,
        params: Any = None,
    ) -> None:
        super().__init__(h, beta, grad, alpha, params)

    @property
    def h(self) -> Callable:
        """The function ``h``."""
        return self.fn

    @property
    def beta(self) -> float | None:
        """The rate ``beta`` (None when a class-K ``alpha`` is used)."""
        return self.rate

    @property
    def alpha(self) -> Callable | None:
        """The class-K function ``alpha`` (None for the linear rate)."""
        return self.class_k


def high_order_cbf(
    system: ControlAffineSystem,
    h: Callable[[jax.Array], jax.Array],
    *,
    alpha1: Callable[[jax.Array], jax.Array] | float,
    beta: float | None = None,
    alpha: Callable[[jax.Array], jax.Array] | None = None,
    probe: Any = None,
    params: Any = None,
) -> CBF:
    """A CBF of relative degree 2 (a high-order / exponential CBF), built by autodiff.

    For ``h`` with ``L_g h = 0`` (the input does not act on ``h`` directly), the barrier
    ``psi1(x) = L_f h(x) + alpha1(h(x))`` has relative degree 1, and the returned CBF imposes
    ``L_f psi1 + L_g psi1 u + alpha2(psi1) >= rho Gamma`` on it (with ``alpha2`` the linear
    ``beta`` or the class-K ``alpha``). Keeping ``psi1 >= 0`` keeps ``h >= 0`` from states with
    ``h >= 0`` and ``psi1 >= 0``.

    Parameters
    ----------
    system : ControlAffineSystem
        The model whose ``f`` defines ``L_f h``.
    h : callable
        The constraint, a state of shape (n,) to a scalar; safe set ``h >= 0``.
    alpha1 : float or callable
        Rate of the first stage: a number ``> 0`` (``alpha1 h``) or an extended class-K
        function.
    beta, alpha : optional
        The second stage's rate, as for :class:`CBF` (exactly one).
    probe : array of shape (k, n), optional
        States at which ``L_g h = 0`` is checked at construction (default: the origin and 16
        seeded standard-normal states).
    params : pytree, optional
        An example of run-time parameters; when given, ``h`` takes ``(x, p)``. The returned
        CBF takes ``(x, p)`` when ``h`` or the system does (the probe check uses the example).

    Returns
    -------
    CBF
        With ``fn = psi1``, ``relative_degree = 2`` and ``base = h``; the controllers also
        check ``L_g h = 0`` at every state and report the step status ``RELATIVE_DEGREE``
        where it fails.

    Raises
    ------
    ParameterError
        If ``L_g h`` is not zero at a probe state (the relative degree is not 2 there), or a
        rate is invalid.
    """
    if callable(alpha1):
        _check_class_k("alpha1", alpha1)
        first = alpha1
    else:
        check_real("alpha1", alpha1)
        check_scalar_range("alpha1", alpha1, lower=0.0, strict_lower=True)
        rate1 = float(alpha1)

        def first(v: jax.Array) -> jax.Array:
            return rate1 * v

    grad_h = jax.grad(h)
    spec = merge_specs([system.params_spec, make_spec(params, "high_order_cbf's h")])
    takes = params is not None
    h_of, grad_h_of = bind(h, takes), bind(grad_h, takes)
    psi1: Callable
    if spec is None:

        def psi1(x: jax.Array) -> jax.Array:
            return grad_h(x) @ system.f(x) + first(h(x))

    else:

        def psi1(x: jax.Array, p: Any) -> jax.Array:
            return grad_h_of(x, p) @ system.f_of(x, p) + first(h_of(x, p))

    n = system.n_states
    pts = np.asarray(probe, dtype=float).reshape(-1, n) if probe is not None else _probe_states(n)
    example = None if spec is None else spec.example
    lgh, scale = _lg_h(system, grad_h_of, jnp.asarray(pts), example)
    bad = np.flatnonzero(
        ~(np.abs(np.asarray(lgh)) <= RELATIVE_DEGREE_RTOL * np.asarray(scale)).all(-1)
    )
    if bad.size:
        i = int(bad[0])
        raise ParameterError(
            f"h does not have relative degree 2: L_g h = {np.asarray(lgh)[i].tolist()} != 0 at "
            f"x = {pts[i].tolist()}; use a plain CBF, or a constraint the input does not act on"
        )
    cbf = CBF(psi1, beta=beta, alpha=alpha, params=example)
    cbf.relative_degree = 2
    cbf.base = h
    cbf.base_grad = grad_h_of
    return cbf


def check_actuated(system: ControlAffineSystem, cbf: CBF, name: str, params: Any = None) -> None:
    """Refuse a barrier the input cannot move: ``L_g h = 0`` at every probe state.

    The probe states are the origin and 16 seeded standard-normal states (those of
    :func:`high_order_cbf`); ``L_g h`` counts as zero where ``|L_g h| <= RELATIVE_DEGREE_RTOL
    (|grad h| |g|)``. A barrier whose ``L_g h`` vanishes only on a set (where ``grad h`` is
    orthogonal to every input direction) passes; the controllers then name a step where its
    condition fails there (status ``CBF_UNACTUATED``). The result is kept on the barrier per
    system, so :meth:`~safestab.Controller.replace` does not probe again. A system built of
    traced values (inside a user's ``jit`` or ``vmap``) cannot be probed, and is not.

    Parameters
    ----------
    system : ControlAffineSystem
    cbf : CBF
    name : str
        The argument's name in the message (``"cbf"``, ``"cbfs[2]"``).
    params : pytree, optional
        The run-time parameters' example, when the system or the barrier takes them.

    Raises
    ------
    RelativeDegreeError
        If ``L_g h`` is zero at every probe state.
    """
    checked = cbf.__dict__.setdefault("_actuated_by", [])
    if any(s is system for s in checked):
        return
    pts = _probe_states(system.n_states)
    with jax.ensure_compile_time_eval():
        lgh, scale = _lg_h(system, cbf.grad_of, jnp.asarray(pts), params)
    if not is_concrete(lgh, scale):  # the system holds traced values (a vmapped model): the
        return  # run-time status CBF_UNACTUATED still names a failing step
    lgh, scale = np.asarray(lgh), np.asarray(scale)
    if np.all(np.abs(lgh) <= RELATIVE_DEGREE_RTOL * scale):
        raise RelativeDegreeError(
            f"{name}: L_g h is zero at every probe state (the origin and 16 random states), so "
            "no input moves h: its relative degree is 2 or more (a distance when the input is "
            "an acceleration, say). Build the barrier with high_order_cbf(system, h, "
            "alpha1=...), which imposes the condition on L_f h + alpha1 h instead"
        )
    checked.append(system)


def _probe_states(n: int) -> np.ndarray:
    """Where ``L_g h`` is probed: the origin and 16 seeded standard-normal states, (17, n)."""
    return np.vstack([np.zeros((1, n)), np.random.default_rng(0).standard_normal((16, n))])


def _lg_h(
    system: ControlAffineSystem, grad_h_of: Callable, x: jax.Array, p: Any
) -> tuple[Any, Any]:
    """``L_g h`` (..., m) and the scale ``|grad h| |g|`` (..., m) of its rounding."""

    def point(s: jax.Array) -> tuple[jax.Array, jax.Array]:
        gh, g = grad_h_of(s, p), system.g_of(s, p)
        return gh @ g, jnp.abs(gh) @ jnp.abs(g)

    return over_batch(point, x)


def lie_terms(
    system: ControlAffineSystem, clf: CLF | None, cbf: CBF | None, x: Any, *, params: Any = None
) -> LieTerms:
    """Compute ``(a, b, c, d)`` at states ``x`` of shape (..., n).

    Parameters
    ----------
    system : ControlAffineSystem
    clf : CLF or None
        None: ``a = 0`` and ``b = 0`` (no CLF condition).
    cbf : CBF or None
        None: ``c = 0`` and ``d = 0`` (no CBF condition).
    x : array of shape (..., n)
    params : pytree, optional
        The run-time parameters, when the system or a certificate declared them (the same
        ``p`` for every state of the batch).

    Returns
    -------
    LieTerms
        ``a``, ``c`` of shape (...,); ``b``, ``d`` of shape (..., m).

    Raises
    ------
    InputTypeError
        If ``x`` is bool, complex or a string.
    DimensionError
        If ``x`` has the wrong last axis, or ``V`` or ``h`` does not return a scalar.
    NonFiniteError
        If ``x`` contains NaN or inf, or a term is not finite at a finite state (the model
        or a certificate overflows there); under a JAX transformation the terms are returned
        as computed.
    ParameterError
        If ``params`` is missing where a function takes parameters, given where none does,
        or of another structure than the declared example (a wrong leaf shape is a
        ``DimensionError``).
    """
    check_real("x", x)
    x = system.check_state(x)
    for name, cert, kind in (("clf", clf, CLF), ("cbf", cbf, CBF)):
        if cert is not None and not isinstance(cert, kind):
            raise TypeError(f"{name} must be a {kind.__name__} or None, got {type(cert).__name__}")
    certs = [c for c in (clf, cbf) if c is not None]
    for cert in certs:
        cert.check(system.n_states)
    spec = merge_specs([system.params_spec, *(c.params_spec for c in certs)])
    p = resolve(spec, params, "lie_terms' system and certificates")
    terms = over_batch(lambda s: lie_terms_point(system, clf, cbf, s, p), x)
    if is_concrete(*terms):
        xs = np.asarray(x).reshape(-1, x.shape[-1])
        for name, value in zip("abcd", terms, strict=True):
            bad = ~np.all(np.isfinite(np.asarray(value).reshape(len(xs), -1)), axis=-1)
            if np.any(bad):
                i = int(np.argmax(bad))
                where = f"state index {i} " if x.ndim > 1 else ""
                raise NonFiniteError(
                    f"the Lie term {name} is not finite at {where}(x = {xs[i].tolist()}): f, g, "
                    "V or h (or a gradient) overflows or is not finite there"
                )
    return terms


def lie_terms_point(
    system: ControlAffineSystem, clf: CLF | None, cbf: CBF | None, x: jax.Array, p: Any = None
) -> LieTerms:
    """``(a, b, c, d)`` at one state of shape (n,), unchecked and jittable.

    ``p``: the run-time parameters (unchecked), when the system or a certificate takes them.
    A missing certificate (``None``) gives zero terms: ``a = 0, b = 0`` without a CLF (every
    input meets ``b.u <= -a``), ``c = 0, d = 0`` without a CBF.
    """
    zeros = (jnp.zeros(()), jnp.zeros(system.n_inputs))
    a, b = zeros if clf is None else clf.lie_point(system, x, p)
    c, d = zeros if cbf is None else cbf.lie_point(system, x, p)
    return LieTerms(a, b, c, d)
