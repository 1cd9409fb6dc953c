"""Use fitted scikit-learn ``GaussianProcessRegressor`` models as the uncertainty model.

The adapter reads the fitted kernel, training inputs and Cholesky factor of each regressor
and re-implements its latent posterior in JAX, so a controller built on it is jittable.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import solve_triangular

from ..errors import DimensionError

__all__ = ["SklearnGPAdapter"]


def _parse_kernel(kernel: Any) -> tuple[str, float, np.ndarray]:
    """Return (kind, amplitude^2, lengthscale) of ``C * RBF``/``C * Matern(2.5)`` (+ White)."""
    from sklearn.gaussian_process import kernels as K

    if isinstance(kernel, K.Sum):
        parts = [kernel.k1, kernel.k2]
        white = [p for p in parts if isinstance(p, K.WhiteKernel)]
        rest = [p for p in parts if not isinstance(p, K.WhiteKernel)]
        if len(white) != 1 or len(rest) != 1:
            raise TypeError(f"unsupported kernel {kernel}: expected C * RBF (+ WhiteKernel)")
        kernel = rest[0]
    amp2 = 1.0
    if isinstance(kernel, K.Product):
        consts = [p for p in (kernel.k1, kernel.k2) if isinstance(p, K.ConstantKernel)]
        others = [p for p in (kernel.k1, kernel.k2) if not isinstance(p, K.ConstantKernel)]
        if len(consts) != 1 or len(others) != 1:
            raise TypeError(f"unsupported kernel {kernel}: expected C * RBF (+ WhiteKernel)")
        amp2 = float(consts[0].constant_value)
        kernel = others[0]
    if isinstance(kernel, K.Matern):
        if kernel.nu != 2.5:
            raise TypeError(f"only Matern(nu=2.5) is supported, got nu={kernel.nu}")
        return "matern52", amp2, np.atleast_1d(np.asarray(kernel.length_scale, float))
    if isinstance(kernel, K.RBF):
        return "se", amp2, np.atleast_1d(np.asarray(kernel.length_scale, float))
    raise TypeError(f"unsupported kernel {kernel}: expected RBF or Matern(nu=2.5)")


class SklearnGPAdapter:
    """Wrap fitted scikit-learn regressors, one per learned component of ``omega``.

    Parameters
    ----------
    regressors : mapping of component index to fitted ``GaussianProcessRegressor``
        Components not in the mapping are treated as exact (mean 0, std 0). Supported kernels:
        ``ConstantKernel * RBF`` or ``ConstantKernel * Matern(nu=2.5)``, optionally plus a
        ``WhiteKernel`` (treated as observation noise, excluded from the latent variance);
        ``normalize_y`` is honoured.
    n_states : int

    Raises
    ------
    TypeError
        For an unsupported kernel or an unfitted regressor.
    DimensionError
        For a component index out of range or training inputs of the wrong width.
    """

    def __init__(self, regressors: Mapping[int, Any], n_states: int) -> None:
        self.n_states = int(n_states)
        self.components_ = tuple(sorted(int(c) for c in regressors))
        parts = []
        for comp in self.components_:
            if not 0 <= comp < self.n_states:
                raise DimensionError(f"component {comp} out of range [0, {self.n_states})")
            reg = regressors[comp]
            if not hasattr(reg, "alpha_") or not hasattr(reg, "L_"):
                raise TypeError(f"regressor for component {comp} is not fitted")
            kind, amp2, ls = _parse_kernel(reg.kernel_)
            x_train = np.asarray(reg.X_train_, float)
            if x_train.ndim != 2 or x_train.shape[1] != self.n_states:
                raise DimensionError(
                    f"regressor {comp} was trained on inputs of shape {x_train.shape}, "
                    f"expected (Q, {self.n_states})"
                )
            y_mean = float(np.ravel(getattr(reg, "_y_train_mean", 0.0))[0])
            y_std = float(np.ravel(getattr(reg, "_y_train_std", 1.0))[0])
            ls = np.broadcast_to(ls, (self.n_states,))
            parts.append((kind, amp2, ls, x_train, np.ravel(reg.alpha_), reg.L_, y_mean, y_std))
        self._parts = parts

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation of ``omega`` at one state (n,), jittable."""
        mean = jnp.zeros(self.n_states)
        var = jnp.zeros(self.n_states)
        for comp, (kind, amp2, ls, xt, alpha, chol, y_mean, y_std) in zip(
            self.components_, self._parts, strict=True
        ):
            r = (jnp.asarray(xt) - x) / jnp.asarray(ls)
            d2 = jnp.sum(r * r, -1)
            if kind == "se":
                k = amp2 * jnp.exp(-0.5 * d2)
            else:
                s = jnp.sqrt(5.0 * d2)
                k = amp2 * (1 + s + 5.0 * d2 / 3.0) * jnp.exp(-s)
            v = solve_triangular(jnp.asarray(chol), k, lower=True)
            mean = mean.at[comp].set(y_std * (k @ jnp.asarray(alpha)) + y_mean)
            var = var.at[comp].set(y_std**2 * jnp.maximum(amp2 - v @ v, 0.0))
        return mean, jnp.sqrt(var)
