"""GP posterior arithmetic shared by the exact GP, its FastGP cache and their batched forms.

Internal: unchecked, jittable functions of plain arrays (the callers check their inputs and
own the arrays). One place for every expression a posterior is computed with, so that the
exact model (:class:`~safestab.learning.GaussianProcessModel`), its inducing-point cache
(:class:`~safestab.learning.FastGP`) and the batched containers of
:mod:`safestab.learning.batched` evaluate the same formulas.

* Kernels: :func:`kernel` and :func:`kernel_matrix` through tinygp (SE or L2 Matern 5/2,
  ``amplitude^2 base(x / lengthscale)``), and :func:`kernel_from_r2` from squared scaled
  distances (:func:`sq_dist` as a matrix product, :func:`sq_dist_exact` by differences).
* The exact posterior: :func:`factor` (Cholesky factor of ``K + noise^2 I`` and
  ``alpha``), :func:`exact_point` (mean and latent variance at one state, with the factor
  as row :func:`panels` for a closed loop: :func:`solve_panels`),
  :func:`predict_batch` (the same, compiled and mapped over states) and
  :func:`exact_products` (a batch of states as matrix products).
* The cache's band (docs/learning.md proves it contains the exact band):
  :func:`band_point` (per learned component at one state), :func:`band_point_unpadded`,
  :func:`band_batch`, the running-error magnitudes :func:`band_magnitudes` and
  :func:`band_magnitudes_batch`, and :func:`band_products` (one component at a batch of
  states as matrix products, at its own :func:`bucket` of inducing inputs).

The per-state forms use tinygp's kernels and ``vmap``; the matrix-product forms evaluate the
same formulas with the batch as a matrix dimension, so they agree to rounding, not bit for
bit (tests/test_mc_gp.py).

Every function takes the arrays as arguments, never as constants of a compiled program: a
compilation then serves every data set of the same shapes (with the training arrays as
constants the first exact predict at Q = 6,000 took 15.8 s and 5.35 GB, issue 14).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
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
    "band_products",
    "bucket",
    "chol_alpha",
    "exact_point",
    "exact_products",
    "factor",
    "kernel",
    "kernel_from_r2",
    "kernel_matrix",
    "noisy_kernel",
    "PANEL_ROWS",
    "panels",
    "predict_batch",
    "solve_panels",
    "sq_dist",
    "sq_dist_exact",
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


def kernel_from_r2(kind: str, amp, r2):
    """``amp^2 base(r)`` from squared scaled distances, as tinygp's SE and (L2) Matern 5/2.

    Parameters
    ----------
    kind : {"se", "matern52"}
    amp : array broadcasting against ``r2``
    r2 : array of any shape
        Squared distances of the inputs divided by the lengthscales.

    Returns
    -------
    array of the broadcast shape
    """
    if kind == "se":
        return amp**2 * jnp.exp(-0.5 * r2)
    r = jnp.sqrt(r2)
    s5 = np.sqrt(5.0)
    return amp**2 * (1.0 + s5 * r + 5.0 / 3.0 * r2) * jnp.exp(-s5 * r)


def sq_dist(xl, zl, z2):
    """Squared distances (C, B, M) from ``xl`` (C, B, n) and ``zl`` (C, M, n), as a matrix product.

    ``|x|^2 + |z|^2 - 2 x.z`` with ``z2 = |zl|^2`` (C, M) precomputed, floored at 0: rounding
    of about ``1e-16 (|x|^2 + |z|^2)``, in exchange for a GEMM.
    """
    cross = jnp.einsum("cbn,cmn->cbm", xl, zl)
    return jnp.maximum(jnp.sum(xl * xl, -1)[..., None] + z2[:, None, :] - 2.0 * cross, 0.0)


def sq_dist_exact(xl_t, zl):
    """Squared distances (M, B) from ``xl_t`` (n, B) and ``zl`` (M, n), by exact differences.

    The squared differences are summed over the ``n`` coordinates in order, as tinygp's
    kernel (:func:`kernel`) sums them; the batch ``B`` is the minor (contiguous) axis.
    """
    r2 = jnp.square(xl_t[0][None, :] - zl[:, 0][:, None])
    for d in range(1, xl_t.shape[0]):
        r2 = r2 + jnp.square(xl_t[d][None, :] - zl[:, d][:, None])
    return r2


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


#: Rows per panel of :func:`panels`: the fastest of 64 to 500 rows on the paper preset's
#: factor (3 components, Q = 2,000) in a compiled loop, where it takes about a third of the
#: time of XLA's solve of the whole factor (``python benchmarks/gp_step.py``, its block in
#: docs/performance.md).
PANEL_ROWS = 128


def panels(chol, rows=PANEL_ROWS):
    """Cholesky factors (k, Q, Q) as row panels, for :func:`solve_panels`.

    Returns, per component, a list of ``(off, diag)``: ``off = L[s:e, :s]`` and ``diag =
    L[s:e, s:e]`` for consecutive row blocks ``[s, e)`` of ``rows`` rows: the lower triangle
    only, each block contiguous. A closed loop solves with a loop-invariant factor at every
    step: XLA's triangular solve of the whole factor takes about three times as long as the
    panels (:data:`PANEL_ROWS`).
    """
    chol = np.asarray(chol)
    q = chol.shape[-1]
    bounds = [(s, min(s + rows, q)) for s in range(0, q, rows)]
    with jax.ensure_compile_time_eval():  # arrays, not tracers, when first made inside a trace
        return [[(jnp.array(c[s:e, :s]), jnp.array(c[s:e, s:e])) for s, e in bounds] for c in chol]


def solve_panels(pan, b):
    """``L^-1 b`` by blocked forward substitution over :func:`panels` of one factor ``L``.

    Block row ``i``: ``v_i = L_ii^-1 (b_i - L_i,<i v_<i)``, the diagonal block by
    substitution: the column-oriented form of forward substitution, backward stable as the
    unblocked one (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., sec.
    8.1 and 13.1). ``b`` is (Q,) or (Q, B).
    """
    vs: list = []
    s = 0
    for off, diag in pan:
        e = s + diag.shape[0]
        r = b[s:e] if s == 0 else b[s:e] - off @ jnp.concatenate(vs)
        vs.append(solve_triangular(diag, r, lower=True))
        s = e
    return jnp.concatenate(vs)


def exact_point(post, x, kind, n):
    """Exact posterior mean and latent variance at one state, eqs. (12), (13).

    Parameters
    ----------
    post : dict of str to array
        :attr:`GaussianProcessModel.posterior_ <safestab.learning.GaussianProcessModel>`:
        ``xs`` (Q, n), ``offset`` and ``scale`` (n,), ``chol`` (k, Q, Q), ``alpha`` (k, Q),
        ``amp`` and ``mu`` (k,), ``ls`` (k, n), ``comps`` (k,); optionally ``panels``, the
        factors as :func:`panels` (then solved with :func:`solve_panels`: the same values to
        rounding, faster in a closed loop).
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

    def per_comp(a, l_, al, m, solve):
        kstar = kernel(kind, a, l_)(post["xs"], z)[:, 0]
        v = solve(kstar)  # L^-1 k*
        return kstar @ al + m, jnp.maximum(a**2 - v @ v, 0.0)

    if "panels" in post:  # per component, unrolled: each has its own panel arrays
        outs = [
            per_comp(
                post["amp"][j],
                post["ls"][j],
                post["alpha"][j],
                post["mu"][j],
                functools.partial(solve_panels, pan),
            )
            for j, pan in enumerate(post["panels"])
        ]
        mean_c, var_c = jnp.stack([o[0] for o in outs]), jnp.stack([o[1] for o in outs])
    else:
        mean_c, var_c = jax.vmap(
            lambda a, l_, al, m, chol: per_comp(
                a, l_, al, m, lambda k: solve_triangular(chol, k, lower=True)
            )
        )(post["amp"], post["ls"], post["alpha"], post["mu"], post["chol"])
    mean = jnp.zeros(n, dtype=mean_c.dtype).at[post["comps"]].set(mean_c)
    var = jnp.zeros(n, dtype=var_c.dtype).at[post["comps"]].set(var_c)
    return mean, var


#: :func:`exact_point` at states (B, n), compiled once per shape: ``(post, x, kind, n)`` ->
#: mean and variance, each (B, n).
predict_batch = jax.jit(jax.vmap(exact_point, in_axes=(None, 0, None, None)), static_argnums=(2, 3))


def exact_products(xs, inv_ls, xl, x2, chol, alpha, amplitude, mean, *, kind):
    """Exact posterior mean and std at a batch of states, as matrix products.

    A ``(B, Q)`` cross-kernel matrix per component (:func:`sq_dist`, :func:`kernel_from_r2`),
    one product with ``alpha`` and one triangular solve with ``B`` right-hand sides.

    Parameters
    ----------
    xs : array of shape (B, n)
        Standardised states.
    inv_ls : array of shape (C, n)
        Inverse lengthscales of the standardised inputs, per learned component.
    xl : array of shape (C, Q, n)
        Standardised training inputs times ``inv_ls``.
    x2 : array of shape (C, Q)
        Their squared norms.
    chol : array of shape (C, Q, Q)
        Cholesky factor of ``K + noise^2 I``.
    alpha : array of shape (C, Q)
    amplitude, mean : arrays of shape (C,)
    kind : {"se", "matern52"}

    Returns
    -------
    mean, std : arrays of shape (C, B)
        The variance is floored at 0 before the square root.
    """
    xq = xs[None, :, :] * inv_ls[:, None, :]
    k = kernel_from_r2(kind, amplitude[:, None, None], sq_dist(xq, xl, x2))
    mean_c = jnp.einsum("cbq,cq->cb", k, alpha) + mean[:, None]
    v = solve_triangular(chol, jnp.swapaxes(k, 1, 2), lower=True)
    var = jnp.maximum(amplitude[:, None] ** 2 - jnp.sum(v * v, 1), 0.0)
    return mean_c, jnp.sqrt(var)


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


def band_products(
    xs_t, inv_ls, zl, maps_t, weights, mask, amp, mean, err, rho, rnd, min_beta, *, kind
):
    """One component's cache mean and guaranteed std at a batch of states, as matrix products.

    The formula of :func:`band_point` (``m~ = mu + k . w``, ``sigma~ = sqrt(r^2 + |G a|^2 +
    2 |C a| rho r) + E r / min_beta``) with the batch as the minor (contiguous) axis of every
    intermediate, ``(M, B)``: the sums over the inducing inputs are then additions of whole
    rows, fused with the elementwise work, instead of short reductions along the minor axis
    (measured: 190 ns -> 130 ns per state on one core at ``M = 8``, ``B = 1000``). Only the
    summation order of the dot products differs from :func:`band_point`, which the rounding
    allowance ``rnd`` covers: the band still contains the exact band.

    Parameters
    ----------
    xs_t : array of shape (n, B)
        Standardised states, transposed.
    inv_ls : array of shape (n,)
        Inverse lengthscales of the standardised inputs.
    zl : array of shape (M, n)
        Standardised inducing inputs times ``inv_ls`` (padded rows masked out).
    maps_t : array of shape (M, 3 M)
        ``[Lj^-1; G Lj^-1; C Lj^-1]^T``: a kernel row times it gives ``[a, G a, C a]``.
    weights, mask : arrays of shape (M,)
        Mean weights; ``mask > 0`` on the rows in use.
    amp, mean, err, rho, rnd, min_beta : arrays of shape ()
        Amplitude, prior mean, ``E``, ``rho``, rounding allowance of ``r^2``, ``min_beta``.
    kind : {"se", "matern52"}

    Returns
    -------
    mean, std : arrays of shape (B,)
    """
    xl = xs_t * inv_ls[:, None]  # (n, B)
    m = zl.shape[0]
    k = kernel_from_r2(kind, amp, sq_dist_exact(xl, zl))
    k = jnp.where(mask[:, None] > 0, k, 0.0)  # (M, B)
    all3 = maps_t.T @ k  # (3 M, B): [a; G a; C a]
    # |a|^2, |G a|^2, |C a|^2 at once: (3, M, B) summed over M
    sq = jnp.sum(jnp.square(all3).reshape((3, m, all3.shape[-1])), 1)
    r2_res = jnp.maximum(amp**2 - sq[0], 0.0) + rnd
    r = jnp.sqrt(r2_res)
    cross = 2.0 * jnp.sqrt(sq[2]) * rho * r
    var = r2_res + sq[1] + cross  # >= the exact variance (FastGP)
    std = jnp.sqrt(var) + err * r / min_beta
    return weights @ k + mean, std


def bucket(used: int) -> int:
    """Inducing inputs kept for a component that uses ``used``: 1, 2, 4, then multiples of 4.

    Caches whose counts fall in one bucket share compiled shapes (a compilation of a closed
    loop costs about 10 s); the padding adds at most 60 % to that component's work (5 -> 8),
    at most a third from 9 inducing inputs up.
    """
    return max(used, 1) if used <= 2 else -(-used // 4) * 4
