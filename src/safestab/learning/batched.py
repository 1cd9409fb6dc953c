"""GP posteriors evaluated for a batch of states as matrix products, as JAX pytrees.

:func:`condition` conditions a GP with given :class:`Hyperparameters` on a data set (no
optimisation; :meth:`GaussianProcessModel.from_hyperparameters`), :class:`ExactPosterior`
batches its exact posterior and :func:`inducing_cache` its :class:`~safestab.learning.FastGP`
cache, so that a batch of ``B`` states costs, per learned component,

* ``M_c x B`` kernel values (squared distances by exact differences, as FastGP's kernel),
* one ``(3 M_c, M_c) x (M_c, B)`` product for ``[a; G a; C a]`` (the whole band),

GEMM-shaped work instead of ``B`` small matrix-vector products. The exact posterior is
batched the same way (a ``(B, Q)`` cross-kernel matrix, one product with ``alpha`` and one
triangular solve with ``B`` right-hand sides). :class:`BatchedUncertainty` wraps either as an
uncertainty model whose ``jax.vmap`` is the batched evaluation.

Both caches are JAX pytrees of arrays, so a compiled function takes them as arguments (one
compilation for every data set of the same shapes: the inducing-input counts' buckets) and
they travel between processes as plain arrays. The arithmetic is
``safestab.learning._posterior``'s (``exact_products``, ``band_products``).

Notes
-----
:class:`InducingCache` holds FastGP's own arrays (:meth:`FastGP.arrays`: the construction is
FastGP's, not a copy of it) and evaluates FastGP's formula, ``m~ = mu + k . w`` and
``sigma~ = sqrt(r^2 + |G a|^2 + 2 |C a| rho r) + E r / min_beta``, batched. FastGP proves
(docs/learning.md) that ``m~ +- beta sigma~`` contains the exact band ``m +- beta sigma`` at
*every* state for every ``beta >= min_beta``, with a rounding allowance on ``r^2`` that covers
any summation order of the dot products; the batched form only changes that order, so the
guarantee carries over (tests/test_mc_gp.py checks containment far outside the data and the
equality with FastGP to rounding). The exact posterior's squared distances are expanded as
``|x|^2 + |z|^2 - 2 x.z`` (a matrix product, adding rounding of about
``1e-16 (|x|^2 + |z|^2)`` in units of the lengthscale).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._batching import as_float_array
from .._validation import is_concrete
from .._values import register_model
from ._posterior import band_products, bucket, exact_products
from ._predict import Predictor
from ._threads import one_blas_thread
from .fast import FastGP
from .gp import GaussianProcessModel

__all__ = [
    "Hyperparameters",
    "ExactPosterior",
    "InducingCache",
    "BatchedUncertainty",
    "condition",
    "inducing_cache",
    "one_blas_thread",
]


def _padded(v: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``v`` in the leading corner of zeros of ``shape``."""
    out = np.zeros(shape)
    out[tuple(slice(0, d) for d in v.shape)] = v
    return out


def _scatter(values: Any, comps: tuple[int, ...], n: int) -> Any:
    """(C, B) per learned component -> (B, n) with zeros elsewhere."""
    out = jnp.zeros((values.shape[1], n), values.dtype)
    return out.at[:, jnp.asarray(comps)].set(values.T)


@dataclasses.dataclass(frozen=True)
class Hyperparameters:
    """GP hyperparameters per learned component, in the units of ``x``.

    Attributes
    ----------
    amplitude, noise, mean : arrays of shape (C,)
        ``noise`` is the effective noise std (jitter included), as ``noise_``.
    lengthscale : array of shape (C, n)
    kernel : {"se", "matern52"}
    jitter : float
        Relative diagonal jitter (already part of ``noise``; recorded).
    components : tuple of int
    n_states : int
    """

    amplitude: np.ndarray
    noise: np.ndarray
    mean: np.ndarray
    lengthscale: np.ndarray
    kernel: str
    jitter: float
    components: tuple[int, ...]
    n_states: int

    @classmethod
    def from_model(cls, model: Any) -> Hyperparameters:
        """The fitted hyperparameters of a :class:`~safestab.learning.GaussianProcessModel`."""
        return cls(
            amplitude=np.asarray(model.amplitude_, float),
            noise=np.asarray(model.noise_, float),
            mean=np.asarray(model.mean_, float),
            lengthscale=np.asarray(model.lengthscale_, float),
            kernel=str(model.kernel),
            jitter=float(model.jitter),
            components=tuple(int(c) for c in model.components_),
            n_states=int(model.n_states_),
        )


@dataclasses.dataclass(frozen=True)
class ExactPosterior:
    """The exact GP posterior, batched (arrays per learned component ``C``).

    Attributes
    ----------
    offset, scale : arrays of shape (n,)
        The model's input standardisation.
    xl : array of shape (C, Q, n)
        Standardised training inputs divided by each component's lengthscale.
    x2 : array of shape (C, Q)
        Their squared norms.
    inv_ls : array of shape (C, n)
        Inverse lengthscales of the standardised inputs.
    chol : array of shape (C, Q, Q)
        Cholesky factor of ``K + noise^2 I``.
    alpha : array of shape (C, Q)
    amplitude, mean : arrays of shape (C,)
    """

    offset: Any
    scale: Any
    xl: Any
    x2: Any
    inv_ls: Any
    chol: Any
    alpha: Any
    amplitude: Any
    mean: Any
    kernel: str
    components: tuple[int, ...]
    n_states: int

    @classmethod
    def from_model(cls, model: GaussianProcessModel) -> ExactPosterior:
        """The posterior of a fitted :class:`~safestab.learning.GaussianProcessModel`."""
        inv_ls = 1.0 / np.asarray(model.lengthscale_ / model.x_scale_, float)
        xs = (model.x_train_ - model.x_offset_) / model.x_scale_
        xl = xs[None, :, :] * inv_ls[:, None, :]
        return cls(
            offset=np.asarray(model.x_offset_, float), scale=np.asarray(model.x_scale_, float),
            xl=xl, x2=np.sum(xl**2, -1), inv_ls=inv_ls, chol=np.asarray(model.chol_),
            alpha=np.asarray(model.alpha_), amplitude=np.asarray(model.amplitude_, float),
            mean=np.asarray(model.mean_, float), kernel=str(model.kernel),
            components=tuple(int(c) for c in model.components_), n_states=int(model.n_states_),
        )  # fmt: skip

    def mean_std_batch(self, x: Any) -> tuple[Any, Any]:
        """Posterior mean and standard deviation at states ``x`` of shape (B, n), each (B, n)."""
        xs = (x - self.offset) / self.scale
        mean, std = exact_products(
            xs, self.inv_ls, self.xl, self.x2, self.chol, self.alpha, self.amplitude,
            self.mean, kind=self.kernel,
        )  # fmt: skip
        n, comps = self.n_states, self.components
        return _scatter(mean, comps, n), _scatter(std, comps, n)


@dataclasses.dataclass(frozen=True)
class InducingCache:
    """:class:`~safestab.learning.FastGP`'s cache, batched (arrays per learned component ``C``).

    Each component keeps its own number of inducing inputs ``M_c`` (the number FastGP chose,
    rounded up to 1, 2, 4 or a multiple of 4 so that data sets share compiled shapes; padded
    rows are masked out), instead of FastGP's padding of every component to the largest: the
    stress preset's GP needs a few inducing inputs for each kinematic component and a dozen
    for its drag, and the padding to the largest made most kernel values and products zeros
    (measured: the GP was three quarters of that preset's closed-loop time). The rows dropped
    are padding (zero kernel values, zero weights, zero maps), so the band is FastGP's.

    Attributes
    ----------
    offset, scale : arrays of shape (n,)
        Input standardisation.
    zl : tuple of C arrays of shape (M_c, n)
        Standardised inducing inputs times ``inv_ls`` (padded rows masked out).
    inv_ls : array of shape (C, n)
        Inverse lengthscales of the standardised inputs.
    mask : tuple of C arrays of shape (M_c,)
    li, kzz, g, cm : tuples of C arrays of shape (M_c, M_c)
        ``Lj^-1``, ``K_ZZ``, ``G`` and ``C`` (:meth:`FastGP.arrays`).
    b, rho_b : tuples of C arrays of shape (M_c,)
        The mean's weights and residual.
    scal : tuple of C arrays of shape (11,)
        ``amp, mu, E, ek, gnorm, bnorm, rho_err, rho, wnorm, cnorm`` and the rows in use
        (``band_products``).
    min_beta : array of shape ()
        The band contains the exact band for every ``beta >= min_beta``.
    """

    offset: Any
    scale: Any
    zl: Any
    inv_ls: Any
    mask: Any
    li: Any
    kzz: Any
    g: Any
    cm: Any
    b: Any
    rho_b: Any
    scal: Any
    min_beta: Any
    kernel: str
    components: tuple[int, ...]
    n_states: int
    proven: bool = True

    @classmethod
    def from_fastgp(cls, fast: FastGP) -> InducingCache:
        """The arrays of a :class:`~safestab.learning.FastGP` (its proven band), batched."""
        a = fast.arrays()
        inv_ls = 1.0 / a["ls"]
        out: dict[str, list] = {
            key: [] for key in ("zl", "mask", "li", "kzz", "g", "cm", "b", "rho_b")
        }
        scal = []
        for c in range(a["mask"].shape[0]):
            used = int(a["mask"][c].sum())  # FastGP pads at the end
            m = bucket(used)
            out["zl"].append(_padded(a["z"][c, :used] * inv_ls[c], (m, a["z"].shape[2])))
            out["mask"].append(_padded(a["mask"][c, :used].astype(float), (m,)))
            for key in ("li", "kzz", "g", "cm"):
                out[key].append(_padded(a[key][c, :used, :used], (m, m)))
            for key in ("b", "rho_b"):
                out[key].append(_padded(a[key][c, :used], (m,)))
            keys = ("amp", "mu", "err", "ek", "gnorm", "bnorm", "rho_err", "rho", "wnorm", "cnorm")
            # the allowances count the rows in use: the bucket's padding is exact zeros
            scal.append(np.array([float(a[key][c]) for key in keys] + [float(used)]))
        return cls(
            offset=a["offset"], scale=a["scale"], inv_ls=inv_ls, scal=tuple(scal),
            **{key: tuple(v) for key, v in out.items()},
            min_beta=np.asarray(fast.min_beta, float), kernel=fast.model.kernel,
            components=tuple(int(c) for c in fast.components_), n_states=int(fast.n_states),
            proven=bool(fast.proven),
        )  # fmt: skip

    def mean_std_batch(self, x: Any) -> tuple[Any, Any]:
        """FastGP's mean and guaranteed std at states ``x`` (B, n), each (B, n).

        Per component ``band_products`` of ``safestab.learning._posterior``, with the
        batch as the minor (contiguous) axis of every intermediate, ``(M_c, B)``.
        """
        xs_t = ((x - self.offset) / self.scale).T  # (n, B)
        means, stds = [], []
        for c in range(len(self.zl)):
            mean, std = band_products(
                xs_t, self.inv_ls[c], self.zl[c], self.mask[c], self.li[c], self.kzz[c],
                self.g[c], self.cm[c], self.b[c], self.rho_b[c], self.scal[c], self.min_beta,
                kind=self.kernel, proven=self.proven,
            )  # fmt: skip
            stds.append(std)
            means.append(mean)
        n, comps = self.n_states, self.components
        return _scatter(jnp.stack(means), comps, n), _scatter(jnp.stack(stds), comps, n)


for _cls in (ExactPosterior, InducingCache):
    _names = [f.name for f in dataclasses.fields(_cls)]
    _meta = [m for m in ("kernel", "components", "n_states", "proven") if m in _names]
    jax.tree_util.register_dataclass(
        _cls, data_fields=[f for f in _names if f not in _meta], meta_fields=_meta
    )


def condition(hyper: Hyperparameters, x: Any, y: Any, *, seed: int = 0) -> GaussianProcessModel:
    """Condition a GP with given hyperparameters on data ``(x, y)``; no optimisation.

    Parameters
    ----------
    hyper : Hyperparameters
    x, y : arrays of shape (Q, n)
        States and targets (``y``'s learned columns are used).
    seed : int
        Seeds the model's leave-one-out check.

    Returns
    -------
    GaussianProcessModel
        From :meth:`GaussianProcessModel.from_hyperparameters`: the matrix
        ``K + noise^2 I`` a fit with these hyperparameters factorises, one Cholesky
        factorisation per component instead of a marginal-likelihood optimisation (one fit's
        hyperparameters reused on another data set).
    """
    with one_blas_thread():
        return GaussianProcessModel.from_hyperparameters(
            x, y, amplitude=hyper.amplitude, noise=hyper.noise, lengthscale=hyper.lengthscale,
            mean=hyper.mean, kernel=hyper.kernel,  # type: ignore[arg-type]
            components=hyper.components, jitter=hyper.jitter, seed=seed,
        )  # fmt: skip


def inducing_cache(
    model: GaussianProcessModel,
    n_inducing: int = 32,
    *,
    min_beta: float = 1.0,
    pivot_tol: float = 1e-10,
) -> InducingCache:
    """FastGP's cache of a fitted model, batched: its band contains the exact band everywhere.

    Parameters
    ----------
    model : GaussianProcessModel
    n_inducing : int
        ``M`` per component.
    min_beta, pivot_tol : float
        As for :class:`~safestab.learning.FastGP` (the band contains the exact band for every
        ``beta >= min_beta``).

    Returns
    -------
    InducingCache

    Warns
    -----
    InducingPointsWarning
        As :class:`~safestab.learning.FastGP`, when the band is needlessly wide.
    """
    with one_blas_thread():
        fast = FastGP(model, n_inducing, min_beta=min_beta, pivot_tol=pivot_tol)
    return InducingCache.from_fastgp(fast)


@jax.custom_batching.custom_vmap
def _mean_std_point(cache: Any, x: Any) -> tuple[Any, Any]:
    mean, std = cache.mean_std_batch(x[None, :])
    return mean[0], std[0]


@_mean_std_point.def_vmap
def _mean_std_rule(axis_size, in_batched, cache, x):
    cache_batched, x_batched = in_batched
    if any(jax.tree_util.tree_leaves(cache_batched)):
        # a batch of caches (say, vmapped over data sets): per-state evaluation
        axes = jax.tree_util.tree_map(lambda b: 0 if b else None, cache_batched)
        out = jax.vmap(_mean_std_point, in_axes=(axes, 0 if x_batched else None))(cache, x)
        return out, (True, True)
    if not x_batched:
        x = jnp.broadcast_to(x, (axis_size,) + x.shape)
    return cache.mean_std_batch(x), (True, True)


class BatchedUncertainty(Predictor):
    """An :class:`~safestab.robust.UncertaintyModel` whose batches are matrix products.

    ``mean_std`` takes one state, as the protocol asks; under ``jax.vmap`` a custom batching
    rule evaluates the whole batch with the cache's ``mean_std_batch`` instead of mapping the
    one-state function.

    Parameters
    ----------
    cache : InducingCache or ExactPosterior
    """

    def __init__(self, cache: Any) -> None:
        self.cache = cache
        self.n_states = cache.n_states
        self.components_ = cache.components

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation of ``omega`` at one state (n,), each (n,).

        Called on values (not inside a transformation), it runs as one compiled program with
        the cache as its argument.
        """
        if is_concrete(x, *jax.tree_util.tree_leaves(self.cache)):
            return _mean_std_point_program(self.cache, x)
        return _mean_std_point(self.cache, x)

    def mean_std_batch(self, x: Any) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation at states ``x`` (B, n), each (B, n).

        Compiled once per cache shape and batch size (one module-level ``jax.jit``), not
        traced again for every cache: a Monte Carlo study calls it once per data set.
        """
        return _mean_std_batch(self.cache, as_float_array(x))

    def _predict_rows(self, x: np.ndarray) -> tuple[jax.Array, jax.Array]:
        # predict(x, return_std=False): Predictor's, over the batched evaluation
        return self.mean_std_batch(x)


register_model(
    BatchedUncertainty,
    lambda u: {"cache": u.cache},
    lambda u: (BatchedUncertainty, u.n_states, tuple(u.components_)),
)


@jax.jit
def _mean_std_batch(cache: Any, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    return cache.mean_std_batch(x)


_mean_std_point_program = jax.jit(_mean_std_point)
