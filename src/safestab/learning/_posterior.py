"""GP posterior arithmetic shared by the exact GP, its FastGP cache and their batched forms.

Internal: unchecked, jittable functions of plain arrays (the callers check their inputs and
own the arrays). One place for every expression a posterior is computed with, so that the
exact model (:class:`~safestab.learning.GaussianProcessModel`), its inducing-point cache
(:class:`~safestab.learning.FastGP`) and the batched containers of
:mod:`safestab.learning.batched` evaluate the same formulas.

* Kernels: :func:`kernel` and :func:`kernel_matrix` through tinygp (SE or L2 Matern 5/2,
  ``amplitude^2 base(x / lengthscale)``).
* The exact posterior: :func:`factor` (Cholesky factor of ``K + noise^2 I`` and
  ``alpha``), :func:`exact_point` (mean and latent variance at one state) and
  :func:`predict_batch` (the same, compiled and mapped over states).
* The cache's band (docs/learning.md proves it contains the exact band):
  :func:`band_point` (per learned component at one state), :func:`band_point_unpadded`,
  :func:`band_batch`, and the running-error magnitudes :func:`band_magnitudes` and
  :func:`band_magnitudes_batch`.

Every function takes the arrays as arguments, never as constants of a compiled program: a
compilation then serves every data set of the same shapes (with the training arrays as
constants the first exact predict at Q = 6,000 took 15.8 s and 5.35 GB, issue 14).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve, solve_triangular
from tinygp import kernels, transforms

from .._numerics import safe_sqrt

__all__ = [
    "BAND_KEYS",
    "band_batch",
    "band_component",
    "band_magnitudes",
    "band_magnitudes_batch",
    "band_point",
    "band_point_unpadded",
    "chol_alpha",
    "exact_point",
    "factor",
    "kernel",
    "kernel_matrix",
    "noisy_kernel",
    "predict_batch",
]

# ------------------------------------------------------------------------------- kernels


def kernel(kind: str, amplitude, lengthscale):
    """The tinygp kernel ``amplitude^2 * base(x / lengthscale)``.

    Parameters
    ----------
    kind : {"se", "matern52"}
        ``base`` is the squared exponential or the (L2) Matern 5/2.
    amplitude : array of shape ()
    lengthscale : array of shape (n,)

    Returns
    -------
    tinygp.kernels.Kernel
        Called on ``(x1, x2)`` of shapes (N1, n) and (N2, n), gives a matrix (N1, N2).
    """
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
    """Kernel matrix (N1, N2) of ``x1`` (N1, n) and ``x2`` (N2, n), compiled once per shape.

    Eagerly, tinygp re-traces the kernel at every call.
    """
    return kernel(kind, amplitude, lengthscale)(x1, x2)


# ----------------------------------------------------------------------- exact posterior


@functools.partial(jax.jit, static_argnames=("kind",))
def noisy_kernel(amp, ls, nz, xs, *, kind):
    """``K + nz^2 I`` (Q, Q) of ``xs`` (Q, n), compiled once per ``Q``.

    Eagerly, the sum cost as much as the factorisation. ``nz`` is the effective noise std
    (jitter included).
    """
    k = kernel_matrix(amp, ls, xs, xs, kind=kind)
    return k + nz**2 * jnp.eye(xs.shape[0])  # noise_ is effective: jitter included


@jax.jit
def chol_alpha(k, y, mu):
    """Cholesky factor (Q, Q) of ``k`` (Q, Q) and ``alpha = k^-1 (y - mu)`` (Q,).

    Compiled apart from :func:`noisy_kernel`: fused with the kernel, the factor differed from
    the eager one in the last bits; apart, both are bit for bit the eager operations'.
    """
    chol = jnp.linalg.cholesky(k)
    return chol, cho_solve((chol, True), y - mu)


def factor(amp, ls, nz, xs, y, mu, *, kind):
    """Cholesky factor (Q, Q) of ``K + nz^2 I`` and ``alpha`` (Q,): two compiled calls per Q.

    Parameters
    ----------
    amp, nz, mu : arrays of shape ()
        Amplitude, effective noise std and constant prior mean.
    ls : array of shape (n,)
        Lengthscales of the standardised inputs.
    xs : array of shape (Q, n)
        Standardised training inputs.
    y : array of shape (Q,)
    kind : {"se", "matern52"}
    """
    return chol_alpha(noisy_kernel(amp, ls, nz, xs, kind=kind), y, mu)


def exact_point(post, x, kind, n):
    """Exact posterior mean and latent variance at one state, eqs. (12), (13).

    Parameters
    ----------
    post : dict of str to array
        :attr:`GaussianProcessModel.posterior_ <safestab.learning.GaussianProcessModel>`:
        ``xs`` (Q, n), ``offset`` and ``scale`` (n,), ``chol`` (k, Q, Q), ``alpha`` (k, Q),
        ``amp`` and ``mu`` (k,), ``ls`` (k, n), ``comps`` (k,).
    x : array of shape (n,)
    kind : {"se", "matern52"}
    n : int
        State dimension.

    Returns
    -------
    mean, var : arrays of shape (n,)
        Zero for the components that are not learned; the variance is floored at 0.
    """
    z = ((x - post["offset"]) / post["scale"])[None, :]

    def per_comp(a, l_, al, chol, m):
        kstar = kernel(kind, a, l_)(post["xs"], z)[:, 0]
        v = solve_triangular(chol, kstar, lower=True)
        return kstar @ al + m, jnp.maximum(a**2 - v @ v, 0.0)

    mean_c, var_c = jax.vmap(per_comp)(
        post["amp"], post["ls"], post["alpha"], post["chol"], post["mu"]
    )
    mean = jnp.zeros(n, dtype=mean_c.dtype).at[post["comps"]].set(mean_c)
    var = jnp.zeros(n, dtype=var_c.dtype).at[post["comps"]].set(var_c)
    return mean, var


#: :func:`exact_point` at states (B, n), compiled once per shape: ``(post, x, kind, n)`` ->
#: mean and variance, each (B, n).
predict_batch = jax.jit(jax.vmap(exact_point, in_axes=(None, 0, None, None)), static_argnums=(2, 3))

# ---------------------------------------------------------------------------- cache band


def band_component(kind, mm, z0, work_unit, with_scales):
    """One learned component's cache evaluation, as a function of that component's arrays.

    Parameters
    ----------
    kind : {"se", "matern52"}
    mm : int
        Inducing inputs ``M`` of the arrays the returned function receives.
    z0 : array of shape (n,)
        The standardised state.
    work_unit : float
        Rounding allowance per query (0 in float64; see :func:`band_point`).
    with_scales : bool
        Return the running magnitudes (:func:`band_magnitudes`) instead of the band.

    Returns
    -------
    callable
        ``(amp, ls, z, wk, maps, mask, err, rho, round)`` (shapes (), (n,), (M, n), (M,),
        (3M, M), (M,) or None for no padded rows, (), (), ()) -> three arrays of shape ():
        the mean without the prior mean, ``sqrt(v~)`` and ``E r(x)``; with ``with_scales``,
        the magnitudes of these.
    """

    def per_comp(a, l_, z, wk, maps, mask, err, rho, rnd):
        k = kernel(kind, a, l_)(z, z0[None, :])[:, 0]
        if mask is not None:
            k = jnp.where(mask, k, 0.0)
        all3 = maps @ k
        v, gv, cv = all3[:mm], all3[mm : 2 * mm], all3[2 * mm :]
        r2 = jnp.maximum(a * a - v @ v, 0.0) + rnd
        mean = k @ wk
        if not (work_unit or with_scales):
            r = safe_sqrt(r2)  # safe_sqrt: derivative 0, not NaN, at 0
            var = r2 + gv @ gv + 2.0 * safe_sqrt(cv @ cv) * rho * r  # >= exact variance
            return mean, safe_sqrt(var), err * r
        # running magnitudes: the products are rounded relative to |maps| |k|; a working
        # precision's allowance (work_unit > 0) is relative to them
        mag3 = jnp.abs(maps) @ jnp.abs(k)
        mv, mg, mc = mag3[:mm], mag3[mm : 2 * mm], mag3[2 * mm :]
        r2_mag = a * a + 2.0 * jnp.abs(v) @ mv + r2
        r2 = r2 + work_unit * r2_mag
        r = safe_sqrt(r2)  # > 0: rnd > 0
        cn = safe_sqrt(cv @ cv)
        var = r2 + gv @ gv + 2.0 * cn * rho * r
        r_mag = r2_mag / (2.0 * r)
        cn_mag = jnp.where(cn > 0, jnp.abs(cv) @ mc / jnp.where(cn > 0, cn, 1.0), 0.0)
        var_mag = r2_mag + 2.0 * jnp.abs(gv) @ mg + 2.0 * rho * (cn_mag * r + cn * r_mag) + var
        var = var + work_unit * var_mag
        mean_mag = jnp.abs(wk) @ jnp.abs(k)
        sd = safe_sqrt(var)
        if with_scales:
            return mean_mag, var_mag / (2.0 * sd), err * r_mag
        return mean, sd, err * r + work_unit * (mean_mag + err * r_mag)

    return per_comp


#: The per-component arrays of a cache, in the order :func:`band_component`'s function takes.
BAND_KEYS = ("amp", "ls", "z", "wk", "maps", "mask", "err", "rho", "round")


def band_point(p, x, kind, work_unit=0.0):
    """Per learned component: cache mean (without the prior mean), sqrt(v~) and E r(x).

    Parameters
    ----------
    p : dict of str to array
        :meth:`FastGP.arrays <safestab.learning.FastGP.arrays>`: ``offset`` and ``scale``
        (n,) and, per learned component padded to a common ``M``, the :data:`BAND_KEYS`.
    x : array of shape (n,)
    kind : {"se", "matern52"}
    work_unit : float
        ``> 0`` (a Python float: the precision the step will be evaluated in, times a safety
        factor; :meth:`FastGP.for_precision <safestab.learning.FastGP.for_precision>`) adds
        that rounding allowance per query, relative to the running magnitudes of
        :func:`band_magnitudes`, to ``r^2``, ``v~`` and the mean-error term, so that the band
        still contains the exact one when every operation is rounded to that precision. 0
        (float64): the constant allowance ``round`` covers it.

    Returns
    -------
    mean, sd, merr : arrays of shape (k,)
    """
    z0 = (x - p["offset"]) / p["scale"]
    per_comp = band_component(kind, p["z"].shape[1], z0, work_unit, False)
    return jax.vmap(per_comp)(*(p[key] for key in BAND_KEYS))


def band_point_unpadded(p, comps, x, kind, work_unit):
    """:func:`band_point` with each component at its own number of inducing inputs.

    ``comps``: per component, a dict of its :data:`BAND_KEYS` arrays without padding (``mask``
    None). The same values as the padded, vmapped evaluation, with fewer operations in
    exported code (the padded rows and their masks are gone).
    """
    z0 = (x - p["offset"]) / p["scale"]
    outs = []
    for c in comps:
        per_comp = band_component(kind, c["z"].shape[0], z0, work_unit, False)
        outs.append(per_comp(*(c[key] for key in BAND_KEYS)))
    return tuple(jnp.stack([o[i] for o in outs]) for i in range(3))


#: :func:`band_point` at states (B, n): ``(p, x, kind, work_unit)`` -> three arrays (B, k).
#: The cache's arrays are arguments: one compilation per (M, kernel), not per cache.
band_batch = jax.jit(jax.vmap(band_point, in_axes=(None, 0, None, None)), static_argnums=(2, 3))


def band_magnitudes(p, x, kind, work_unit=0.0):
    """Per learned component: the magnitudes the cache's mean and std are rounded relative to.

    A running-error analysis of :func:`band_point`: every kernel value carries a relative
    rounding error (``exp``), and every product ``maps @ k`` one relative to
    ``|maps| @ |k|``. Carried through the squares, the differences ``amp^2 - |a|^2`` and the
    square roots to first order, the mean's error is a small multiple of ``u |wk| . |k|``
    and the std's of ``u`` times ``var_mag / (2 sd) + E r_mag / min_beta``. These, not the
    cond(Lj)-based allowance, are what two float64 evaluations (XLA's and the exported C)
    differ by.

    Returns
    -------
    mean_mag, sd_mag, merr_mag : arrays of shape (k,)
        The mean's magnitude, the std's without the mean-error term, the mean-error term's.
    """
    z0 = (x - p["offset"]) / p["scale"]
    per_comp = band_component(kind, p["z"].shape[1], z0, work_unit, True)
    return jax.vmap(per_comp)(*(p[key] for key in BAND_KEYS))


#: :func:`band_magnitudes` at states (B, n), compiled once per shape.
band_magnitudes_batch = jax.jit(
    jax.vmap(band_magnitudes, in_axes=(None, 0, None, None)), static_argnums=(2, 3)
)
