"""Independent Gaussian processes for the components of ``omega(x)`` (eqs. (12), (13)).

Kernels come from tinygp; hyperparameters are fitted by maximising the log marginal
likelihood with SciPy's L-BFGS-B on JAX gradients, from several starts (data-driven and
seeded random ones; ``safestab.learning._likelihood``). Prediction uses a Cholesky factor
computed once at fit time; the compiled predictor receives the training arrays as arguments,
so compiling it costs the same at every ``Q`` (``safestab.learning._posterior`` holds the
posterior arithmetic, shared with FastGP and the batched forms).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import solve_triangular

from .._batching import device_array
from .._numerics import safe_sqrt
from .._validation import check_finite, check_real, check_scalar_range, is_concrete
from .._values import register_model
from ..errors import (
    DataWarning,
    DimensionError,
    NumericalError,
    ParameterError,
)
from ._checks import check_fitted, check_seed
from ._likelihood import fit_components, pose_component
from ._posterior import exact_point, factor, panels, predict_batch
from ._predict import Predictor
from ._threads import fit_threads
from .kernels import StationaryKernel, as_kernel

__all__ = [
    "GaussianProcessModel",
    "DEFAULT_JITTER",
    "MIN_ROWS_PER_HYPERPARAMETER",
    "LOO_ROWS",
    "LOO_MIN_COVERAGE",
]

#: Added to the diagonal, relative to the signal variance ``amplitude^2``, before every
#: Cholesky factorisation: 1e-10 keeps K + sigma^2 I positive definite in float64 for
#: Q up to tens of thousands even with sigma = 0. It is part of the model's noise: the
#: reported ``noise_`` is the effective ``sqrt(sigma^2 + jitter amplitude^2)``.
DEFAULT_JITTER = 1e-10
#: Fewer fitting rows than this many per hyperparameter raise a :class:`DataWarning`: a
#: rule of thumb, not a theorem (with 5 rows for 5 hyperparameters the ACC fit covered 21 %
#: of held-out states at beta = 2).
MIN_ROWS_PER_HYPERPARAMETER = 5
#: Largest data magnitude :meth:`GaussianProcessModel.fit` accepts: the fit squares the data
#: (variances, squared distances), which overflow float64 beyond about 1e154.
MAX_DATA_MAGNITUDE = 1e150
#: Rows (at most) of the leave-one-out check run after every fit.
LOO_ROWS = 64
#: A leave-one-out coverage at 2 predictive standard deviations below this raises a
#: :class:`DataWarning` (a calibrated model gives 0.954; below 0.5 the predictive band is far
#: too narrow, e.g. ``noise=0`` on noisy data).
LOO_MIN_COVERAGE = 0.5
#: Data-driven starts of the hyperparameter search (the others are seeded random ones).
N_DATA_STARTS = 2
_FORMAT = "safestab-gp-v2"  # v2: ``noise`` is the effective noise (jitter included)
_FORMAT_V1 = "safestab-gp-v1"


def _components(components: Any, n: int) -> tuple[int, ...]:
    """The learned components: all ``n`` by default, else distinct indices in ``[0, n)``."""
    comps = tuple(range(n)) if components is None else tuple(int(c) for c in components)
    if not comps or any(c < 0 or c >= n for c in comps) or len(set(comps)) != len(comps):
        raise DimensionError(f"components must be distinct indices in [0, {n}), got {components!r}")
    return comps


def _standardisation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The training inputs' offset and scale (their mean and std per coordinate).

    A constant coordinate's std can round above 0 (0.7 repeated: 1e-16), which would blow
    its rounding up to unit size: it is scaled by 1, as a zero std is.
    """
    scale = x.std(0)
    return x.mean(0), np.where((scale > 0) & ~np.all(x == x[0], axis=0), scale, 1.0)


#: The training inputs' design is rank-deficient (a :class:`DataWarning`) where the smallest
#: singular value of the centred, standardised inputs is below this fraction of the largest:
#: an exact linear relation between coordinates leaves about 1e-15 of rounding; a coordinate
#: that varies independently, far more (a uniform draw of 300 rows in 3 coordinates: 0.8).
DESIGN_RANK_TOL = 1e-8


def _check_design(x: np.ndarray) -> None:
    """Raise where every row of ``x`` (Q, n) is one state; warn where its columns are dependent.

    Raises
    ------
    ParameterError
        If all ``Q`` rows of ``x`` are the same state: a GP cannot learn how ``omega`` varies
        with ``x`` from them (held-out coverage 0.000 on such data, std 1e-6).

    Warns
    -----
    DataWarning
        If the centred varying coordinates have a lower rank than their count (one is a
        linear combination of the others): the lengthscales along the missing directions are
        not identified and the prediction off the data's subspace is the prior's. An exactly
        constant coordinate (held fixed while the data were taken) is not warned about: the
        data say nothing along it, and the prediction there is the prior's.
    """
    q, n = x.shape
    if q > 1 and np.all(x == x[0]):
        raise ParameterError(
            f"x has all {q} rows at one state {np.array2string(x[0], precision=4)}: a GP "
            "cannot learn how omega varies with x from them (it would report a near-zero "
            "std wherever it is asked); collect data at distinct states"
        )
    # an exactly constant coordinate (a quantity held fixed while the data were taken: the
    # ACC's lead speed) is left out of the check: it is scaled by 1, its lengthscale is the
    # fit's bound, and the prediction along it is the prior's (documented, not warned)
    varying = ~np.all(x == x[0], axis=0)
    xs = x[:, varying]
    centred = xs - xs.mean(0)
    scale = np.sqrt(np.mean(centred**2, 0))
    sv = np.linalg.svd(centred / np.where(scale > 0, scale, 1.0), compute_uv=False)
    rank = int(np.sum(sv > DESIGN_RANK_TOL * sv[0]))
    if rank < xs.shape[1]:
        warnings.warn(
            f"the training inputs are rank-deficient: x's varying coordinates "
            f"{np.flatnonzero(varying).tolist()} are linearly dependent (rank {rank} of "
            f"{xs.shape[1]} after centring): the data lie in a lower-dimensional set, the "
            "lengthscales across it are not identified and the GP predicts its prior off it; "
            "collect data that vary every coordinate independently, or fit on independent "
            "coordinates",
            DataWarning,
            stacklevel=3,
        )


@jax.jit
def _inverse_diagonal(chol: jax.Array, e: jax.Array) -> jax.Array:
    """``|L^-1 e_i|^2`` per column of ``e``: the diagonal of ``K^-1`` on those rows."""
    w = solve_triangular(chol, e, lower=True)
    return jnp.sum(w * w, 0)


class GaussianProcessModel(Predictor):
    """n independent GPs, one per learned component of ``omega``.

    Parameters
    ----------
    kernel : StationaryKernel or {"se", "matern52"}
        ARD squared-exponential or ARD Matern 5/2 kernel
        (:class:`~safestab.learning.SquaredExponential`,
        :class:`~safestab.learning.Matern52`), as an object or by name. The model stores
        the name (``kernel``), which its files carry.
    mean : {"zero", "constant"}
        Prior mean: zero, or a constant fitted with the other hyperparameters.
    noise : float or array of shape (k,), optional
        Known noise standard deviation ``sigma_epsilon`` per component; fitted when omitted.
    jitter : float
        Relative diagonal jitter (see :data:`DEFAULT_JITTER`); part of the effective noise.
    max_iter : int
        L-BFGS-B iteration limit per start and component; 0 keeps the best start values (with
        a :class:`~safestab.errors.ConvergenceWarning`).
    n_restarts : int
        Seeded random starts in addition to the :data:`N_DATA_STARTS` data-driven ones.
    n_threads : int, optional
        Where BLAS runs one thread
        (:func:`~safestab.learning.batched.one_blas_thread`; the studies and the Monte Carlo
        runner fit inside it), how many starts, of all components, :meth:`fit` optimises at
        once in threads; default one per CPU. The fit does not depend on this count. With a
        multi-threaded BLAS the starts run one after the other.

    Attributes
    ----------
    n_states_ : int
    components_ : tuple of int
        The learned components; the others are treated as exact (mean 0, std 0).
    x_train_ : array of shape (Q, n)
    amplitude_, mean_ : arrays of shape (k,)
    noise_ : array of shape (k,)
        Effective noise standard deviation ``sqrt(sigma^2 + jitter amplitude^2)``: the one the
        likelihood and the posterior use.
    lengthscale_ : array of shape (k, n)
        In the units of ``x``.
    x_offset_, x_scale_ : arrays of shape (n,)
        The inputs are standardised as ``(x - x_offset_) / x_scale_`` (mean and std of the
        training inputs; a zero std is replaced by 1).
    lengthscale_std_ : array of shape (k, n)
        Lengthscales of the standardised inputs (``lengthscale_ / x_scale_``): the ones the
        kernel is evaluated with.
    y_train_ : array of shape (Q, k)
        The learned components' targets.
    log_marginal_likelihood_ : array of shape (k,)
        At the fitted hyperparameters, on the data used to fit them.
    n_starts_ : int
        Optimiser starts per component.
    start_log_marginal_likelihoods_ : array of shape (k, n_starts_)
        Final log marginal likelihood of each start (-inf where it failed).
    n_iter_ : array of shape (k,)
        L-BFGS-B iterations of the retained start.
    converged_ : array of shape (k,)
        Whether the retained start met L-BFGS-B's convergence test.
    optimizer_status_ : tuple of str
        L-BFGS-B's message for the retained start, per component.
    loo_coverage_ : array of shape (k,)
        Leave-one-out coverage of the noisy targets at 2 predictive standard deviations, on
        at most :data:`LOO_ROWS` rows (0.954 for a calibrated model).
    chol_ : array of shape (k, Q, Q)
        Cholesky factor of ``K + noise_^2 I`` per component.
    alpha_ : array of shape (k, Q)
        ``(K + noise_^2 I)^-1 (y - mean)``.
    posterior_ : dict of str to jax.Array
        The arrays the compiled predictor takes as arguments (standardised training inputs
        ``xs`` (Q, n), ``offset`` and ``scale`` (n,), ``chol`` (k, Q, Q), ``alpha`` (k, Q),
        ``amp`` and ``mu`` (k,), ``ls`` (k, n), ``comps`` (k,)), on the device.
    """

    def __init__(
        self,
        kernel: StationaryKernel | Literal["se", "matern52"] = "se",
        mean: Literal["zero", "constant"] = "zero",
        noise: Any = None,
        jitter: float = DEFAULT_JITTER,
        max_iter: int = 200,
        n_restarts: int = 2,
        n_threads: int | None = None,
    ) -> None:
        kernel_name = as_kernel(kernel).name
        if mean not in ("zero", "constant"):
            raise ParameterError(f"mean must be 'zero' or 'constant', got {mean!r}")
        if noise is not None:
            check_scalar_range("noise", noise, lower=0.0)
        check_scalar_range("jitter", jitter, lower=0.0)
        for name, value in (("max_iter", max_iter), ("n_restarts", n_restarts)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
                raise ParameterError(f"{name} must be an integer >= 0, got {value!r}")
        if n_threads is not None and (
            isinstance(n_threads, bool)
            or not isinstance(n_threads, int | np.integer)
            or n_threads < 1
        ):
            raise ParameterError(f"n_threads must be None or an integer >= 1, got {n_threads!r}")
        self.kernel = kernel_name
        self.mean = mean
        self.noise = noise
        self.jitter = float(jitter)
        self.max_iter = int(max_iter)
        self.n_restarts = int(n_restarts)
        self.n_threads = None if n_threads is None else int(n_threads)

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
            Targets ``omega(x) + noise``. Only the learned components' columns are read (a
            NaN in a skipped column is allowed).
        components : sequence of int, optional
            Components to learn (default: all). Components known to be exact are skipped.
        hyper_subset : int, optional
            Fit hyperparameters on a random subset of this many rows, then condition on all
            ``Q`` rows: cost ``O(hyper_subset^3)`` per optimiser step instead of ``O(Q^3)``.
        seed : int
            Integer in ``[0, 2**32 - 1]``; seeds the subset, the random starts and the rows of
            the leave-one-out check.

        Returns
        -------
        self

        Raises
        ------
        DimensionError
            If ``x`` and ``y`` are not (Q, n) arrays of equal shape, or a component index is
            out of range.
        NonFiniteError
            If ``x`` or a learned column of ``y`` contains NaN or inf.
        ParameterError
            If there are too few samples for the hyperparameters, ``seed`` or
            ``hyper_subset`` is invalid, or the data exceed :data:`MAX_DATA_MAGNITUDE`.
        InputTypeError
            If ``x`` or ``y`` is not real (strings, complex, objects).
        NumericalError
            If every start fails or the Cholesky factorisation fails.

        Warns
        -----
        DataWarning
            Fewer than :data:`MIN_ROWS_PER_HYPERPARAMETER` rows per hyperparameter; exact
            duplicate rows; a zero-mean prior on targets with a large offset; a leave-one-out
            coverage below :data:`LOO_MIN_COVERAGE`.
        ConvergenceWarning
            The retained start did not converge, ``max_iter=0``, or the fitted noise or a
            lengthscale sits at its lower bound.

        Notes
        -----
        Starts: ``amplitude = scale(y)``, ``noise = 0.1 std(y)``, unit lengthscales (in
        standardised inputs); ``noise`` from nearest-neighbour differences with lengthscales
        3; and ``n_restarts`` draws with log-uniform amplitude (0.3 to 3 times the scale),
        noise (1e-3 to 0.3 std(y)) and lengthscales (0.3 to 30). ``scale(y)`` is ``std(y)``
        for ``mean="constant"`` and the root mean square of ``y`` for ``mean="zero"`` (a
        zero-mean prior must explain the offset with its amplitude).
        """
        seed = check_seed("seed", seed)
        with fit_threads():  # one BLAS thread (learning/_threads.py)
            check_real("x", x)
            check_real("y", y)
            x = np.asarray(x, dtype=float)
            y = np.asarray(y, dtype=float)
            if x.ndim != 2:
                raise DimensionError(f"x must have shape (Q, n), got shape {x.shape}")
            if y.shape != x.shape:
                raise DimensionError(
                    f"y must have the same shape as x, (Q, n) = {x.shape}, got {y.shape}"
                )
            q, n = x.shape
            comps = _components(components, n)
            check_finite("x", x)
            check_finite("y", y[:, list(comps)])  # skipped columns are never read
            for name, arr in (("x", x), ("y", y[:, list(comps)])):
                # the fit squares the data (variances, kernel distances): beyond 1e150 they overflow
                big = float(np.max(np.abs(arr))) if arr.size else 0.0
                if big > MAX_DATA_MAGNITUDE:
                    raise ParameterError(
                        f"{name} has entries up to {big:.3g} in magnitude; their squares overflow "
                        f"float64 (the fit needs |{name}| <= {MAX_DATA_MAGNITUDE:g}): rescale the "
                        "data, e.g. to units in which the values are of order one"
                    )
            if hyper_subset is not None and (
                isinstance(hyper_subset, bool)
                or not isinstance(hyper_subset, int | np.integer)
                or hyper_subset < 1
            ):
                raise ParameterError(f"hyper_subset must be an integer >= 1, got {hyper_subset!r}")
            n_hyper = n + 2 + (self.mean == "constant") - (self.noise is not None)
            n_fit = q if hyper_subset is None else min(int(hyper_subset), q)
            if n_fit <= n_hyper:
                raise ParameterError(
                    f"too few samples to fit {n_hyper} hyperparameters per component: got "
                    f"{n_fit}, need at least {n_hyper + 1} (more in practice, or fix noise=)"
                )
            _check_design(x)
            if n_fit < MIN_ROWS_PER_HYPERPARAMETER * n_hyper:
                warnings.warn(
                    f"only {n_fit} rows to fit {n_hyper} hyperparameters per component: the fit "
                    f"is unreliable (fewer than {MIN_ROWS_PER_HYPERPARAMETER} rows per "
                    "hyperparameter); collect more data or fix noise=, and check the band with "
                    "conformal_beta on held-out data",
                    DataWarning,
                    stacklevel=2,
                )
            noise = None
            if self.noise is not None:
                noise = np.broadcast_to(np.asarray(self.noise, float), (len(comps),))

            offset, scale = _standardisation(x)
            xs = (x - offset) / scale
            rng = np.random.default_rng(seed)
            idx = np.sort(rng.choice(q, n_fit, replace=False)) if n_fit < q else np.arange(q)
            self._warn_about_data(x[idx], y[idx][:, list(comps)], comps)

            # every component's problem first (in order: each draws its starts from rng), then
            # all their starts in one pool (fit_components)
            problems = [
                pose_component(
                    self,
                    xs[idx],
                    y[idx, comp],
                    None if noise is None else float(noise[j]),
                    rng,
                    comp,
                )
                for j, comp in enumerate(comps)
            ]
            fits = fit_components(self, problems)

            self._set_data(x, y, comps, offset, scale)
            self.amplitude_ = np.array([f["amplitude"] for f in fits])
            self.noise_ = np.array([f["noise"] for f in fits])
            self.mean_ = np.array([f["mean"] for f in fits])
            self.lengthscale_std_ = np.array([f["lengthscale"] for f in fits])
            self.lengthscale_ = self.lengthscale_std_ * scale
            self.log_marginal_likelihood_ = np.array([f["lml"] for f in fits])
            self.n_starts_ = len(fits[0]["start_lmls"])
            self.start_log_marginal_likelihoods_ = np.array([f["start_lmls"] for f in fits])
            self.n_iter_ = np.array([f["nit"] for f in fits], dtype=int)
            self.converged_ = np.array([f["converged"] for f in fits], dtype=bool)
            self.optimizer_status_ = tuple(f["message"] for f in fits)
            self._condition()
            self.loo_coverage_ = self._loo_coverage(rng)
            for comp, cov in zip(comps, self.loo_coverage_, strict=True):
                if cov < LOO_MIN_COVERAGE:
                    warnings.warn(
                        f"leave-one-out check of component {comp}: only {cov:.0%} of the training "
                        "targets lie within 2 predictive standard deviations of the prediction "
                        "from the other rows (0.954 expected): the model understates the noise "
                        "or the function's variation; do not fix noise= below the sensor's noise, "
                        "and check the band with conformal_beta",
                        DataWarning,
                        stacklevel=2,
                    )
            return self

    @classmethod
    def from_hyperparameters(
        cls,
        x: Any,
        y: Any,
        *,
        amplitude: Any,
        noise: Any,
        lengthscale: Any,
        mean: Any = None,
        kernel: StationaryKernel | Literal["se", "matern52"] = "se",
        components: Any = None,
        jitter: float = DEFAULT_JITTER,
        seed: int = 0,
    ) -> GaussianProcessModel:
        """A model with given hyperparameters conditioned on ``(x, y)``; no optimisation.

        For a new data set with the hyperparameters of an earlier fit (a Monte Carlo study's
        ``hyperparameters = "reuse"``): one Cholesky factorisation per component.

        Parameters
        ----------
        x, y : arrays of shape (Q, n)
            States and targets (only the learned columns of ``y`` are read).
        amplitude, noise : arrays of shape (k,)
            Signal std and *effective* noise std (as ``amplitude_`` and ``noise_`` of a
            fitted model: the jitter is not added again).
        lengthscale : array of shape (k, n)
            In the units of ``x`` (as ``lengthscale_``).
        mean : array of shape (k,), optional
            Constant prior mean (default 0; nonzero values make ``mean="constant"``).
        kernel : StationaryKernel or {"se", "matern52"}
        components : sequence of int, optional
            The ``k`` learned components (default: all ``n``).
        jitter : float
            Recorded as the model's ``jitter`` (already part of ``noise``).
        seed : int
            Seeds the rows of the leave-one-out check.

        Returns
        -------
        GaussianProcessModel
            ``log_marginal_likelihood_`` is on ``(x, y)``; nothing was optimised:
            ``n_starts_ = 0``, ``n_iter_ = 0``, ``converged_ = True`` and
            ``optimizer_status_`` says so.

        Raises
        ------
        DimensionError
            If ``x``, ``y``, the components or a hyperparameter have the wrong shape.
        NonFiniteError
            If ``x`` or a learned column of ``y`` contains NaN or inf.
        ParameterError
            If ``amplitude``, ``noise`` or ``lengthscale`` is not positive and finite, or
            ``kernel`` is unknown.
        NumericalError
            If the Cholesky factorisation fails.
        """
        seed = check_seed("seed", seed)
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if x.ndim != 2 or y.shape != x.shape:
            raise DimensionError(
                f"x and y must be (Q, n) arrays of equal shape, got {x.shape} and {y.shape}"
            )
        q, n = x.shape
        comps = _components(components, n)
        k = len(comps)
        mean = np.zeros(k) if mean is None else mean
        hyper = {}
        for name, value, shape in (
            ("amplitude", amplitude, (k,)),
            ("noise", noise, (k,)),
            ("lengthscale", lengthscale, (k, n)),
            ("mean", mean, (k,)),
        ):
            arr = np.asarray(value, dtype=float)
            if arr.shape != shape:
                raise DimensionError(f"{name} must have shape {shape}, got {arr.shape}")
            if name == "mean":
                check_finite(name, arr)
            else:
                check_scalar_range(name, arr, lower=0.0, strict_lower=True)
            hyper[name] = arr
        check_finite("x", x)
        check_finite("y", y[:, list(comps)])
        model = cls(kernel=kernel, mean="constant" if np.any(hyper["mean"] != 0) else "zero",
                    jitter=jitter)  # fmt: skip
        offset, scale = _standardisation(x)
        model._set_data(x, y, comps, offset, scale)
        model.amplitude_ = hyper["amplitude"]
        model.noise_ = hyper["noise"]
        model.mean_ = hyper["mean"]
        model.lengthscale_std_ = hyper["lengthscale"] / scale
        model.lengthscale_ = hyper["lengthscale"]
        with fit_threads():
            model._condition()
        # log p(y) = -1/2 (y - mu)^T alpha - sum log diag L - Q/2 log(2 pi)
        resid = model.y_train_ - model.mean_
        logdet = np.sum(np.log(np.diagonal(model.chol_, axis1=-2, axis2=-1)), -1)
        model.log_marginal_likelihood_ = (
            -0.5 * np.sum(resid.T * model.alpha_, -1) - logdet - 0.5 * q * np.log(2 * np.pi)
        )
        model.n_starts_ = 0
        model.start_log_marginal_likelihoods_ = np.zeros((k, 0))
        model.n_iter_ = np.zeros(k, dtype=int)
        model.converged_ = np.ones(k, dtype=bool)
        model.optimizer_status_ = ("hyperparameters given; no optimisation",) * k
        with fit_threads():
            model.loo_coverage_ = model._loo_coverage(np.random.default_rng(seed))
        return model

    def _warn_about_data(self, x: np.ndarray, y: np.ndarray, comps: tuple[int, ...]) -> None:
        rows = np.unique(np.concatenate([x, y], 1), axis=0).shape[0]
        if rows < x.shape[0]:
            warnings.warn(
                f"{x.shape[0] - rows} of the {x.shape[0]} fitting rows are exact duplicates "
                "(same x and y): the likelihood reads them as noise-free repeats and drives the "
                "noise down; remove them (np.unique(np.hstack([x, y]), axis=0)) or fix noise=",
                DataWarning,
                stacklevel=3,
            )
        if self.mean == "zero":
            for j, comp in enumerate(comps):
                mu, sd = float(np.mean(y[:, j])), float(np.std(y[:, j]))
                if abs(mu) > 10 * sd:
                    warnings.warn(
                        f"component {comp}: the targets have mean {mu:.3g}, more than 10 times "
                        f"their std {sd:.3g}; a zero-mean GP must explain the offset with its "
                        "amplitude, whose relative jitter then swamps the variation: use "
                        "mean='constant' or subtract the offset",
                        DataWarning,
                        stacklevel=3,
                    )

    def _set_data(self, x, y, comps, offset, scale) -> None:
        """Set the fitted attributes of the data (a fit and ``from_hyperparameters`` alike)."""
        self.n_states_ = x.shape[1]
        self.components_ = comps
        self.x_train_ = x
        self.y_train_ = y[:, list(comps)]
        self.x_offset_ = offset
        self.x_scale_ = scale

    def _condition(self) -> None:
        # host arrays go to the device by device_array (jnp.asarray would compile a program
        # per shape), and the factor is checked on the host
        xs = device_array((self.x_train_ - self.x_offset_) / self.x_scale_)
        chols, alphas = [], []
        for j in range(len(self.components_)):
            chol, alpha = factor(
                self.amplitude_[j], device_array(self.lengthscale_std_[j]), self.noise_[j], xs,
                device_array(self.y_train_[:, j]), self.mean_[j], kind=self.kernel,
            )  # fmt: skip
            if not np.all(np.isfinite(np.asarray(chol))):
                raise NumericalError(
                    f"Cholesky factorisation failed for component {self.components_[j]}: the "
                    "kernel matrix is not positive definite; try increasing the noise (noise=) "
                    "or jitter="
                )
            alphas.append(alpha)
            chols.append(chol)
        chol_all = jnp.stack(chols)
        del chols, chol  # one (k, Q, Q) factor in memory, not two (6 GB at Q = 10,000)
        alpha_all = jnp.stack(alphas)
        self.chol_ = np.asarray(chol_all)  # a read-only view of the same buffer on CPU
        self._panels = None  # made from this factor when first needed (_point_posterior)
        self.alpha_ = np.asarray(alpha_all)
        self.posterior_ = {
            "xs": xs,
            "offset": device_array(self.x_offset_),
            "scale": device_array(self.x_scale_),
            "chol": chol_all,
            "alpha": alpha_all,
            "amp": device_array(self.amplitude_),
            "ls": device_array(self.lengthscale_std_),
            "mu": device_array(self.mean_),
            "comps": device_array(self.components_),
        }

    def _loo_coverage(self, rng: np.random.Generator) -> np.ndarray:
        # LOO residual alpha_i / [K^-1]_ii and variance 1 / [K^-1]_ii (GPML eq. (5.12)); the
        # diagonal of K^-1 on r rows is |L^-1 e_i|^2, one triangular solve with r columns.
        q = self.x_train_.shape[0]
        rows = rng.choice(q, min(LOO_ROWS, q), replace=False)
        e = np.zeros((q, len(rows)))
        e[rows, np.arange(len(rows))] = 1.0
        out = []
        e = device_array(e)
        for j in range(len(self.components_)):
            kinv = np.asarray(_inverse_diagonal(device_array(self.chol_[j]), e))
            z = self.alpha_[j, rows] / np.sqrt(kinv)
            out.append(float(np.mean(np.abs(z) <= 2.0)))
        return np.array(out)

    # -------------------------------------------------------------------------- predict

    # predict(x, return_std=False): Predictor's, over these rows (the batched solve with the
    # whole factor)
    _spread = "variance"
    _legacy_predict = True

    def _check_fitted(self) -> None:
        check_fitted(self)

    def _predict_rows(self, x: np.ndarray) -> tuple[jax.Array, jax.Array]:
        """Mean and variance (eqs. (12), (13)) at checked states (N, n).

        Rounding can make ``k(x, x) - k_*^T (K + sigma^2 I)^-1 k_*`` slightly negative; the
        variance is floored at 0.
        """
        return predict_batch(self.posterior_, device_array(x), self.kernel, self.n_states_)

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation at one state of shape (n,) (jittable).

        Raises
        ------
        NonFiniteError
            If a concrete ``x`` contains NaN or inf (not checked inside ``jax.jit``).
        """
        check_fitted(self)
        if is_concrete(x):
            check_finite("x", x)
        mean, var = exact_point(self._point_posterior(), x, self.kernel, self.n_states_)
        return mean, safe_sqrt(var)  # derivative 0, not NaN, where the std is 0

    _panels: Any = None

    def _point_posterior(self) -> dict[str, Any]:
        """:attr:`posterior_` with the factor also as row panels, for one state at a time.

        The panels (``_posterior.panels``: the lower triangles again, half the factor's
        memory) are made on the first call; a closed loop solves with them about three times
        faster than with the whole factor (``PANEL_ROWS``). :meth:`predict` keeps the factor.
        """
        if self._panels is None:
            self._panels = panels(self.chol_)
        return {**self.posterior_, "panels": self._panels}

    @property
    def n_states(self) -> int:
        """State dimension (for the :class:`~safestab.robust.UncertaintyModel` protocol)."""
        check_fitted(self)
        return self.n_states_

    # ------------------------------------------------------------------------ save/load

    def save(self, path: str | Path) -> None:
        """Write the fitted model to a ``.npz`` file (plain arrays and JSON; no pickle)."""
        check_fitted(self)
        meta = {
            "format": _FORMAT,
            "kernel": self.kernel,
            "mean": self.mean,
            "jitter": self.jitter,
            "components": list(self.components_),
            "n_states": self.n_states_,
            "optimizer_status": list(getattr(self, "optimizer_status_", ())),
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
            lengthscale_std=self.lengthscale_std_,
            log_marginal_likelihood=self.log_marginal_likelihood_,
        )

    @classmethod
    def load(cls, path: str | Path) -> GaussianProcessModel:
        """Read a model written by :meth:`save`; the Cholesky factor is recomputed.

        Files of format v1 stored the noise without the jitter; it is converted to the
        effective noise on reading.
        """
        with np.load(Path(path), allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") not in (_FORMAT, _FORMAT_V1):
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
            if meta["format"] == _FORMAT_V1:
                model.noise_ = np.sqrt(model.noise_**2 + model.jitter * model.amplitude_**2)
            model.mean_ = data["mean"]
            model.lengthscale_std_ = data["lengthscale_std"]
            model.lengthscale_ = model.lengthscale_std_ * model.x_scale_
            model.log_marginal_likelihood_ = data["log_marginal_likelihood"]
            model.optimizer_status_ = tuple(meta.get("optimizer_status", ()))
        with fit_threads():
            model._condition()
        return model


# A fitted model is data: its posterior arrays are the pytree's leaves (the closed loop takes
# them as arguments), the kernel, the dimension and the components its static part.
def _model_arrays(model: GaussianProcessModel) -> dict[str, Any]:
    if not hasattr(model, "posterior_"):
        return {}
    return {"posterior_": model.posterior_, "_panels": model._point_posterior()["panels"]}


register_model(
    GaussianProcessModel,
    _model_arrays,
    lambda m: (GaussianProcessModel, m.kernel, m.n_states_, tuple(m.components_)),
)
