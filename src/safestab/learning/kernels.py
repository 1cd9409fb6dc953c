"""Stationary GP kernels as values, each formula written once.

A kernel is a small frozen object (hashable, so a static argument of a jitted function, as
scikit-learn's and tinygp's kernels are objects) that holds the unit-amplitude kernel as a
function of the squared scaled distance ``r2 = |(x1 - x2) / lengthscale|^2``, written once
over an array namespace ``xp``: ``jax.numpy`` in the posterior and the likelihood, NumPy
(float64 and ``longdouble``) in the fast cache's build. The posterior's tinygp kernel, the
likelihood's gradient and the cache's error bound all come from the same object.

Its :attr:`~StationaryKernel.name` (``"se"``, ``"matern52"``) is what models store and what
files, JSON and the command line carry; :func:`as_kernel` turns either form into the object.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from tinygp import kernels as tinygp_kernels
from tinygp import transforms

from ..errors import ParameterError

__all__ = [
    "KERNELS",
    "KERNEL_NAMES",
    "Matern52",
    "SquaredExponential",
    "StationaryKernel",
    "as_kernel",
]


@dataclasses.dataclass(frozen=True)
class StationaryKernel(abc.ABC):
    """A stationary kernel ``amplitude^2 k(r2)`` of the squared scaled distance ``r2``.

    Subclasses define :attr:`name`, :meth:`of_r2`, :meth:`d_of_r2` and ``_error_sum`` (the
    terms of :meth:`error_coefficient`); everything else is shared. The models store a
    kernel by its name, so they take the kernels of :data:`KERNELS`.
    """

    #: The kernel's name in files, JSON and on the command line.
    name: ClassVar[str]

    @abc.abstractmethod
    def of_r2(self, r2: Any, xp: Any = jnp) -> Any:
        """The unit-amplitude kernel ``k(r2)``.

        Parameters
        ----------
        r2 : array of any shape
            Squared Euclidean distances of the inputs divided by the lengthscales (>= 0).
        xp : module
            The array namespace: ``jax.numpy`` (default) or ``numpy``; NumPy keeps the dtype
            of ``r2`` (``longdouble`` included).

        Returns
        -------
        array of the shape of ``r2``
            Differentiable by JAX at ``r2 = 0`` too.
        """

    @abc.abstractmethod
    def d_of_r2(self, r2: Any, xp: Any = jnp) -> Any:
        """The derivative ``dk/dr2`` of :meth:`of_r2`, arguments as there.

        With ``r2 = sum_d (x_d - x'_d)^2 / l_d^2``, the derivative of ``k`` in ``log l_d``
        is ``-2 dk/dr2 (x_d - x'_d)^2 / l_d^2`` (the likelihood's gradient).
        """

    @abc.abstractmethod
    def _error_sum(self, n: int, zsum: float) -> float:
        """:meth:`error_coefficient` before its 10 % for second-order terms."""

    def tinygp(self, amplitude: Any, lengthscale: Any) -> tinygp_kernels.Kernel:
        """The tinygp kernel ``amplitude^2 k(|(x1 - x2) / lengthscale|^2)``.

        Parameters
        ----------
        amplitude : array of shape ()
        lengthscale : array of shape (n,)

        Returns
        -------
        tinygp.kernels.Kernel
            Called on ``(x1, x2)`` of shapes (N1, n) and (N2, n), gives a matrix (N1, N2).
        """
        return amplitude**2 * transforms.Linear(1.0 / lengthscale, _OfSquaredDistance(self))

    def error_coefficient(self, z_scaled_max: Any) -> float:
        """``e`` such that a kernel value computed in precision ``u`` is within ``e u amp^2``.

        The query's standardisation (``(x - offset) / scale``), the scaling by the inverse
        lengthscales (and the inverse lengthscale itself), the differences to the inducing
        inputs, the sum of squares, ``exp`` (taken as accurate to 2 ulp) and the factors are
        each rounded once; an error in the scaled difference ``d_i`` is at most
        ``5 u (Z_i + |d_i|)``, ``Z_i`` the largest scaled ``|z_i|`` (``z_scaled_max``).
        Carried through the kernel's derivative, whose products with powers of the distance
        are bounded (the class's ``MAXIMA``), the bound is independent of the query; 10 % is
        added for second-order terms. The tests check it against 50-digit kernel values, far
        from the data too.

        Parameters
        ----------
        z_scaled_max : array of shape (n,)
            Per coordinate, the largest ``|z_i| / l_i`` over the inducing inputs.

        Returns
        -------
        float
        """
        z_scaled_max = np.asarray(z_scaled_max, float)
        return 1.1 * self._error_sum(len(z_scaled_max), float(np.sum(z_scaled_max)))


@dataclasses.dataclass(frozen=True)
class SquaredExponential(StationaryKernel):
    """The squared exponential (RBF) kernel ``k(r2) = exp(-r2 / 2)``.

    With one lengthscale per input, the ARD kernel of scikit-learn's ``RBF`` and tinygp's
    ``ExpSquared``.
    """

    name: ClassVar[str] = "se"
    #: The largest values of ``sqrt(t) e^(-t/2)`` and ``t e^(-t/2)`` (``t = r2``), rounded up.
    MAXIMA: ClassVar[tuple[float, ...]] = (0.6066, 0.7358)

    def of_r2(self, r2: Any, xp: Any = jnp) -> Any:
        """``exp(-r2 / 2)``; see :meth:`StationaryKernel.of_r2`."""
        return xp.exp(-0.5 * r2)

    def d_of_r2(self, r2: Any, xp: Any = jnp) -> Any:
        """``-exp(-r2 / 2) / 2``; see :meth:`StationaryKernel.d_of_r2`."""
        return -0.5 * xp.exp(-0.5 * r2)

    def _error_sum(self, n: int, zsum: float) -> float:
        a = self.MAXIMA
        return 5 * a[0] * zsum + (n + 11) / 2 * a[1] + 4


@dataclasses.dataclass(frozen=True)
class Matern52(StationaryKernel):
    """The Matern 5/2 kernel ``k = (1 + t + t^2 / 3) exp(-t)``, ``t = sqrt(5 r2)``.

    ``r2`` is the squared *Euclidean* distance (GPML, scikit-learn's ``Matern(nu=2.5)``):
    tinygp's ``Matern52`` defaults to the L1 distance, which is not positive definite in more
    than one dimension.
    """

    name: ClassVar[str] = "matern52"
    #: The largest values of ``r (1 + sqrt5 r) e^(-sqrt5 r)``, ``r^2 (1 + sqrt5 r)
    #: e^(-sqrt5 r)`` and ``t (1 + t + t^2/3) e^(-t)`` (``r = sqrt(r2)``), rounded up.
    MAXIMA: ClassVar[tuple[float, ...]] = (0.3756, 0.3628, 1.1720)

    @staticmethod
    def _t(r2: Any, xp: Any) -> Any:
        # sqrt(5 r2) in r2's precision (no float64 sqrt(5) constant, so longdouble keeps its
        # digits); its JAX derivative at r2 = 0 is 0, not the inf * 0 = NaN of the sqrt,
        # which leaves k's derivative in the inputs (2 (x - x') dk/dr2 = 0 there) exact.
        pos = r2 > 0
        return xp.where(pos, xp.sqrt(xp.where(pos, 5 * r2, 1)), 0)

    def of_r2(self, r2: Any, xp: Any = jnp) -> Any:
        """``(1 + t + t^2 / 3) exp(-t)``; see :meth:`StationaryKernel.of_r2`."""
        t = self._t(r2, xp)
        return (1 + t + t * t / 3) * xp.exp(-t)

    def d_of_r2(self, r2: Any, xp: Any = jnp) -> Any:
        """``-5/6 (1 + t) exp(-t)``; see :meth:`StationaryKernel.d_of_r2`.

        The float64 constant 5/6 (the likelihood's gradient is computed in float64): times -2
        it is exactly 5/3.
        """
        t = self._t(r2, xp)
        return -5 / 6 * (1 + t) * xp.exp(-t)

    def _error_sum(self, n: int, zsum: float) -> float:
        a = self.MAXIMA
        return 5 / 3 * (5 * a[0] * zsum + (n + 13) / 2 * a[1]) + 2 * a[2] + 8


class _OfSquaredDistance(tinygp_kernels.Kernel):
    """A :class:`StationaryKernel` as a tinygp kernel of the squared Euclidean distance."""

    kernel: StationaryKernel = eqx.field(static=True)

    def evaluate(self, X1: Any, X2: Any) -> Any:
        """``k(|X1 - X2|^2)`` for two points ``X1``, ``X2`` of shape (n,)."""
        return self.kernel.of_r2(jnp.sum(jnp.square(X1 - X2)), jnp)


#: The kernels, one object each.
KERNELS: tuple[StationaryKernel, ...] = (SquaredExponential(), Matern52())
#: Their names, as files, JSON and the command line give them.
KERNEL_NAMES: tuple[str, ...] = tuple(k.name for k in KERNELS)
_BY_NAME = {k.name: k for k in KERNELS}


def as_kernel(kernel: Any) -> StationaryKernel:
    """The kernel object for ``kernel``, a :class:`StationaryKernel` or one of its names.

    Parameters
    ----------
    kernel : StationaryKernel or {"se", "matern52"}
        One of :data:`KERNELS` or its name.

    Returns
    -------
    StationaryKernel

    Raises
    ------
    ParameterError
        If ``kernel`` is neither one of :data:`KERNELS` nor one of :data:`KERNEL_NAMES`.
    """
    if isinstance(kernel, StationaryKernel) and _BY_NAME.get(kernel.name) == kernel:
        return kernel
    if isinstance(kernel, str) and kernel in _BY_NAME:
        return _BY_NAME[kernel]
    names = ", ".join(repr(n) for n in KERNEL_NAMES)
    raise ParameterError(
        f"kernel must be one of {names} or a StationaryKernel such as SquaredExponential() "
        f"or Matern52(), got {kernel!r}"
    )
