"""The GP of the Monte Carlo loop, evaluated for a batch of states as matrix products.

From a fitted model's hyperparameters (public attributes of
:class:`~safestab.learning.GaussianProcessModel`) and a data set, :func:`condition` computes
the exact posterior (a Cholesky factor per learned component, the same conditioning as the
model's own) and :func:`inducing_cache` the inducing-point cache of
:class:`~safestab.learning.FastGP`, rebuilt here so that a batch of ``B`` states costs

* one ``(B, n) x (n, M)`` product for the squared distances to the inducing inputs ``Z``,
* one ``(B, M) x (M, 2M)`` product for ``a = Lz^-1 k`` and ``G a`` (mean and variance),

per component: GEMM-shaped work instead of ``B`` small matrix-vector products. The exact
posterior is batched the same way (a ``(B, Q)`` cross-kernel matrix, one product with
``alpha`` and one triangular solve with ``B`` right-hand sides).

Both caches are JAX pytrees of arrays, so a compiled closed loop takes them as arguments (one
compilation for every data set) and Ray ships them as plain arrays.

Notes
-----
:func:`inducing_cache` mirrors ``FastGP`` (learning/fast.py: greedy pivoted-Cholesky inducing
inputs, exact posterior at ``Z``, the two-term projected variance, and the measured widening of
:meth:`FastGP.calibrate`). tests/test_mc_gp.py checks it against ``FastGP``; when the GP-trust
work (issue 14) replaces FastGP's variance with a provably conservative bound, rewire
:func:`inducing_cache` to it (the loop only needs :meth:`InducingCache.mean_std_batch`).
Squared distances are expanded as ``|x|^2 + |z|^2 - 2 x.z`` (a matrix product); the rounding
this adds, about ``1e-16 (|x|^2 + |z|^2)`` in units of the lengthscale, is far below the
cancellation the projected variance already carries (documented in fast.py).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

__all__ = [
    "Hyperparameters",
    "ExactPosterior",
    "InducingCache",
    "BatchedUncertainty",
    "condition",
    "inducing_cache",
]


def _kernel_from_r2(kind: str, amp: Any, r2: Any) -> Any:
    if kind == "se":
        return amp**2 * jnp.exp(-0.5 * r2)
    r = jnp.sqrt(r2)
    s5 = np.sqrt(5.0)
    return amp**2 * (1.0 + s5 * r + 5.0 / 3.0 * r2) * jnp.exp(-s5 * r)


def _kernel_np(kind: str, amp: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Kernel matrix of lengthscale-scaled inputs a (A, n), b (B, n) by exact differences."""
    r2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, -1)
    return np.array(_kernel_from_r2(kind, amp, jnp.asarray(r2)))  # a writable copy


def _sq_dist(xl: Any, zl: Any, z2: Any) -> Any:
    """Squared distances (C, B, M) from xl (C, B, n) and zl (C, M, n), as a matrix product."""
    cross = jnp.einsum("cbn,cmn->cbm", xl, zl)
    return jnp.maximum(jnp.sum(xl * xl, -1)[..., None] + z2[:, None, :] - 2.0 * cross, 0.0)


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
    lengthscale : array of shape (C, n)
    kernel : {"se", "matern52"}
    jitter : float
        Relative diagonal jitter (times ``amplitude^2``).
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
    xl : array of shape (C, Q, n)
        Training inputs divided by each component's lengthscale.
    x2 : array of shape (C, Q)
        Their squared norms.
    inv_ls : array of shape (C, n)
    chol : array of shape (C, Q, Q)
        Cholesky factor of ``K + (noise^2 + jitter amplitude^2) I``.
    alpha : array of shape (C, Q)
    amplitude, mean : arrays of shape (C,)
    """

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

    def mean_std_batch(self, x: Any) -> tuple[Any, Any]:
        """Posterior mean and standard deviation at states ``x`` of shape (B, n), each (B, n)."""
        xl = x[None, :, :] * self.inv_ls[:, None, :]
        k = _kernel_from_r2(self.kernel, self.amplitude[:, None, None],
                            _sq_dist(xl, self.xl, self.x2))  # fmt: skip
        mean = jnp.einsum("cbq,cq->cb", k, self.alpha) + self.mean[:, None]
        v = jax.scipy.linalg.solve_triangular(self.chol, jnp.swapaxes(k, 1, 2), lower=True)
        var = jnp.maximum(self.amplitude[:, None] ** 2 - jnp.sum(v * v, 1), 0.0)
        n, comps = self.n_states, self.components
        return _scatter(mean, comps, n), _scatter(jnp.sqrt(var), comps, n)


@dataclasses.dataclass(frozen=True)
class InducingCache:
    """FastGP's inducing-point cache, batched (arrays per learned component ``C``).

    Attributes
    ----------
    zl : array of shape (C, M, n)
        Inducing inputs divided by the lengthscale (padded rows masked out).
    z2 : array of shape (C, M)
    inv_ls : array of shape (C, n)
    maps_t : array of shape (C, M, 2M)
        ``[Lz^-1; G Lz^-1]^T``: a query's kernel row times it gives ``a`` and ``G a``.
    weights : array of shape (C, M)
        ``Lz^-T Lz^-1 mu_Z``: the mean is ``k . weights``.
    mask : array of shape (C, M)
    amplitude, mean, widening : arrays of shape (C,)
    """

    zl: Any
    z2: Any
    inv_ls: Any
    maps_t: Any
    weights: Any
    mask: Any
    amplitude: Any
    mean: Any
    widening: Any
    kernel: str
    components: tuple[int, ...]
    n_states: int

    def mean_std_batch(self, x: Any, *, widened: bool = True) -> tuple[Any, Any]:
        """Mean and (widened) standard deviation at states ``x`` (B, n), each (B, n)."""
        xl = x[None, :, :] * self.inv_ls[:, None, :]
        r2 = _sq_dist(xl, self.zl, self.z2)
        k = _kernel_from_r2(self.kernel, self.amplitude[:, None, None], r2) * self.mask[:, None]
        both = jnp.einsum("cbm,cmk->cbk", k, self.maps_t)
        m = self.maps_t.shape[1]
        v, gv = both[..., :m], both[..., m:]
        # prior residual given f_Z (>= 0) plus the projected posterior covariance at Z
        var = jnp.maximum(self.amplitude[:, None] ** 2 - jnp.sum(v * v, -1), 0.0)
        var = var + jnp.sum(gv * gv, -1)
        std = jnp.sqrt(var) * (self.widening[:, None] if widened else 1.0)
        mean = jnp.einsum("cbm,cm->cb", k, self.weights) + self.mean[:, None]
        n, comps = self.n_states, self.components
        return _scatter(mean, comps, n), _scatter(std, comps, n)


for _cls in (ExactPosterior, InducingCache):
    _names = [f.name for f in dataclasses.fields(_cls)]
    _meta = ["kernel", "components", "n_states"]
    jax.tree_util.register_dataclass(
        _cls, data_fields=[f for f in _names if f not in _meta], meta_fields=_meta
    )


def condition(hyper: Hyperparameters, x: Any, y: Any) -> ExactPosterior:
    """Condition a GP with given hyperparameters on data ``(x, y)``; no optimisation.

    Parameters
    ----------
    hyper : Hyperparameters
    x, y : arrays of shape (Q, n)
        States and targets (``y``'s learned columns are used).

    Returns
    -------
    ExactPosterior

    Notes
    -----
    The same matrix as :class:`~safestab.learning.GaussianProcessModel` factorises,
    ``K + (noise^2 + jitter amplitude^2) I``, for ``refit = "reuse"`` in a Monte Carlo study:
    one Cholesky factorisation per component instead of a marginal-likelihood optimisation.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    xls, chols, alphas = [], [], []
    for j, comp in enumerate(hyper.components):
        amp = float(hyper.amplitude[j])
        xl = x / hyper.lengthscale[j]
        k = _kernel_np(hyper.kernel, amp, xl, xl)
        k[np.diag_indices_from(k)] += hyper.noise[j] ** 2 + hyper.jitter * amp * amp
        chol = scipy.linalg.cholesky(k, lower=True, check_finite=False)
        alphas.append(scipy.linalg.cho_solve((chol, True), y[:, comp] - hyper.mean[j]))
        chols.append(chol)
        xls.append(xl)
    xl_all = np.stack(xls)
    return ExactPosterior(
        xl=jnp.asarray(xl_all),
        x2=jnp.asarray(np.sum(xl_all**2, -1)),
        inv_ls=jnp.asarray(1.0 / hyper.lengthscale),
        chol=jnp.asarray(np.stack(chols)),
        alpha=jnp.asarray(np.stack(alphas)),
        amplitude=jnp.asarray(hyper.amplitude),
        mean=jnp.asarray(hyper.mean),
        kernel=hyper.kernel,
        components=hyper.components,
        n_states=hyper.n_states,
    )


def _pivots(kind: str, amp: float, xl: np.ndarray, m: int, tol: float) -> np.ndarray:
    """Greedy pivoted Cholesky: ``m`` rows maximising the residual prior variance."""
    q = xl.shape[0]
    m = min(m, q)
    diag = np.full(q, amp * amp)
    rows = np.zeros((m, q))
    chosen: list[int] = []
    for i in range(m):
        j = int(np.argmax(diag))
        if diag[j] <= tol * amp * amp:
            break
        chosen.append(j)
        col = _kernel_np(kind, amp, xl, xl[j : j + 1])[:, 0] - rows[:i].T @ rows[:i, j]
        rows[i] = col / np.sqrt(diag[j])
        diag = np.maximum(diag - rows[i] ** 2, 0.0)
    return np.array(chosen)


def inducing_cache(
    post: ExactPosterior,
    n_inducing: int = 32,
    *,
    x_check: Any = None,
    beta: float = 2.0,
    margin: float = 1.05,
    pivot_tol: float = 1e-12,
) -> InducingCache:
    """FastGP's inducing-point cache of an exact posterior, with its measured widening.

    Parameters
    ----------
    post : ExactPosterior
    n_inducing : int
        ``M`` per component.
    x_check : array of shape (N, n), optional
        Held-out states: the widening ``c_i = margin max (|m~_i - m_i| + beta sigma_i) /
        (beta sigma~_i)`` (at least 1) makes the cache's band contain the exact band there, as
        :meth:`FastGP.calibrate`. Without it the widening is 1.
    beta, margin : float
        As for :meth:`FastGP.calibrate`.
    pivot_tol : float
        Stop adding inducing inputs once the residual prior variance is below
        ``pivot_tol amplitude^2``.

    Returns
    -------
    InducingCache
    """
    xl_all, chol_all = np.asarray(post.xl), np.asarray(post.chol)
    alpha_all, amp_all = np.asarray(post.alpha), np.asarray(post.amplitude)
    jitter_rel = 1e-10  # FastGP's Kzz jitter (the model's default jitter)
    zs, maps, weights = [], [], []
    for j in range(len(post.components)):
        amp, xl = float(amp_all[j]), xl_all[j]
        z = xl[_pivots(post.kernel, amp, xl, int(n_inducing), pivot_tol)]
        kzz = _kernel_np(post.kernel, amp, z, z) + jitter_rel * amp * amp * np.eye(len(z))
        lz = np.linalg.cholesky(kzz)
        a_train = np.linalg.solve(lz, _kernel_np(post.kernel, amp, z, xl))  # (M, Q)
        w = a_train @ alpha_all[j]
        wmat = scipy.linalg.solve_triangular(chol_all[j], a_train.T, lower=True)  # (Q, M)
        t = np.eye(len(z)) - wmat.T @ wmat
        evals, evecs = np.linalg.eigh(0.5 * (t + t.T))
        g = (evecs * np.sqrt(np.maximum(evals, 0.0))).T  # G^T G = T
        lz_inv = np.linalg.solve(lz, np.eye(len(z)))
        zs.append(z)
        maps.append(np.concatenate([lz_inv, g @ lz_inv], 0))
        weights.append(lz_inv.T @ w)  # m~ = k . Lz^-T Lz^-1 mu_Z
    m_max = max(len(z) for z in zs)

    def pad_rows(a: np.ndarray, rows: int) -> np.ndarray:
        return np.pad(a, [(0, rows - a.shape[0])] + [(0, 0)] * (a.ndim - 1))

    zl = np.stack([pad_rows(z, m_max) for z in zs])
    maps_t = []
    for mp, z in zip(maps, zs, strict=True):
        k = len(z)
        full = np.zeros((2 * m_max, m_max))
        full[:k, :k] = mp[:k]
        full[m_max : m_max + k, :k] = mp[k:]
        maps_t.append(full.T)
    cache = InducingCache(
        zl=jnp.asarray(zl),
        z2=jnp.asarray(np.sum(zl**2, -1)),
        inv_ls=post.inv_ls,
        maps_t=jnp.asarray(np.stack(maps_t)),
        weights=jnp.asarray(np.stack([pad_rows(w, m_max) for w in weights])),
        mask=jnp.asarray(np.stack([np.arange(m_max) < len(z) for z in zs]), float),
        amplitude=post.amplitude,
        mean=post.mean,
        widening=jnp.ones(len(zs)),
        kernel=post.kernel,
        components=post.components,
        n_states=post.n_states,
    )
    if x_check is None:
        return cache
    xc = jnp.asarray(np.asarray(x_check, float))
    comps = list(post.components)
    m_ex, s_ex = (np.asarray(a)[:, comps] for a in jax.jit(post.mean_std_batch)(xc))
    m_fa, s_fa = (np.asarray(a)[:, comps] for a in jax.jit(
        lambda x: cache.mean_std_batch(x, widened=False))(xc))  # fmt: skip
    need = np.abs(m_fa - m_ex) + beta * s_ex
    have = beta * np.maximum(s_fa, 1e-300)
    widening = np.maximum(margin * np.max(need / have, axis=0), 1.0)
    return dataclasses.replace(cache, widening=jnp.asarray(widening))


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


class BatchedUncertainty:
    """An :class:`~safestab.robust.UncertaintyModel` whose batches are matrix products.

    ``mean_std`` takes one state, as controllers expect; under ``jax.vmap`` (a controller's
    batched step, the Monte Carlo loop) a custom batching rule evaluates the whole batch with
    the cache's ``mean_std_batch`` instead of mapping the one-state function.

    Parameters
    ----------
    cache : InducingCache or ExactPosterior
    """

    def __init__(self, cache: Any) -> None:
        self.cache = cache
        self.n_states = cache.n_states
        self.components_ = cache.components

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation of ``omega`` at one state (n,), each (n,)."""
        return _mean_std_point(self.cache, x)
