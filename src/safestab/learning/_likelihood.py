"""The GP's log marginal likelihood, its gradient and its maximisation (internal).

:class:`~safestab.learning.GaussianProcessModel` fits each learned component's
hyperparameters with :func:`pose_component` and :func:`fit_components`: SciPy's L-BFGS-B on
the likelihood and gradient of :func:`nll_value_and_grad` (unchecked and jittable; the data are
arguments), from several starts, every component's starts in one pool of threads where BLAS
runs one thread (:func:`fit_components`). The
hyperparameter vector ``theta`` of one component is
``[log amplitude, log noise, mean, log lengthscale_1, ..., log lengthscale_n]`` (lengthscales
of the standardised inputs).
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jax.scipy.linalg import cho_solve
from tinygp import GaussianProcess

from .._batching import cpu_count, in_threads
from ..errors import ConvergenceWarning, NumericalError
from ._fit_cache import fit_cache_dir, load, problem_key, store
from ._posterior import kernel
from ._threads import blas_single_threaded
from .kernels import as_kernel

__all__ = [
    "fit_components",
    "nll_tinygp",
    "nll_value_and_grad",
    "nn_noise",
    "optimise_start",
    "pose_component",
    "stationary",
    "unpack",
]


def unpack(theta, n_features):
    """Amplitude, noise std, mean (each of shape ()) and lengthscales (n,) from ``theta``."""
    log_amp, log_noise, mean = theta[0], theta[1], theta[2]
    log_ls = theta[3 : 3 + n_features]
    return jnp.exp(log_amp), jnp.exp(log_noise), mean, jnp.exp(log_ls)


@functools.partial(jax.jit, static_argnames=("kind",))
def nll_value_and_grad(theta, xs, y, fixed_var, use_fixed, use_mean, jitter, *, kind):
    """Negative log marginal likelihood and its gradient in ``theta`` (GPML eq. (5.9)).

    The data are arguments, so one compilation serves every component and every start. The
    gradient ``-1/2 tr((alpha alpha^T - K^-1) dK/dtheta)`` is written out: three times
    faster than reverse-mode through the Cholesky factorisation at Q = 500 (a test checks
    it against ``jax.grad`` of :func:`nll_tinygp`).

    Parameters
    ----------
    theta : array of shape (3 + n,)
    xs : array of shape (Q, n)
        Standardised inputs.
    y : array of shape (Q,)
    fixed_var : array of shape ()
        Noise variance used instead of ``exp(theta[1])^2`` where ``use_fixed``.
    use_fixed : bool array of shape ()
    use_mean : array of shape ()
        1.0 for a constant prior mean ``theta[2]``, 0.0 for a zero mean.
    jitter : array of shape ()
        Relative diagonal jitter (times ``amplitude^2``).
    kind : StationaryKernel or {"se", "matern52"}

    Returns
    -------
    value : array of shape ()
    grad : array of shape (3 + n,)
    """
    q, n = xs.shape
    amp, noise, mean, ls = unpack(theta, n)
    z = xs / ls
    diff2 = (z[:, None, :] - z[None, :, :]) ** 2  # (Q, Q, n)
    r2 = jnp.sum(diff2, -1)
    base = as_kernel(kind)
    k0 = base.of_r2(r2, jnp)
    dk0 = -2.0 * base.d_of_r2(r2, jnp)  # d k0 / d log ls_d = dk0 * diff2_d
    noise_var = jnp.where(use_fixed, fixed_var, noise**2)
    s2 = noise_var + jitter * amp**2
    kmat = amp**2 * k0 + s2 * jnp.eye(q)
    chol = jnp.linalg.cholesky(kmat)
    resid = y - mean * use_mean
    alpha = cho_solve((chol, True), resid)
    value = 0.5 * resid @ alpha + jnp.sum(jnp.log(jnp.diag(chol))) + 0.5 * q * jnp.log(2 * jnp.pi)
    w = jnp.outer(alpha, alpha) - cho_solve((chol, True), jnp.eye(q))
    tr_w = jnp.trace(w)
    g_amp = -0.5 * (2.0 * amp**2 * jnp.sum(w * k0) + 2.0 * jitter * amp**2 * tr_w)
    g_noise = jnp.where(use_fixed, 0.0, -0.5 * tr_w * 2.0 * noise**2)
    g_mean = -jnp.sum(alpha) * use_mean
    g_ls = -0.5 * amp**2 * jnp.einsum("ij,ijd->d", w * dk0, diff2)
    return value, jnp.concatenate([jnp.stack([g_amp, g_noise, g_mean]), g_ls])


def nll_tinygp(theta, xs, y, fixed_var, use_fixed, use_mean, jitter, kind):
    """The same negative log marginal likelihood through tinygp (reference for the tests)."""
    amp, noise, mean, ls = unpack(theta, xs.shape[1])
    var = jnp.where(use_fixed, fixed_var, noise**2) + jitter * amp**2
    gp = GaussianProcess(kernel(kind, amp, ls), xs, diag=var, mean=mean * use_mean)
    return -gp.log_probability(y)


def stationary(theta, grad, lo, hi, value, rtol: float = 1e-4) -> bool:
    """Whether the projected gradient is below ``rtol (1 + |value|)``.

    L-BFGS-B's line search stalls ("ABNORMAL") when the likelihood's rounding noise (about
    1e-4 nats at Q = 500 on the ACC data, where the kernel matrix is ill-conditioned) exceeds
    the decrease it looks for. With this test passed, changing any log-hyperparameter by 0.01
    changes the log-likelihood by less than 1e-6 of its size: converged for any use.
    """
    g = np.asarray(grad, float)
    g = np.where((theta <= lo) & (g > 0), 0.0, g)
    g = np.where((theta >= hi) & (g < 0), 0.0, g)
    g = np.where(lo == hi, 0.0, g)
    return bool(np.isfinite(value) and np.max(np.abs(g)) <= rtol * (1.0 + abs(value)))


def nn_noise(xs: np.ndarray, y: np.ndarray, rng: np.random.Generator) -> float:
    """Noise std estimated from nearest-neighbour differences (on at most 1,000 rows)."""
    rows = rng.choice(len(xs), min(len(xs), 1000), replace=False)
    xr, yr = xs[rows], y[rows]
    d2 = np.sum((xr[:, None, :] - xr[None, :, :]) ** 2, -1)
    np.fill_diagonal(d2, np.inf)
    diff = yr - yr[np.argmin(d2, 1)]
    # y_i - y_j ~ N(0, 2 s^2) where f is locally flat; median of a chi^2_1 is 0.4549
    return float(np.sqrt(np.median(diff**2) / (2 * 0.4549)))


def optimise_start(fun, start, bounds, lo, hi, max_iter):
    """L-BFGS-B from one start: ``(value, theta, nit, converged, message)``."""
    if max_iter == 0:
        return (fun(start)[0], start, 0, False, "max_iter=0: start values kept")
    with np.errstate(all="ignore"):  # in the calling thread (NumPy's error state is per thread)
        res = scipy.optimize.minimize(
            fun, start, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": max_iter}
        )
    ok = res.status == 0 or stationary(res.x, res.jac, lo, hi, res.fun)
    return (float(res.fun), res.x, int(res.nit), bool(ok), str(res.message))


#: Starts run at once only while their working arrays together stay under this many bytes
#: (about ``8 Q^2 (n + 6)`` each: the (Q, Q, n) differences and a few Q x Q matrices), so
#: that a fit on many rows keeps the peak memory of one start.
THREADS_MEMORY = 2 * 2**30


def fit_components(model, problems):
    """Maximise each component's log marginal likelihood over its hyperparameters.

    L-BFGS-B from the data-driven and ``model.n_restarts`` seeded random starts of each
    problem (:func:`pose_component`); the best finite start is kept. The starts of every
    component are independent optimisations. Where BLAS runs one thread
    (:func:`~safestab.learning.batched.one_blas_thread`, entered by the caller), they run
    ``model.n_threads`` at a time in threads (default one per CPU; JAX releases the GIL
    while the likelihood runs): no start's arithmetic then depends on what runs beside it,
    so the results do not depend on the count. With a multi-threaded BLAS they run one after
    the other (two threads in a multi-threaded BLAS could split its work otherwise), and so
    they do where their working arrays together would exceed :data:`THREADS_MEMORY`. Warns
    (``stacklevel`` for a call from ``model.fit``) when a fit did not converge or a
    hyperparameter sits at its bound, component by component.

    Parameters
    ----------
    model : GaussianProcessModel
        Its settings ``kernel``, ``mean``, ``jitter``, ``max_iter``, ``n_restarts`` and
        ``n_threads``.
    problems : list of dict
        One :func:`pose_component` per component.

    Returns
    -------
    list of dict
        Per component: ``amplitude``, ``noise`` (effective), ``mean``, ``lengthscale`` (n,) of
        the standardised inputs, ``lml``, ``start_lmls``, ``nit``, ``converged``, ``message``.

    Raises
    ------
    NumericalError
        If a component's likelihood is not finite at any start.
    """
    # the optimisation is a deterministic function of the problem: a run that poses it again
    # reads the first run's results (_fit_cache.py; off with SAFESTAB_FIT_CACHE=off)
    found = [
        None if pr["key"] is None else load(pr["key"], *np.shape(pr["starts"])) for pr in problems
    ]
    tasks = [(i, s) for i, pr in enumerate(problems) if found[i] is None for s in pr["starts"]]

    def run(task):
        i, s = task
        pr = problems[i]
        return optimise_start(pr["fun"], s, pr["bounds"], pr["lo"], pr["hi"], model.max_iter)

    workers = 1  # one after the other: all read from the cache, or a multi-threaded BLAS
    if tasks and blas_single_threaded():
        per_start = max(8 * pr["q"] ** 2 * (pr["n"] + 6) for pr in problems)
        workers = max(
            1, min(len(tasks), model.n_threads or cpu_count(), THREADS_MEMORY // per_start)
        )
    done = iter(in_threads(run, tasks, workers, lambda count: None))
    for i, pr in enumerate(problems):
        if found[i] is None:
            found[i] = [next(done) for _ in pr["starts"]]
            if pr["key"] is not None:
                store(pr["key"], found[i])
    fits = []
    for pr, results in zip(problems, found, strict=True):  # a loop: stacklevel counts frames
        fits.append(_finish(model, pr, results))
    return fits


def pose_component(model, xs, y, fixed_noise, rng, comp):
    """One component's likelihood problem: its starts (drawn from ``rng``), bounds and data.

    Parameters
    ----------
    model : GaussianProcessModel
    xs : array of shape (Q, n)
        Standardised inputs.
    y : array of shape (Q,)
    fixed_noise : float or None
        Known noise std; fitted when None.
    rng : numpy.random.Generator
        Draws the nearest-neighbour noise rows and the random starts, in this order.
    comp : int
        The component's index (for messages).

    Returns
    -------
    dict
        What :func:`fit_components` needs (``fun``, ``starts``, ``bounds``, ``key``, ...).
    """
    n = xs.shape[1]
    sd = float(np.std(y))
    rms = float(np.sqrt(np.mean(y**2)))
    sd = sd if sd > 0 else (rms if rms > 0 else 1.0)
    amp_scale = max(rms, sd) if model.mean == "zero" else sd
    mean0 = float(np.mean(y)) if model.mean == "constant" else 0.0
    lo_amp, hi_amp = np.log(1e-6 * amp_scale), np.log(1e3 * amp_scale)
    lo_noise, hi_noise = np.log(1e-6 * sd), np.log(10 * sd)
    lo_ls, hi_ls = np.log(1e-3), np.log(1e5)  # long: irrelevant inputs, as in sklearn
    nn = float(np.clip(nn_noise(xs, y, rng), 1e-4 * sd, 0.5 * sd))
    starts = [
        np.concatenate([[np.log(amp_scale), np.log(0.1 * sd), mean0], np.zeros(n)]),
        np.concatenate([[np.log(amp_scale), np.log(nn), mean0], np.full(n, np.log(3.0))]),
    ]
    for _ in range(model.n_restarts):
        starts.append(
            np.concatenate(
                [
                    [
                        np.log(amp_scale) + rng.uniform(np.log(0.3), np.log(3.0)),
                        np.log(sd) + rng.uniform(np.log(1e-3), np.log(0.3)),
                        mean0,
                    ],
                    rng.uniform(np.log(0.3), np.log(30.0), n),
                ]
            )
        )
    if fixed_noise is not None:
        noise_bound = (0.0, 0.0)  # unused: the fixed variance enters instead
        for s in starts:
            s[1] = 0.0
    else:
        noise_bound = (lo_noise, hi_noise)
    bounds = [
        (lo_amp, hi_amp),
        noise_bound,
        (None, None) if model.mean == "constant" else (0.0, 0.0),
    ] + [(lo_ls, hi_ls)] * n
    lo = np.array([-np.inf if b[0] is None else b[0] for b in bounds])
    hi = np.array([np.inf if b[1] is None else b[1] for b in bounds])
    args = (
        jnp.asarray(xs),
        jnp.asarray(y),
        jnp.asarray(0.0 if fixed_noise is None else fixed_noise**2),
        jnp.asarray(fixed_noise is not None),
        jnp.asarray(float(model.mean == "constant")),
        jnp.asarray(model.jitter),
    )

    def fun(t):
        v, g = nll_value_and_grad(jnp.asarray(t), *args, kind=model.kernel)
        return float(v), np.asarray(g, dtype=float)

    starts = [np.clip(s, lo, hi) for s in starts]
    key = None if fit_cache_dir() is None else problem_key(
        {"kernel": model.kernel, "max_iter": int(model.max_iter), "bounds": repr(bounds),
         "fixed_noise": None if fixed_noise is None else float(fixed_noise).hex(),
         "mean": model.mean, "jitter": float(model.jitter).hex()},
        {"xs": xs, "y": y, "starts": np.stack(starts)},
    )  # fmt: skip
    return {
        "comp": comp, "n": n, "q": xs.shape[0], "sd": sd, "fixed_noise": fixed_noise, "fun": fun,
        "starts": starts, "bounds": bounds, "lo": lo, "hi": hi, "lo_noise": lo_noise,
        "lo_ls": lo_ls, "key": key,
    }  # fmt: skip


def _finish(model, pr, results):
    """One component's fit from the results of its starts (see :func:`fit_components`)."""
    comp, n, fixed_noise, sd = pr["comp"], pr["n"], pr["fixed_noise"], pr["sd"]
    lo_noise, lo_ls, starts = pr["lo_noise"], pr["lo_ls"], pr["starts"]
    values = np.array([r[0] for r in results])
    finite = np.isfinite(values)
    if not np.any(finite):
        raise NumericalError(
            f"the marginal likelihood of component {comp} is not finite at any of the "
            f"{len(starts)} starts; the kernel matrix is not positive definite: try "
            "increasing the noise (noise=) or jitter="
        )
    best = int(np.argmin(np.where(finite, values, np.inf)))
    fun_best, theta, nit, converged, message = results[best]
    if model.max_iter == 0:
        warnings.warn(
            f"max_iter=0: component {comp} keeps the best of {len(starts)} start values; "
            "the hyperparameters are not fitted",
            ConvergenceWarning,
            stacklevel=4,
        )
    elif not converged:
        warnings.warn(
            f"the fit of component {comp} did not converge: L-BFGS-B stopped after {nit} "
            f"iterations ({message}); raise max_iter= or check the data",
            ConvergenceWarning,
            stacklevel=4,
        )
    amp, nz, mu, ls = (np.asarray(v) for v in unpack(jnp.asarray(theta), n))
    if fixed_noise is not None:
        nz = np.asarray(fixed_noise)
    elif model.max_iter > 0 and theta[1] <= lo_noise + 1e-6:
        warnings.warn(
            f"the fitted noise of component {comp} is at its lower bound (1e-6 std(y) = "
            f"{1e-6 * sd:.3g}): the likelihood sees no noise (duplicate rows? an "
            "interpolating fit?); fix noise= from the sensor's specification",
            ConvergenceWarning,
            stacklevel=4,
        )
    noise_eff = float(np.sqrt(nz**2 + model.jitter * amp**2))
    # a lengthscale at its lower bound matters only where the signal is not negligible
    if model.max_iter > 0 and np.any(theta[3:] <= lo_ls + 1e-6) and amp > noise_eff:
        dims = np.flatnonzero(theta[3:] <= lo_ls + 1e-6).tolist()
        warnings.warn(
            f"the fitted lengthscale of component {comp} along input(s) {dims} is at its "
            "lower bound (1e-3 std(x)): the GP treats the rows as unrelated points and "
            "predicts the prior mean between them (noise=0 or too small on noisy data? too "
            "few rows?); fit the noise or give the sensor's noise",
            ConvergenceWarning,
            stacklevel=4,
        )
    return {
        "amplitude": float(amp),
        "noise": noise_eff,
        "mean": float(mu) if model.mean == "constant" else 0.0,
        "lengthscale": ls,
        "lml": -fun_best,
        "start_lmls": np.where(finite, -values, -np.inf),
        "nit": nit,
        "converged": converged,
        "message": message,
    }
