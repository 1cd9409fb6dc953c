"""Use fitted scikit-learn ``GaussianProcessRegressor`` models as the uncertainty model.

The adapter reads the fitted kernel, training inputs and Cholesky factor of each regressor
and evaluates its latent posterior with the package's one posterior module
(:func:`safestab.learning._posterior.exact_point`, the exact GP's own arithmetic), so a
controller built on it is jittable. scikit-learn's ``normalize_y`` is folded into the factors:
with ``y = s y' + m``, the posterior of ``y`` is that of a GP with amplitude ``s a``, Cholesky
factor ``s L``, weights ``alpha / s`` and constant mean ``m``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DimensionError
from ._posterior import exact_point
from ._predict import Predictor
from .kernels import Matern52, SquaredExponential, StationaryKernel

__all__ = ["SklearnGPAdapter"]


def _parse_kernel(kernel: Any) -> tuple[StationaryKernel, float, np.ndarray]:
    """Return (kernel, amplitude^2, lengthscale) of ``C * RBF``/``C * Matern(2.5)`` (+ White)."""
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
        return Matern52(), amp2, np.atleast_1d(np.asarray(kernel.length_scale, float))
    if isinstance(kernel, K.RBF):
        return SquaredExponential(), amp2, np.atleast_1d(np.asarray(kernel.length_scale, float))
    raise TypeError(f"unsupported kernel {kernel}: expected RBF or Matern(nu=2.5)")


class SklearnGPAdapter(Predictor):
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
            post = {
                "xs": x_train,
                "offset": np.zeros(self.n_states),
                "scale": np.ones(self.n_states),
                "chol": (y_std * np.asarray(reg.L_, float))[None],
                "alpha": (np.ravel(reg.alpha_) / y_std)[None],
                "amp": np.array([np.sqrt(amp2) * y_std]),
                "mu": np.array([y_mean]),
                "ls": np.asarray(ls, float)[None],
                "comps": np.array([comp]),
            }
            parts.append((kind, post))
        self._parts = parts

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation of ``omega`` at one state (n,), jittable."""
        mean = jnp.zeros(self.n_states)
        var = jnp.zeros(self.n_states)
        for kind, post in self._parts:  # one component each (their training sets may differ)
            m, v = exact_point(post, x, kind, self.n_states)
            mean, var = mean + m, var + v
        return mean, jnp.sqrt(var)

    def _predict_rows(self, x: np.ndarray) -> tuple[jax.Array, jax.Array]:
        # predict(x, return_std=False): Predictor's, over mean_std mapped with jax.vmap
        return jax.vmap(self.mean_std)(jnp.asarray(x))
