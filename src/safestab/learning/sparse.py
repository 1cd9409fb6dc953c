"""A GP for large data: inducing points with the DTC/VFE posterior, cost O(Q M^2) to fit.

The exact GP conditions on all ``Q`` rows with one ``Q x Q`` Cholesky factor per component
(``O(Q^3)`` time, ``8 Q^2`` bytes: 80 GB at ``Q = 100,000``). :class:`SparseGP` instead

1. fits the hyperparameters on a random subset of ``hyper_subset`` rows (as
   ``GaussianProcessModel.fit(..., hyper_subset=...)`` does), then
2. picks ``M`` inducing inputs ``Z`` among all training inputs (greedy pivoted Cholesky of the
   prior, the rules of :class:`~safestab.learning.FastGP`), and
3. conditions the inducing values on all ``Q`` rows with the deterministic training
   conditional (DTC; the predictive of Titsias's variational bound): with
   ``Lj Lj^T = K_ZZ + eps I``, ``a(x) = Lj^-1 k_Z(x)``, ``V = Lj^-1 K_ZX`` (accumulated over
   row chunks, never stored) and ``B = I + V V^T / s^2 = LB LB^T``:

       mean(x) = mu + a(x) . B^-1 V (y - mu) / s^2
       var(x)  = k(x, x) - |a(x)|^2 + |LB^-1 a(x)|^2.

   The first two terms of the variance are the prior's residual given the inducing values,
   the last the posterior variance of the inducing part. With ``Z`` all training inputs the
   two formulas are the exact posterior.

There is **no proof** that this band contains the exact posterior band (the DTC variance
can be below the exact one, and its mean differs from the exact mean). Use it with a
calibrated ``beta``: :func:`~safestab.learning.conformal_beta` on trajectories not used to
fit gives the guarantee ``P(a new trajectory inside m +- beta sigma) >= 1 - delta``
(docs/learning.md, "Large data").
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

from .._validation import check_finite, check_real, check_scalar_range
from ..errors import DimensionError, ParameterError
from ._checks import check_count, check_seed
from ._posterior import kernel_error_coefficient
from ._threads import fit_threads
from .fast import InducingBand, inducing_inputs
from .gp import DEFAULT_JITTER, GaussianProcessModel
from .kernels import StationaryKernel, as_kernel

__all__ = ["SparseGP"]


class SparseGP(InducingBand):
    """Inducing-point GP (DTC/VFE posterior) for ``Q`` up to 1e5 rows and more.

    Parameters
    ----------
    n_inducing : int
        ``M``, most inducing inputs per component (default 256). The pivoted Cholesky stops
        earlier once the prior is resolved at the data (``pivot_tol``; ``noise_tol``: once the
        largest residual prior std at the training inputs is below ``noise_tol`` noise stds).
    kernel : StationaryKernel or {"se", "matern52"}
        As :class:`~safestab.learning.GaussianProcessModel`'s (stored by name).
    mean : {"zero", "constant"}
        Prior mean, as :class:`~safestab.learning.GaussianProcessModel`'s (``"constant"`` for
        targets with a large offset, which the fit warns about).
    noise : float or array of shape (k,), optional
        Known noise standard deviation per learned component; fitted when omitted.
    jitter : float
        Relative diagonal jitter (:data:`~safestab.learning.gp.DEFAULT_JITTER`).
    max_iter, n_restarts : int
        The hyperparameter fit's L-BFGS-B iteration limit and seeded random starts (defaults
        200 and 2). With ``mean``, ``noise`` and ``jitter`` these are the arguments of
        :class:`~safestab.learning.GaussianProcessModel` that its fit's warnings advise;
        checked as it checks them.
    hyper_subset : int
        Rows (drawn at random) on which the hyperparameters are fitted (default 500, as the
        ACC presets: the fit costs O(hyper_subset^3) per likelihood evaluation).
    pivot_tol, noise_tol : float
        The pivoted Cholesky's stopping rules (defaults 1e-10 and 0.1).
    chunk : int
        Rows per block when the inducing values are conditioned on the data (default 8192):
        memory ``O(M chunk)`` besides the data.

    Attributes
    ----------
    model : GaussianProcessModel
        The GP fitted on the hyperparameter subset (kernel, input scaling, hyperparameters).
    n_inducing_ : array of shape (k,)
        Inducing inputs used per learned component.
    inducing_ : array of shape (k, M, n)
        The inducing inputs, padded with zeros to a common ``M``.
    n_samples_ : int
        ``Q``, the rows conditioned on.

    Notes
    -----
    A query costs ``M`` kernel evaluations and a ``3M x M`` matrix-vector product per
    component (:class:`~safestab.learning.FastGP`'s evaluation, whose third block, the cross
    term's, is zero here); ``mean_std`` is jittable, so the
    controllers use it as any uncertainty model. Its std is not a proven bound on the
    exact posterior std: calibrate ``beta`` (module docstring).
    """

    proven = False  # the DTC band: no proof that it contains the exact band

    def __init__(
        self,
        n_inducing: int = 256,
        *,
        kernel: StationaryKernel | str = "se",
        mean: str = "zero",
        noise: Any = None,
        jitter: float = DEFAULT_JITTER,
        max_iter: int = 200,
        n_restarts: int = 2,
        hyper_subset: int = 500,
        pivot_tol: float = 1e-10,
        noise_tol: float = 0.1,
        chunk: int = 8192,
    ) -> None:
        self.n_inducing = check_count("n_inducing", n_inducing)
        self.kernel = as_kernel(kernel).name
        # checked by the exact model's constructor, which names each argument
        GaussianProcessModel(kernel, mean, noise, jitter, max_iter, n_restarts)  # type: ignore[arg-type]
        self.mean, self.noise, self.jitter = mean, noise, float(jitter)
        self.max_iter, self.n_restarts = int(max_iter), int(n_restarts)
        self.hyper_subset = check_count("hyper_subset", hyper_subset)
        if self.hyper_subset < 2:
            raise ParameterError(f"hyper_subset must be an integer >= 2, got {hyper_subset!r}")
        check_scalar_range("pivot_tol", pivot_tol, lower=0.0)
        check_scalar_range("noise_tol", noise_tol, lower=0.0)
        self.pivot_tol, self.noise_tol = float(pivot_tol), float(noise_tol)
        self.chunk = check_count("chunk", chunk)
        self.min_beta = 1.0

    def fit(self, x: Any, y: Any, *, seed: int = 0) -> SparseGP:
        """Fit the hyperparameters on a subset, then condition on all rows.

        Parameters
        ----------
        x, y : arrays of shape (Q, n)
            States and targets (``y`` the measured ``omega``; columns that are all zero are
            not learned, as in :class:`~safestab.learning.GaussianProcessModel`).
        seed : int
            Draws the hyperparameter subset and seeds the fit's restarts.

        Raises
        ------
        InputTypeError, DimensionError, NonFiniteError
            For bad ``x`` or ``y`` (named).
        """
        check_real("x", x)
        check_real("y", y)
        x, y = np.asarray(x, float), np.asarray(y, float)
        if x.ndim != 2 or y.shape != x.shape:
            raise DimensionError(
                f"x and y must have the same shape (Q, n), got {x.shape} and {y.shape}"
            )
        check_finite("x", x)
        check_finite("y", y)
        seed = check_seed("seed", seed)
        with fit_threads():  # one BLAS thread (learning/_threads.py)
            q = x.shape[0]
            rng = np.random.default_rng(seed)
            sub = np.sort(rng.choice(q, size=min(self.hyper_subset, q), replace=False))
            model = GaussianProcessModel(
                kernel=self.kernel, mean=self.mean, noise=self.noise, jitter=self.jitter,  # type: ignore[arg-type]
                max_iter=self.max_iter, n_restarts=self.n_restarts,
            )  # fmt: skip
            model.fit(x[sub], y[sub], hyper_subset=len(sub), seed=seed)
            self.model = model
            self.n_states = model.n_states_
            self.components_ = model.components_
            self.n_samples_ = q
            xs = (x - model.x_offset_) / model.x_scale_
            zs, packed = [], []
            for j, comp in enumerate(model.components_):
                noise = float(model.noise_[j])
                kfn, z, kzz, lj, _, _ = inducing_inputs(
                    model, j, xs, self.n_inducing, self.pivot_tol, self.noise_tol * noise
                )
                m = len(z)
                target = y[:, comp] - float(model.mean_[j])
                vvt, vy = np.zeros((m, m)), np.zeros(m)
                for s in range(0, q, self.chunk):
                    v = scipy.linalg.solve_triangular(
                        lj, kfn(z, xs[s : s + self.chunk], pad=(True, False)), lower=True
                    )
                    vvt += v @ v.T
                    vy += v @ target[s : s + self.chunk]
                lb = np.linalg.cholesky(np.eye(m) + vvt / noise**2)
                li = scipy.linalg.solve_triangular(lj, np.eye(m), lower=True)  # Lj^-1
                w = scipy.linalg.cho_solve((lb, True), vy) / noise**2  # B^-1 V (y - mu) / s^2
                # the DTC variance's second term |LB^-1 a|^2 with a = Lj^-1 k = Lj^T c
                g = scipy.linalg.solve_triangular(lb, lj.T, lower=True)
                b = li.T @ w
                ls = np.asarray(model.lengthscale_std_[j])
                packed.append({
                    "li": li, "kzz": kzz, "g": g, "cm": np.zeros((m, m)), "b": b,
                    "rho_b": np.zeros(m), "err": 0.0,
                    "ek": kernel_error_coefficient(model.kernel, np.max(np.abs(z), 0) / ls),
                    "gnorm": np.linalg.norm(g), "bnorm": np.sum(np.abs(b)), "rho_err": 0.0,
                    "rho": 0.0, "wnorm": 0.0, "cnorm": 0.0,
                })  # fmt: skip
                zs.append(z)
            # no mean-error term: the DTC band itself (proven = False), with its rounding
            self._pack(model, zs, packed)
        return self

    def mean_std(self, x: Any) -> tuple[Any, Any]:
        """Mean and std (the DTC band, not a proven bound) at one state (n,); jittable."""
        return super().mean_std(x)

    def arrays(self) -> dict[str, np.ndarray]:
        """Copies of the arrays, keys as :meth:`FastGP.arrays`.

        ``err``, ``rho_b`` and ``rho_err`` are zero: the DTC band, not a proven one.
        """
        return super().arrays()
