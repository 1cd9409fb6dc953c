"""GP posterior arithmetic shared by the exact GP, its FastGP cache and their batched forms.

Internal: unchecked, jittable functions of plain arrays (the callers check their inputs and
own the arrays). One place for every expression a posterior is computed with, so that the
exact model (:class:`~safestab.learning.GaussianProcessModel`), its inducing-point cache
(:class:`~safestab.learning.FastGP`) and the batched containers of
:mod:`safestab.learning.batched` evaluate the same formulas.

* Kernels: :func:`kernel` and :func:`kernel_matrix` through tinygp (SE or L2 Matern 5/2,
  ``amplitude^2 base(x / lengthscale)``), and :func:`kernel_from_r2` from squared scaled
  distances (:func:`sq_dist` as a matrix product, :func:`sq_dist_exact` by differences),
  both with the formulas of the kernel objects of :mod:`safestab.learning.kernels`.
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
constants the first exact predict at Q = 6,000 took 15.8 s and 5.35 GB).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_solve, solve_triangular

from .._numerics import safe_sqrt
from .kernels import as_kernel

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
    "kernel_error_coefficient",
    "kernel_from_r2",
    "kernel_matrix",
    "noisy_kernel",
    "PANEL_ROWS",
    "panels",
    "predict_batch",
    "residual_allowance",
    "solve_panels",
    "sq_dist",
    "sq_dist_exact",
]

# ------------------------------------------------------------------------------- kernels


def kernel(kind, amplitude, lengthscale):
    """The tinygp kernel ``amplitude^2 * base(x / lengthscale)``.

    Parameters
    ----------
    kind : StationaryKernel or {"se", "matern52"}
        ``base``: the squared exponential or the (L2) Matern 5/2 (:mod:`~.kernels`).
    amplitude : array of shape ()
    lengthscale : array of shape (n,)

    Returns
    -------
    tinygp.kernels.Kernel
        Called on ``(x1, x2)`` of shapes (N1, n) and (N2, n), gives a matrix (N1, N2).
    """
    return as_kernel(kind).tinygp(amplitude, lengthscale)


@functools.partial(jax.jit, static_argnames=("kind",))
def kernel_matrix(amplitude, lengthscale, x1, x2, *, kind):
    """Kernel matrix (N1, N2) of ``x1`` (N1, n) and ``x2`` (N2, n), compiled once per shape.

    Eagerly, tinygp re-traces the kernel at every call.
    """
    return kernel(kind, amplitude, lengthscale)(x1, x2)


def kernel_from_r2(kind, amp, r2):
    """``amp^2 base(r2)`` from squared scaled distances, the same formula as :func:`kernel`.

    Parameters
    ----------
    kind : StationaryKernel or {"se", "matern52"}
    amp : array broadcasting against ``r2``
    r2 : array of any shape
        Squared distances of the inputs divided by the lengthscales.

    Returns
    -------
    array of the broadcast shape
    """
    return amp**2 * as_kernel(kind).of_r2(r2, jnp)


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
    kind : StationaryKernel or {"se", "matern52"}
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
    kind : StationaryKernel or {"se", "matern52"}
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
    kind : StationaryKernel or {"se", "matern52"}

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


def kernel_error_coefficient(kind, z_scaled_max: np.ndarray) -> float:
    """``e`` such that a kernel value computed in precision ``u`` is within ``e u amp^2``.

    :meth:`~.kernels.StationaryKernel.error_coefficient` of ``kind`` (a kernel object or its
    name) at ``z_scaled_max`` (n,), the largest ``|z_i| / l_i`` over the inducing inputs.
    """
    return as_kernel(kind).error_coefficient(z_scaled_max)


def residual_allowance(amp2, c1, mm, ek, unit):
    """Bound on the rounding of ``q = amp^2 - 2 c.k + c.(K_ZZ c)`` evaluated in unit ``unit``.

    Every term is at most ``amp^2 (1 + |c|_1)^2`` in size: the sums' ``(M + 3) unit`` twice,
    the kernel values' ``ek unit`` twice, and the stored ``K_ZZ`` and the two subtractions.
    One expression for the cache's query (:func:`band_component`, :func:`band_products`) and
    its build (``rho``); works on floats and arrays alike.
    """
    dot_unit = (mm + 3) * unit
    return amp2 * (1.0 + c1) ** 2 * (2.0 * dot_unit + 2.0 * ek * unit + 3.0 * unit)


def _proven_sd(p, r, c, c1, c2, k, kzz, cm, rho, wnorm, cnorm, ek, amp2, mm, unit):
    """FastGP's std ``sqrt(p^2 + r^2 + min(2 p r, cross))`` (docs/learning.md).

    ``2 p r`` is the triangle inequality; ``cross = 2 (|c| |res| + |gamma| (rho r + ||W_X||
    |res|))`` the covariance of the two parts through the data, with ``gamma = C c`` the
    exact posterior's weights on the training rows, ``rho = ||r(X)||``, ``res = k - K_ZZ c``
    (zero for exact weights; its rounding bounded) and ``W_X = K_ZZ^-1 K_ZX``. The second is
    nearly zero where the prior is resolved at the data (``rho`` small).
    Works on one state (vectors of shape (M,)) or a batch (shape (M, B), reduced over axis 0).
    """
    dot_unit = (mm + 3.0) * unit
    res = k - kzz @ c
    res_n = jnp.sqrt(jnp.sum(res * res, 0)) + jnp.sqrt(mm) * amp2 * (1.0 + c1) * (
        dot_unit + (ek + 1.0) * unit
    )
    gc = cm @ c
    gam = jnp.sqrt(jnp.sum(gc * gc, 0)) + (dot_unit + unit) * cnorm * c2
    cross = 2.0 * (c2 * res_n + gam * (rho * r + wnorm * res_n))
    var = p * p + r * r + jnp.minimum(2.0 * p * r, cross)
    return jnp.sqrt(var) * (1.0 + 4.0 * unit)


def band_component(kind, mm, z0, unit, proven, with_scales):
    """One learned component's cache evaluation, as a function of that component's arrays.

    With ``k = k_Z(x)``, weights ``c = Lj^-T Lj^-1 k`` (any ``c`` keeps the bound; these are
    the projection's), ``q = amp^2 - 2 c.k + c.(K_ZZ c)`` the prior variance of
    ``f(x) - c.f_Z`` and ``p = |G c|`` (``G^T G >= Cov(f_Z | data)``), a proven cache's std is
    ``p + sqrt(q + allowance)`` and its mean ``b.k + c.rho_b`` with the error bound
    ``E sqrt(q + allowance)`` (docs/learning.md). The allowances bound every rounding of the
    evaluation in unit roundoff ``unit`` (:func:`kernel_error_coefficient` for the kernel
    values; the standard dot-product bound ``(M + 3) unit`` for the sums; the rounding of the
    stored arrays to that precision). An unproven cache (``SparseGP``, DTC) returns
    ``sqrt(q + allowance + (p + ...)^2)``.

    Parameters
    ----------
    kind : StationaryKernel or {"se", "matern52"}
    mm : int
        Inducing inputs ``M`` of the arrays the returned function receives; where they are
        padded (``mask`` given), the allowances count the component's own rows
        (``sum(mask)``).
    z0 : array of shape (n,)
        The standardised state.
    unit : float
        Unit roundoff of the precision the evaluation runs in (``2^-53`` for float64).
    proven : bool
        FastGP's band (triangle inequality) or SparseGP's (DTC variance).
    with_scales : bool
        Return the running magnitudes (:func:`band_magnitudes`) instead of the band.

    Returns
    -------
    callable
        the arrays of :data:`BAND_KEYS` (shapes (), (n,), (M, n), (M,) or None, (M, M) x 4,
        (M,) x 2, () x 9) -> three arrays of shape
        (): the mean without the prior mean, the std without the mean-error term and the
        mean-error term; with ``with_scales``, the magnitudes of these.
    """

    def per_comp(
        a,
        l_,
        z,
        mask,
        li,
        kzz,
        g,
        cm,
        b,
        rho_b,
        err,
        ek,
        gnorm,
        bnorm,
        rho_err,
        rho,
        wnorm,
        cnorm,
        mu,
    ):
        k = kernel(kind, a, l_)(z, z0[None, :])[:, 0]
        # the component's own M: padded rows hold exact zeros (masked kernel values, zero
        # rows and columns of Lj^-1, K_ZZ, G and C), and a sum with a zero operand is exact
        # in any order, so every dot product rounds as one of its own M terms, not of the
        # padded M (one component's band does not depend on the others' counts)
        m_c = mm
        if mask is not None:
            k = jnp.where(mask, k, 0.0)
            m_c = jnp.sum(mask.astype(k.dtype))
        dot_unit = (m_c + 3) * unit
        amp2 = a * a
        c = li.T @ (li @ k)
        c1 = jnp.sum(jnp.abs(c))
        c2 = safe_sqrt(c @ c)
        q = amp2 - 2.0 * (c @ k) + c @ (kzz @ c)
        allow = residual_allowance(amp2, c1, m_c, ek, unit)
        r2 = jnp.maximum(q, 0.0) + allow
        r = safe_sqrt(r2)  # > 0 wherever amp > 0
        gc = g @ c
        p = safe_sqrt(gc @ gc) + (dot_unit + unit) * gnorm * c2  # G c's and G's rounding
        abs_b_k = jnp.abs(b) @ jnp.abs(k)
        abs_c_rho = jnp.abs(c) @ jnp.abs(rho_b)
        mean = b @ k + c @ rho_b
        # the mean's rounding, the kernel values' in b.k, and b's and rho_b's storage
        mround = (
            dot_unit * (jnp.abs(mu) + abs_b_k + abs_c_rho)
            + unit * (ek * amp2 * bnorm + abs_c_rho + amp2 * c1 * bnorm)
            + c1 * rho_err
        )
        e_w = err + unit * a * bnorm  # ||m - mu - h|| with b as stored
        if with_scales:
            # a kernel value's relative rounding grows with the scaled distance (exp's
            # argument): |k| (1 + 2 |log(k / amp^2)|) (= |k| (1 + r^2) for the SE kernel)
            pos = k > 0
            logk = jnp.log(jnp.where(pos, k, 1.0) / jnp.where(amp2 > 0, amp2, 1.0))
            k_mag = jnp.where(pos, k * (1.0 + 2.0 * jnp.abs(logk)), 0.0)
            c_mag = jnp.abs(li.T) @ (jnp.abs(li) @ k_mag)
            q_mag = amp2 + 2.0 * (c_mag @ k_mag) + c_mag @ (jnp.abs(kzz) @ c_mag)
            r_mag = q_mag / (2.0 * r)
            p_mag = safe_sqrt(jnp.sum(jnp.square(jnp.abs(g) @ c_mag)))
            mean_mag = jnp.abs(b) @ k_mag + c_mag @ jnp.abs(rho_b)
            if proven:
                return mean_mag, r_mag + p_mag, e_w * r_mag + mround
            return mean_mag, (q_mag + 2.0 * p * p_mag) / (2.0 * safe_sqrt(r2 + p * p)), mround
        if proven:
            return (
                mean,
                _proven_sd(p, r, c, c1, c2, k, kzz, cm, rho, wnorm, cnorm, ek, amp2, m_c, unit),
                e_w * r + mround,
            )
        return mean, safe_sqrt(r2 + p * p), mround

    return per_comp


#: The per-component arrays of a cache, in the order :func:`band_component`'s function takes.
BAND_KEYS = (
    "amp", "ls", "z", "mask", "li", "kzz", "g", "cm", "b", "rho_b", "err", "ek", "gnorm",
    "bnorm", "rho_err", "rho", "wnorm", "cnorm", "mu",
)  # fmt: skip


def band_point(p, x, kind, unit, proven=True):
    """Per learned component: cache mean (without the prior mean), std and ``E r(x)``.

    Parameters
    ----------
    p : dict of str to array
        :meth:`FastGP.arrays <safestab.learning.FastGP.arrays>`: ``offset`` and ``scale``
        (n,) and, per learned component padded to a common ``M``, the :data:`BAND_KEYS`.
    x : array of shape (n,)
    kind : StationaryKernel or {"se", "matern52"}
    unit : float
        Unit roundoff of the precision the step will be evaluated in (a Python float;
        :meth:`FastGP.for_precision <safestab.learning.FastGP.for_precision>`): every
        rounding of the evaluation is bounded relative to it.
    proven : bool
        FastGP's band, or SparseGP's DTC band.

    Returns
    -------
    mean, sd, merr : arrays of shape (k,)
    """
    z0 = (x - p["offset"]) / p["scale"]
    per_comp = band_component(kind, p["z"].shape[1], z0, unit, proven, False)
    return jax.vmap(per_comp)(*(p[key] for key in BAND_KEYS))


def band_point_unpadded(p, comps, x, kind, unit, proven=True):
    """:func:`band_point` with each component at its own number of inducing inputs.

    ``comps``: per component, a dict of its :data:`BAND_KEYS` arrays without padding (``mask``
    None). The same values as the padded, vmapped evaluation, with fewer operations in
    exported code (the padded rows and their masks are gone).
    """
    z0 = (x - p["offset"]) / p["scale"]
    outs = []
    for c in comps:
        per_comp = band_component(kind, c["z"].shape[0], z0, unit, proven, False)
        outs.append(per_comp(*(c[key] for key in BAND_KEYS)))
    return tuple(jnp.stack([o[i] for o in outs]) for i in range(3))


#: :func:`band_point` at states (B, n): ``(p, x, kind, unit, proven)`` -> three arrays (B, k).
#: The cache's arrays are arguments: one compilation per (M, kernel), not per cache.
band_batch = jax.jit(
    jax.vmap(band_point, in_axes=(None, 0, None, None, None)), static_argnums=(2, 3, 4)
)


def band_magnitudes(p, x, kind, unit, proven=True):
    """Per learned component: the magnitudes the cache's mean and std are rounded relative to.

    A running-error analysis of :func:`band_point`: every kernel value carries a relative
    rounding error, every product a rounding relative to the product of the absolute values
    (the weights ``c`` through both factors ``|Lj^-T| |Lj^-1| |k|``, where an ill-conditioned
    ``K_ZZ`` amplifies it). Carried through ``q``, the square root and the sums to first order,
    the mean's error is a small multiple of ``u`` times ``mean_mag`` and the std's of ``u``
    times ``sd_mag + merr_mag / min_beta``. These are what two float64 evaluations (XLA's and
    the exported C) differ by; the band's own allowances bound the distance to the exact
    values.

    Returns
    -------
    mean_mag, sd_mag, merr_mag : arrays of shape (k,)
        The mean's magnitude, the std's without the mean-error term, the mean-error term's.
    """
    z0 = (x - p["offset"]) / p["scale"]
    per_comp = band_component(kind, p["z"].shape[1], z0, unit, proven, True)
    return jax.vmap(per_comp)(*(p[key] for key in BAND_KEYS))


#: :func:`band_magnitudes` at states (B, n), compiled once per shape.
band_magnitudes_batch = jax.jit(
    jax.vmap(band_magnitudes, in_axes=(None, 0, None, None, None)), static_argnums=(2, 3, 4)
)


def band_products(
    xs_t, inv_ls, zl, mask, li, kzz, g, cm, b, rho_b, scal, min_beta, *, kind, proven=True
):
    """One component's cache mean and guaranteed std at a batch of states, as matrix products.

    The formula of :func:`band_point` in float64 (FastGP's proven band) with the batch as the
    minor (contiguous) axis of every intermediate, ``(M, B)``: the sums over the inducing
    inputs are then additions of whole rows, fused with the elementwise work, instead of short
    reductions along the minor axis. Only the summation order of the dot products differs from
    :func:`band_point`; the allowances bound any order.

    Parameters
    ----------
    xs_t : array of shape (n, B)
        Standardised states, transposed.
    inv_ls : array of shape (n,)
        Inverse lengthscales of the standardised inputs.
    zl : array of shape (M, n)
        Standardised inducing inputs times ``inv_ls`` (padded rows masked out).
    mask : array of shape (M,)
        ``mask > 0`` on the rows in use.
    li, kzz, g, cm : arrays of shape (M, M)
        ``Lj^-1``, ``K_ZZ``, ``G`` and ``C``.
    b, rho_b : arrays of shape (M,)
        Mean weights and residual.
    scal : array of shape (11,)
        ``amp, mu, E, ek, gnorm, bnorm, rho_err, rho, wnorm, cnorm`` and the component's own
        ``M`` (the rows in use; padded rows are exact zeros and round nothing) as a float.
    min_beta : array of shape ()
    kind : StationaryKernel or {"se", "matern52"}
    proven : bool
        FastGP's band, or SparseGP's DTC band (``sqrt(q + allowance + p^2)``).

    Returns
    -------
    mean, std : arrays of shape (B,)
    """
    unit = float(np.finfo(float).eps) / 2
    amp, mu, err, ek, gnorm, bnorm, rho_err, rho, wnorm, cnorm, mm = (scal[i] for i in range(11))
    dot_unit = (mm + 3.0) * unit
    xl = xs_t * inv_ls[:, None]  # (n, B)
    k = kernel_from_r2(kind, amp, sq_dist_exact(xl, zl))
    k = jnp.where(mask[:, None] > 0, k, 0.0)  # (M, B)
    amp2 = amp * amp
    c = li.T @ (li @ k)
    c1 = jnp.sum(jnp.abs(c), 0)
    c2 = jnp.sqrt(jnp.sum(c * c, 0))
    q = amp2 - 2.0 * jnp.sum(c * k, 0) + jnp.sum(c * (kzz @ c), 0)
    allow = residual_allowance(amp2, c1, mm, ek, unit)
    r = jnp.sqrt(jnp.maximum(q, 0.0) + allow)
    gc = g @ c
    p = jnp.sqrt(jnp.sum(gc * gc, 0)) + (dot_unit + unit) * gnorm * c2
    abs_b_k = jnp.abs(b) @ jnp.abs(k)
    abs_c_rho = jnp.abs(rho_b) @ jnp.abs(c)
    mround = (
        dot_unit * (jnp.abs(mu) + abs_b_k + abs_c_rho)
        + unit * (ek * amp2 * bnorm + abs_c_rho + amp2 * c1 * bnorm)
        + c1 * rho_err
    )
    e_w = err + unit * amp * bnorm
    if not proven:
        return b @ k + rho_b @ c + mu, jnp.sqrt(r * r + p * p) + mround / min_beta
    sd = _proven_sd(p, r, c, c1, c2, k, kzz, cm, rho, wnorm, cnorm, ek, amp2, mm, unit)
    std = sd + (e_w * r + mround) / min_beta
    return b @ k + rho_b @ c + mu, std


def bucket(used: int) -> int:
    """Inducing inputs kept for a component that uses ``used``: 1, 2, 4, then multiples of 4.

    Caches whose counts fall in one bucket share compiled shapes (a compilation of a closed
    loop costs about 10 s); the padding adds at most 60 % to that component's work (5 -> 8),
    at most a third from 9 inducing inputs up.
    """
    return max(used, 1) if used <= 2 else -(-used // 4) * 4
