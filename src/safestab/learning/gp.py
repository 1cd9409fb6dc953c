"""Independent Gaussian processes for the components of ``omega(x)`` (eqs. (12), (13)).

Kernels and the marginal likelihood come from tinygp; hyperparameters are fitted by
maximising the log marginal likelihood with SciPy's L-BFGS-B on JAX gradients. Prediction
uses a Cholesky factor computed once at fit time.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jax.scipy.linalg import cho_solve, solve_triangular
from tinygp import GaussianProcess, kernels, transforms

from .._validation import check_finite, check_scalar_range
from ..errors import DimensionError, NumericalError, ParameterError

__all__ = ["GaussianProcessModel", "KERNELS", "DEFAULT_JITTER"]

KERNELS = ("se", "matern52")
#: Added to the diagonal, relative to the signal variance ``amplitude^2``, before every
#: Cholesky factorisation: 1e-10 keeps K + sigma^2 I positive definite in float64 for
#: Q up to tens of thousands even with sigma = 0, and shifts the posterior variance by at
#: most about 1e-10 amplitude^2.
DEFAULT_JITTER = 1e-10
_FORMAT = "safestab-gp-v1"


def _kernel(kind: str, amplitude, lengthscale):
    # tinygp's Matern kernels default to the L1 distance, which is not positive definite in
    # more than one dimension; the Matern 5/2 of GP regression (GPML, scikit-learn) is L2.
    base: kernels.Kernel
    if kind == "se":
        base = kernels.ExpSquared()
    else:
        base = kernels.Matern52(distance=kernels.distance.L2Distance())
    return amplitude**2 * transforms.Linear(1.0 / lengthscale, base)


def _unpack(theta, n_features):
    log_amp, log_noise, mean = theta[0], theta[1], theta[2]
    log_ls = theta[3 : 3 + n_features]
    return jnp.exp(log_amp), jnp.exp(log_noise), mean, jnp.exp(log_ls)


class GaussianProcessModel:
    """n independent GPs, one per learned component of ``omega``.

    Parameters
    ----------
    kernel : {"se", "matern52"}
        ARD squared-exponential or ARD Matern 5/2 kernel.
    mean : {"zero", "constant"}
        Prior mean: zero, or a constant fitted with the other hyperparameters.
    noise : float or array of shape (k,), optional
        Known noise standard deviation ``sigma_epsilon`` per component; fitted when omitted.
    jitter : float
        Relative diagonal jitter (see :data:`DEFAULT_JITTER`).
    max_iter : int
        L-BFGS-B iteration limit per component.

    Attributes
    ----------
    n_states_ : int
    components_ : tuple of int
        The learned components; the others are treated as exact (mean 0, std 0).
    x_train_ : array of shape (Q, n)
    amplitude_, noise_, mean_ : arrays of shape (k,)
    lengthscale_ : array of shape (k, n)
        In the units of ``x``.
    log_marginal_likelihood_ : array of shape (k,)
        At the fitted hyperparameters, on the data used to fit them.
    chol_ : array of shape (k, Q, Q)
        Cholesky factor of ``K + (sigma^2 + jitter amplitude^2) I`` per component.
    alpha_ : array of shape (k, Q)
        ``(K + ...)^-1 (y - mean)``.
    """

    def __init__(
        self,
        kernel: Literal["se", "matern52"] = "se",
        mean: Literal["zero", "constant"] = "zero",
        noise: Any = None,
        jitter: float = DEFAULT_JITTER,
        max_iter: int = 200,
    ) -> None:
        if kernel not in KERNELS:
            raise ParameterError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        if mean not in ("zero", "constant"):
            raise ParameterError(f"mean must be 'zero' or 'constant', got {mean!r}")
        if noise is not None:
            check_scalar_range("noise", noise, lower=0.0)
        check_scalar_range("jitter", jitter, lower=0.0)
        self.kernel = kernel
        self.mean = mean
        self.noise = noise
        self.jitter = float(jitter)
        self.max_iter = int(max_iter)

    # ------------------------------------------------------------------------------ fit

    def fit(
        self,
        x: Any,
        y: Any,
        *,
        components: Any = None,
        hyper_subset: int | None = None,
        seed: int = 0,
    ) -> GaussianProcessModel:
        """Fit hyperparameters by maximum marginal likelihood and condition on the data.

        Parameters
        ----------
        x : array of shape (Q, n)
            States.
        y : array of shape (Q, n)
            Targets ``omega(x) + noise``.
        components : sequence of int, optional
            Components to learn (default: all). Components known to be exact are skipped.
        hyper_subset : int, optional
            Fit hyperparameters on a random subset of this many rows, then condition on all
            ``Q`` rows: cost ``O(hyper_subset^3)`` per optimiser step instead of ``O(Q^3)``.
        seed : int
            Seeds the subset.

        Returns
        -------
        self

        Raises
        ------
        DimensionError
            If ``x`` and ``y`` are not (Q, n) arrays of equal shape, or a component index is
            out of range.
        NonFiniteError
            If the data contain NaN or inf.
        ParameterError
            If there are too few samples for the hyperparameters.
        NumericalError
            If the Cholesky factorisation fails.
        """
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if x.ndim != 2:
            raise DimensionError(f"x must have shape (Q, n), got shape {x.shape}")
        if y.shape != x.shape:
            raise DimensionError(
                f"y must have the same shape as x, (Q, n) = {x.shape}, got {y.shape}"
            )
        check_finite("x", x)
        check_finite("y", y)
        q, n = x.shape
        comps = tuple(range(n)) if components is None else tuple(int(c) for c in components)
        if not comps or any(c < 0 or c >= n for c in comps) or len(set(comps)) != len(comps):
            raise DimensionError(
                f"components must be distinct indices in [0, {n}), got {components!r}"
            )
        n_hyper = n + 2 + (self.mean == "constant") - (self.noise is not None)
        n_fit = q if hyper_subset is None else min(int(hyper_subset), q)
        if n_fit <= n_hyper:
            raise ParameterError(
                f"too few samples to fit {n_hyper} hyperparameters per component: got "
                f"{n_fit}, need at least {n_hyper + 1} (more in practice, or fix noise=)"
            )
        noise = None
        if self.noise is not None:
            noise = np.broadcast_to(np.asarray(self.noise, float), (len(comps),))

        offset = x.mean(0)
        scale = x.std(0)
        scale = np.where(scale > 0, scale, 1.0)
        xs = (x - offset) / scale
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(q, n_fit, replace=False)) if n_fit < q else np.arange(q)

        amps, noises, means, lss, lmls = [], [], [], [], []
        for j, comp in enumerate(comps):
            fixed = None if noise is None else float(noise[j])
            theta, lml = self._fit_component(xs[idx], y[idx, comp], fixed)
            amp, nz, mu, ls = (np.asarray(v) for v in _unpack(jnp.asarray(theta), n))
            if fixed is not None:
                nz = np.asarray(fixed)
            amps.append(float(amp))
            noises.append(float(nz))
            means.append(float(mu) if self.mean == "constant" else 0.0)
            lss.append(ls)
            lmls.append(lml)

        self.n_states_ = n
        self.components_ = comps
        self.x_train_ = x
        self.y_train_ = y[:, list(comps)]
        self.x_offset_ = offset
        self.x_scale_ = scale
        self.amplitude_ = np.array(amps)
        self.noise_ = np.array(noises)
        self.mean_ = np.array(means)
        self._lengthscale_std = np.array(lss)
        self.lengthscale_ = self._lengthscale_std * scale
        self.log_marginal_likelihood_ = np.array(lmls)
        self._condition()
        return self

    def _nll(self, theta, xs, y, fixed_log_noise):
        amp, noise, mean, ls = _unpack(theta, xs.shape[1])
        if fixed_log_noise is not None:
            noise = jnp.exp(fixed_log_noise)
        if self.mean == "zero":
            mean = 0.0
        gp = GaussianProcess(
            _kernel(self.kernel, amp, ls), xs, diag=noise**2 + self.jitter * amp**2, mean=mean
        )
        return -gp.log_probability(y)

    def _fit_component(self, xs, y, fixed_noise):
        n = xs.shape[1]
        sd = float(np.std(y)) or 1.0
        theta0 = np.concatenate(
            [
                [
                    np.log(sd),
                    np.log(0.1 * sd),
                    float(np.mean(y)) if self.mean == "constant" else 0.0,
                ],
                np.zeros(n),
            ]
        )
        bounds = [
            (np.log(1e-6 * sd), np.log(1e3 * sd)),
            (np.log(1e-6 * sd), np.log(10 * sd)),
            (None, None) if self.mean == "constant" else (0.0, 0.0),
        ] + [(np.log(1e-3), np.log(1e3))] * n
        fixed_log = None if fixed_noise is None else np.log(max(fixed_noise, 1e-300))
        if fixed_noise is not None and fixed_noise == 0.0:
            fixed_log = -np.inf  # exp(-inf) = 0: noise-free, jitter only
        xs_j, y_j = jnp.asarray(xs), jnp.asarray(y)
        vg = jax.jit(jax.value_and_grad(lambda t: self._nll(t, xs_j, y_j, fixed_log)))

        def fun(t):
            v, g = vg(jnp.asarray(t))
            return float(v), np.asarray(g, dtype=float)

        res = scipy.optimize.minimize(
            fun,
            theta0,
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"maxiter": self.max_iter},
        )
        if not np.isfinite(res.fun):
            raise NumericalError(
                "the marginal likelihood is not finite at the optimum; the kernel matrix is "
                "not positive definite: try increasing the noise (noise=) or jitter="
            )
        return res.x, -float(res.fun)

    def _condition(self) -> None:
        xs = jnp.asarray((self.x_train_ - self.x_offset_) / self.x_scale_)
        chols, alphas = [], []
        for j in range(len(self.components_)):
            amp, nz = self.amplitude_[j], self.noise_[j]
            k = _kernel(self.kernel, amp, jnp.asarray(self._lengthscale_std[j]))(xs, xs)
            k = k + (nz**2 + self.jitter * amp**2) * jnp.eye(xs.shape[0])
            chol = jnp.linalg.cholesky(k)
            if not bool(jnp.all(jnp.isfinite(chol))):
                raise NumericalError(
                    f"Cholesky factorisation failed for component {self.components_[j]}: the "
                    "kernel matrix is not positive definite; try increasing the noise (noise=) "
                    "or jitter="
                )
            alphas.append(cho_solve((chol, True), jnp.asarray(self.y_train_[:, j]) - self.mean_[j]))
            chols.append(chol)
        self.chol_ = np.asarray(jnp.stack(chols))
        self.alpha_ = np.asarray(jnp.stack(alphas))
        self._build_predictors()

    def _build_predictors(self) -> None:
        xs = jnp.asarray((self.x_train_ - self.x_offset_) / self.x_scale_)
        offset, scale = jnp.asarray(self.x_offset_), jnp.asarray(self.x_scale_)
        chol, alpha = jnp.asarray(self.chol_), jnp.asarray(self.alpha_)
        amp, ls, mu = (
            jnp.asarray(self.amplitude_),
            jnp.asarray(self._lengthscale_std),
            jnp.asarray(self.mean_),
        )
        comps = jnp.asarray(self.components_)
        n, kind = self.n_states_, self.kernel

        def one(x):
            z = ((x - offset) / scale)[None, :]

            def per_comp(a, l_, al, L, m):
                kstar = _kernel(kind, a, l_)(xs, z)[:, 0]
                v = solve_triangular(L, kstar, lower=True)
                return kstar @ al + m, jnp.maximum(a**2 - v @ v, 0.0)

            mean_c, var_c = jax.vmap(per_comp)(amp, ls, alpha, chol, mu)
            mean = jnp.zeros(n).at[comps].set(mean_c)
            var = jnp.zeros(n).at[comps].set(var_c)
            return mean, var

        self._predict_one = one
        # built once: a fresh jit(vmap(...)) per predict() call would re-trace and recompile
        self._predict_batch = jax.jit(jax.vmap(one))

    # -------------------------------------------------------------------------- predict

    def _check_fitted(self) -> None:
        if not hasattr(self, "alpha_"):
            raise RuntimeError("this GaussianProcessModel is not fitted yet; call fit(x, y) first")

    def predict(self, x: Any) -> tuple[jax.Array, jax.Array]:
        """Posterior mean and variance of ``omega`` at states ``x``, eqs. (12), (13).

        Parameters
        ----------
        x : array of shape (..., n)

        Returns
        -------
        mean : array of shape (..., n)
        var : array of shape (..., n)
            Variance of the latent ``omega_i`` (without the noise); 0 for skipped components.
            Rounding can make ``k(x, x) - k_*^T (K + sigma^2 I)^-1 k_*`` slightly negative; it is
            floored at 0.
        """
        self._check_fitted()
        x = jnp.asarray(x, dtype=float)
        if x.ndim == 0 or x.shape[-1] != self.n_states_:
            raise DimensionError(f"x must have shape (..., {self.n_states_}), got shape {x.shape}")
        flat = x.reshape((-1, self.n_states_))
        mean, var = self._predict_batch(flat)
        return mean.reshape(x.shape), var.reshape(x.shape)

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation at one state of shape (n,) (jittable)."""
        self._check_fitted()
        mean, var = self._predict_one(x)
        return mean, jnp.sqrt(var)

    @property
    def n_states(self) -> int:
        """State dimension (for the :class:`~safestab.robust.UncertaintyModel` protocol)."""
        self._check_fitted()
        return self.n_states_

    # ------------------------------------------------------------------------ save/load

    def save(self, path: str | Path) -> None:
        """Write the fitted model to a ``.npz`` file (plain arrays and JSON; no pickle)."""
        self._check_fitted()
        meta = {
            "format": _FORMAT,
            "kernel": self.kernel,
            "mean": self.mean,
            "jitter": self.jitter,
            "components": list(self.components_),
            "n_states": self.n_states_,
        }
        np.savez(
            Path(path),
            meta=np.array(json.dumps(meta)),
            x_train=self.x_train_,
            y_train=self.y_train_,
            x_offset=self.x_offset_,
            x_scale=self.x_scale_,
            amplitude=self.amplitude_,
            noise=self.noise_,
            mean=self.mean_,
            lengthscale_std=self._lengthscale_std,
            log_marginal_likelihood=self.log_marginal_likelihood_,
        )

    @classmethod
    def load(cls, path: str | Path) -> GaussianProcessModel:
        """Read a model written by :meth:`save`; the Cholesky factor is recomputed."""
        with np.load(Path(path), allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") != _FORMAT:
                raise ValueError(
                    f"{path} is not a safestab GP file (format {meta.get('format')!r})"
                )
            model = cls(kernel=meta["kernel"], mean=meta["mean"], jitter=meta["jitter"])
            model.n_states_ = int(meta["n_states"])
            model.components_ = tuple(meta["components"])
            model.x_train_ = data["x_train"]
            model.y_train_ = data["y_train"]
            model.x_offset_ = data["x_offset"]
            model.x_scale_ = data["x_scale"]
            model.amplitude_ = data["amplitude"]
            model.noise_ = data["noise"]
            model.mean_ = data["mean"]
            model._lengthscale_std = data["lengthscale_std"]
            model.lengthscale_ = model._lengthscale_std * model.x_scale_
            model.log_marginal_likelihood_ = data["log_marginal_likelihood"]
        model._condition()
        return model
