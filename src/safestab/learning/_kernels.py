"""Unchecked kernel functions shared by the GP and its cache (internal)."""

from __future__ import annotations

import functools

import jax
from tinygp import kernels, transforms

__all__ = ["kernel", "kernel_matrix"]


def kernel(kind: str, amplitude, lengthscale):
    """``amplitude^2 * base(x / lengthscale)``, ``base`` the SE or the (L2) Matern 5/2."""
    # tinygp's Matern kernels default to the L1 distance, which is not positive definite in
    # more than one dimension; the Matern 5/2 of GP regression (GPML, scikit-learn) is L2.
    base: kernels.Kernel
    if kind == "se":
        base = kernels.ExpSquared()
    else:
        base = kernels.Matern52(distance=kernels.distance.L2Distance())
    return amplitude**2 * transforms.Linear(1.0 / lengthscale, base)


@functools.partial(jax.jit, static_argnames=("kind",))
def kernel_matrix(amplitude, lengthscale, x1, x2, *, kind):
    """Kernel matrix of shape (N1, N2), compiled once per shape (eager tinygp re-traces)."""
    return kernel(kind, amplitude, lengthscale)(x1, x2)
