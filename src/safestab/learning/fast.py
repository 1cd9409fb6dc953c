"""A prediction cache for the control loop, cost O(M^2) per query, with a proven band.

From a fitted :class:`~safestab.learning.GaussianProcessModel`, pick ``M`` inducing inputs
``Z`` among the training inputs (greedy pivoted Cholesky of the prior kernel matrix). At a
query ``x``, with ``k = k_Z(x)`` and the projection weights ``c = K_ZZ^-1 k`` (two products
with ``Lj^-1``, ``Lj Lj^T = K_ZZ``), write ``f(x) = c.f_Z + e(x)``. Then

    sigma(x) <= sqrt(c^T S c) + ||e_x||,       ||e_x||^2 = q(x) = k(x, x) - 2 c.k + c^T K_ZZ c,
    m(x)      = mu + b.k + c.rho_b + <m - mu - h, e_x>,       |<m - mu - h, e_x>| <= E ||e_x||,

with ``S = Cov(f_Z | data)`` (an ``M x M`` matrix computed once from the exact factor),
``h = sum_j b_j k(z_j, .)`` for any weights ``b`` (the projection of the exact mean),
``rho_b = m(Z) - mu - K_ZZ b`` and ``E = ||m - mu - h||_k``. The first line is the triangle
inequality for standard deviations (the posterior variance of ``e(x)`` is at most its prior
variance); where the prior is resolved at the data a second bound, ``sigma^2 <= c^T S c + q``
plus a cross term through the data, is tighter and the cache takes the smaller. The mean is
the reproducing property. All hold for *any* weights ``c``, so the cache evaluates ``q`` as
the quadratic it is, not as ``k(x, x) - |Lj^-1 k|^2``: the rounding of that evaluation is
bounded by ``(1 + |c|_1)^2 amp^2`` times a small multiple of the unit roundoff, with no
``cond(K_ZZ)`` in it (the previous cache's allowance, ``2 (M + 2 + cond(Lj)) u amp^2``, made
its band hundreds of times the exact one where the exact std is far below the amplitude).
``E`` is computed once in extended precision. With ``r = sqrt(q + allowance)`` the cache
returns ``m~(x) = mu + b.k + c.rho_b`` and
``sigma~(x) = sd(x) + (E r + mean rounding) / min_beta``, ``sd`` the smaller variance bound
with ``r`` for ``||e_x||``, so for every ``beta >= min_beta`` its band ``m~ +- beta sigma~``
contains the exact band ``m +- beta sigma``, far from the data too (docs/learning.md).
"""

from __future__ import annotations

import copy
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._batching import device_array
from .._validation import check_finite, check_scalar_range, is_concrete
from .._values import register_model
from ..errors import DimensionError, InducingPointsWarning, ParameterError
from ._checks import check_fitted
from ._posterior import (
    BAND_KEYS,
    band_batch,
    band_magnitudes_batch,
    band_point,
    band_point_unpadded,
    kernel_error_coefficient,
    kernel_matrix,
    residual_allowance,
)
from ._predict import Predictor
from ._threads import fit_threads
from .gp import GaussianProcessModel
from .kernels import as_kernel

__all__ = ["EXCESS_WARN", "FastGP", "INFLATION_WARN", "STD_RATIO_WARN"]

#: A fast cache's std at more than 1 % of the training inputs above this many noise stds is
#: recorded in ``inflation_at_training_`` (the exact posterior std there is at most the noise
#: std).
INFLATION_WARN = 3.0
#: :class:`InducingPointsWarning` when the cache's std at the training inputs is more than this
#: many times the exact std (median over a sample of them) and exceeds it by more than
#: ``EXCESS_WARN`` noise stds: an excess far below the measurement noise (a component whose
#: amplitude is below the noise, the GP having learned next to nothing) changes no decision.
STD_RATIO_WARN = 1.5
EXCESS_WARN = 0.1
_U = np.finfo(float).eps / 2  # unit roundoff of float64
_U_FLOAT = float(np.finfo(np.float32).eps / 2)
_LD = np.longdouble
_U_LD = float(np.finfo(np.longdouble).eps / 2)  # 2^-64 on x86-64; 2^-53 where it is double
#: Training inputs at which the exact std is evaluated (the stopping rule and the warning).
_STD_SAMPLE = 128


def pivoted_cholesky(kfn, xs: np.ndarray, amp2: float, m: int, tol: float, floor: float = 0.0):
    """Pivoted Cholesky: greedy choice of ``m`` distinct rows of largest residual prior variance.

    A chosen row's residual is exactly zero: it is set so, not left to the rounding of the
    update (which leaves it at a few ``u amp2`` and, with ``tol = 0``, let the row be chosen
    again; a repeated inducing input broke the cache's ``Cov(f_Z | data)``, whose formula
    takes the chosen rows as distinct). Stops early where no unchosen row's residual exceeds
    ``tol amp2`` (or, after the first, ``floor``).

    Returns the chosen indices and the residual prior variance left at every row.
    """
    q = xs.shape[0]
    m = min(m, q)
    diag = np.full(q, amp2)
    rows = np.zeros((m, q))
    chosen: list[int] = []
    for i in range(m):
        j = int(np.argmax(diag))
        if diag[j] <= tol * amp2 or (chosen and diag[j] <= floor):
            break
        chosen.append(j)
        col = np.asarray(kfn(xs, xs[j : j + 1]))[:, 0] - rows[:i].T @ rows[:i, j]
        rows[i] = col / np.sqrt(diag[j])
        diag = np.maximum(diag - rows[i] ** 2, 0.0)
        diag[chosen] = 0.0  # exactly resolved: never chosen again
    return np.array(chosen), diag


def size_bucket(n: int) -> int:
    """``n`` rounded up to one of four sizes per octave (16, 20, 24, 28, 32, 40, ...).

    The host-side kernel matrices and batched band evaluations are padded to these sizes, so
    that a data set whose pivoted Cholesky stops at a new number of inducing inputs runs a
    program compiled for an earlier one: one compilation per bucket, not per size (a Monte
    Carlo study of 1,000 data sets would compile a handful of programs for each, and each
    compiled program holds memory maps of its own), at most 25 % more work.
    """
    n = int(n)
    if n <= 16:
        return 16
    step = 1 << (n.bit_length() - 3)
    return -(-n // step) * step


def kernel_rows(
    amp: float, ls, x1: np.ndarray, x2: np.ndarray, kind: str, pad: tuple[bool, bool] = (True, True)
) -> np.ndarray:
    """The kernel matrix ``(N1, N2)`` of ``x1`` (N1, n) and ``x2`` (N2, n), as a numpy array.

    :func:`kernel_matrix` with the rows of the arguments flagged in ``pad`` padded (by
    repeating the last) to :func:`size_bucket` sizes, then cut back. Pad what varies from call
    to call (the inducing inputs), not what a study keeps fixed (its training rows, one
    pivot's column). An entry may differ from the unpadded call's in its last bit (XLA
    vectorises a different loop length).
    """
    x1, x2 = np.asarray(x1, float), np.asarray(x2, float)
    n1, n2 = x1.shape[0], x2.shape[0]

    def padded(x, flag):
        extra = size_bucket(len(x)) - len(x) if flag else 0
        return np.concatenate([x, np.repeat(x[-1:], extra, 0)]) if extra else x

    k = kernel_matrix(amp, device_array(ls), device_array(padded(x1, pad[0])),
                      device_array(padded(x2, pad[1])), kind=kind)  # fmt: skip
    return np.asarray(k)[:n1, :n2]


def pad_inducing(p: dict, m: int) -> dict:
    """A cache's arrays (``FastGP.arrays`` layout) with the inducing axis padded to ``m``.

    Padded rows are what :meth:`FastGP._pack` gives a component with fewer inducing inputs
    than the largest: zero inputs, weights and maps, and ``mask`` False.
    """
    have = p["z"].shape[1]
    if m == have:
        return p
    out = dict(p)
    grow = m - have
    # numpy's pad (an eager jnp.pad would compile a program per size)
    out["z"] = device_array(np.pad(np.asarray(p["z"]), ((0, 0), (0, grow), (0, 0))))
    out["mask"] = device_array(np.pad(np.asarray(p["mask"]), ((0, 0), (0, grow))))
    for key in ("li", "kzz", "g", "cm"):
        out[key] = device_array(np.pad(np.asarray(p[key]), ((0, 0), (0, grow), (0, grow))))
    for key in ("b", "rho_b"):
        out[key] = device_array(np.pad(np.asarray(p[key]), ((0, 0), (0, grow))))
    return out


def _psd_root(mat: np.ndarray) -> np.ndarray:
    """``G`` with ``G^T G = mat`` after clipping negative eigenvalues to 0 (never smaller)."""
    evals, evecs = np.linalg.eigh(0.5 * (mat + mat.T))
    return (evecs * np.sqrt(np.maximum(evals, 0.0))).T


def _kernel_np(kind, amp: float, ls: np.ndarray, x1: np.ndarray, x2: np.ndarray, dtype):
    """The kernel matrix ``(N1, N2)`` in numpy precision ``dtype`` (``longdouble``: extended)."""
    a, b = x1.astype(dtype) / ls.astype(dtype), x2.astype(dtype) / ls.astype(dtype)
    r2 = np.square(a[:, None, 0] - b[None, :, 0])
    for d in range(1, a.shape[1]):  # by coordinate: no (N1, N2, n) array
        r2 += np.square(a[:, None, d] - b[None, :, d])
    return dtype(amp) ** 2 * as_kernel(kind).of_r2(r2, np)


def _quad_form(kind, amp, ls, xs, beta, dtype, unit, chunk: int = 512):
    """``beta^T K beta`` in precision ``dtype`` by row blocks, and a bound on its rounding."""
    q = xs.shape[0]
    ek = kernel_error_coefficient(kind, np.max(np.abs(xs), 0) / ls) * unit
    beta = beta.astype(dtype)
    abs_beta = np.abs(beta)
    e2, e2_abs = dtype(0), dtype(0)
    for s in range(0, q, chunk):  # K is symmetric: the diagonal block and twice the right
        e = min(s + chunk, q)
        kb = _kernel_np(kind, amp, ls, xs[s:e], xs[s:], dtype)
        kd, ko = kb[:, : e - s], kb[:, e - s :]
        e2 += beta[s:e] @ (kd @ beta[s:e]) + 2 * (beta[s:e] @ (ko @ beta[e:]))
        e2_abs += abs_beta[s:e] @ (kd @ abs_beta[s:e]) + 2 * (abs_beta[s:e] @ (ko @ abs_beta[e:]))
    err = 2 * (q + 4) * unit * e2_abs + ek * dtype(amp) ** 2 * np.sum(abs_beta) ** 2
    return float(e2), float(err)


def _mean_terms(kind, amp, ls, xs, alpha, z, idx, lj, chunk: int = 512):
    """Mean weights ``b``, ``rho_b``, its error bound and ``E = ||m - mu - h||_k``.

    ``m(Z) - mu = K_ZX alpha``, ``rho_b = m(Z) - mu - K_ZZ b`` and ``E^2 = beta^T K beta``
    (``beta = alpha - b`` at the inducing rows) are sums of ``Q`` terms whose size is far above
    their value where ``alpha`` is large (small noise): in ``longdouble`` (``E`` in float64
    first, kept where its rounding bound is below a quarter of its value), by row blocks (no
    ``Q x Q`` matrix), with the dot-product error bound ``(Q + 4) u |terms|`` and the kernel
    values' (:func:`~safestab.learning._posterior.kernel_error_coefficient`) added.
    """
    q = xs.shape[0]
    ek = kernel_error_coefficient(kind, np.max(np.abs(xs), 0) / ls) * _U_LD
    a_ld = alpha.astype(_LD)
    kzx = _kernel_np(kind, amp, ls, z, xs, _LD)
    mz = kzx @ a_ld
    b = scipy.linalg.cho_solve((lj, True), mz.astype(float))
    b_ld = b.astype(_LD)
    kzz = _kernel_np(kind, amp, ls, z, z, _LD)
    rho = mz - kzz @ b_ld
    amp2 = _LD(amp) ** 2
    rho_err = (q + len(z) + 4) * _U_LD * np.max(
        np.abs(kzx) @ np.abs(a_ld) + np.abs(kzz) @ np.abs(b_ld)
    ) + ek * amp2 * (np.sum(np.abs(a_ld)) + np.sum(np.abs(b_ld)))
    beta = a_ld.copy()
    np.subtract.at(beta, idx, b_ld)
    # float64 first (a few times faster); extended precision where its rounding dominates
    e2, err = _quad_form(kind, amp, ls, xs, beta.astype(float), np.float64, _U)
    if err > 0.25 * max(e2, 0.0):
        e2, err = _quad_form(kind, amp, ls, xs, beta, _LD, _U_LD)
    e_norm = float(np.sqrt(max(e2 + err, 0.0)))
    return b, rho.astype(float), float(rho_err) + _U * float(np.max(np.abs(rho))), e_norm


def _cross_terms(model, j, xs, z, idx, li, kzz, v, ek):
    """``C`` (``|C c| = |Gamma c|``), ``rho`` and ``||W_X||`` of the cross term.

    ``Gamma = (K + s^2 I)^-1 K_XZ = E_Z - s^2 L^-T V`` (``V = L^-1 E_Z``, ``Z`` among the
    training inputs) are the exact posterior's weights on the training rows for the inducing
    functions; ``C`` is the triangular factor of its QR decomposition, enlarged by the
    rounding of the factorisation. ``rho = ||r(X)||``: the residual prior std at every
    training input, evaluated as a query is (``q`` with its allowance), so an upper bound.
    ``W_X = K_ZZ^-1 K_ZX``: its spectral norm, 1 % up.
    """
    q, m = xs.shape[0], len(z)
    amp = float(model.amplitude_[j])
    s2 = float(model.noise_[j]) ** 2
    u_ = scipy.linalg.solve_triangular(np.asarray(model.chol_[j]).T, v, lower=False)
    gam = -s2 * u_
    gam[idx, np.arange(m)] += 1.0
    cm = np.linalg.qr(gam, mode="r")
    cm = cm * (1.0 + 4 * (q + m) * _U)
    kzx = kernel_rows(amp, model.lengthscale_std_[j], z, xs, model.kernel, pad=(True, False))
    wx = li.T @ (li @ kzx)
    qx = amp * amp - 2.0 * np.sum(wx * kzx, 0) + np.sum(wx * (kzz @ wx), 0)
    c1 = np.sum(np.abs(wx), 0)
    allow = residual_allowance(amp * amp, c1, m, ek, _U)
    rho = float(np.sqrt(np.sum(np.maximum(qx, 0.0) + allow))) * (1.0 + 4 * q * _U)
    wnorm = 1.01 * float(np.linalg.norm(wx, 2))
    return cm, rho, wnorm


def _exact_sd_at_training(model, rows: np.ndarray) -> np.ndarray:
    """The exact posterior std at training inputs ``rows``, per learned component, ``(R, k)``.

    ``sigma^2(x_i) = s^2 (1 - s^2 [(K + s^2 I)^-1]_ii)`` from the model's factor, by one
    triangular solve in SciPy: the exact model's batched ``predict`` (a compiled, vmapped
    triangular solve), called from two Monte Carlo threads at once under a one-thread BLAS
    limit, never returned (both threads waited for it).
    """
    q = model.x_train_.shape[0]
    e = np.zeros((q, len(rows)))
    e[rows, np.arange(len(rows))] = 1.0
    out = []
    for j in range(len(model.components_)):
        s2 = float(model.noise_[j]) ** 2
        v = scipy.linalg.solve_triangular(np.asarray(model.chol_[j]), e, lower=True)
        out.append(np.sqrt(np.maximum(s2 * (1.0 - s2 * np.sum(v * v, 0)), 0.0)))
    return np.stack(out, 1)


def inducing_inputs(model, j, xs, n_inducing, pivot_tol, floor_std):
    """Component ``j``'s kernel, its inducing inputs and the Cholesky factor of ``K_ZZ``.

    The inputs are the pivots of :func:`pivoted_cholesky` over the standardised rows ``xs``
    (at most ``n_inducing``; stopping at ``pivot_tol amp^2`` or, after the first, once the
    largest residual prior std is below ``floor_std``), as FastGP and SparseGP choose them.

    Returns
    -------
    kfn : callable
        ``kfn(x1, x2, pad=(False, False))``: the component's kernel matrix of standardised
        inputs (a numpy array; ``pad`` as :func:`kernel_rows`).
    z : array of shape (M, n)
    kzz : array of shape (M, M)
    lj : array of shape (M, M)
        Lower Cholesky factor of ``K_ZZ + eps I``.
    eps : float
        0, or the model's jitter times ``amp^2`` where ``K_ZZ`` alone did not factor.
    idx : array of shape (M,)
        The rows of ``xs`` chosen.
    """
    amp = float(model.amplitude_[j])
    ls_j = np.asarray(model.lengthscale_std_[j])

    def kfn(x1, x2, pad=(False, False)):
        return kernel_rows(amp, ls_j, x1, x2, model.kernel, pad)

    idx, _ = pivoted_cholesky(kfn, xs, amp * amp, n_inducing, pivot_tol, floor_std**2)
    z = xs[idx]
    kzz = kfn(z, z, pad=(True, True))  # z's size varies from data set to data set
    # The pivoted Cholesky kept pivots >= pivot_tol amp^2, so K_ZZ is positive definite as it
    # usually is; the jitter is the fallback (any factor keeps the band proven: it only
    # makes the projection weights c, whose quadratic q is evaluated as it is)
    eps = 0.0
    try:
        lj = np.linalg.cholesky(kzz)
    except np.linalg.LinAlgError:
        eps = model.jitter * amp * amp
        lj = np.linalg.cholesky(kzz + eps * np.eye(len(z)))
    return kfn, z, kzz, lj, eps, idx


def _component(model, j, xs, n_inducing, pivot_tol, floor):
    """Component ``j``'s inducing inputs and the arrays of its band (``InducingBand._pack``)."""
    q = xs.shape[0]
    amp, s2 = float(model.amplitude_[j]), float(model.noise_[j]) ** 2
    ls = np.asarray(model.lengthscale_std_[j])
    _, z, kzz, lj, _, idx = inducing_inputs(model, j, xs, n_inducing, pivot_tol, floor)
    m = len(z)
    li = scipy.linalg.solve_triangular(lj, np.eye(m), lower=True)  # Lj^-1
    # Cov(f_Z | data) = s^2 (E_Z^T E_Z - s^2 E_Z^T (K + s^2 I)^-1 E_Z) (Z is among the
    # training inputs, E_Z their unit columns; E_Z^T E_Z = I for distinct rows, which
    # pivoted_cholesky chooses, and exact for any): a difference at the scale s^2, not
    # amp^2; its rounding (the triangular solve's forward error, cond(L) <= sqrt(Q amp^2 +
    # s^2) / s) is added on the diagonal. Not in it: the model's factor is the exact factor
    # of a matrix within rounding of K + s^2 I, an error of S up to about cond(K + s^2 I) u
    # s^2 (measured 2.5e-8 s^2 at cond 1e9, 15 times this allowance; far inside the band's
    # other allowances there)
    ez = np.zeros((q, m))
    ez[idx, np.arange(m)] = 1.0
    v = scipy.linalg.solve_triangular(np.asarray(model.chol_[j]), ez, lower=True)
    cov = s2 * (ez.T @ ez - s2 * (v.T @ v))
    cond = np.sqrt(q * amp * amp + s2) / np.sqrt(s2)
    g = _psd_root(cov + 4 * (q + m) * _U * cond * s2 * np.eye(m))
    ek = kernel_error_coefficient(model.kernel, np.max(np.abs(z), 0) / ls)
    cm, rho, wnorm = _cross_terms(model, j, xs, z, idx, li, kzz, v, ek)
    b, rho_b, rho_err, e_norm = _mean_terms(
        model.kernel, amp, ls, xs, np.asarray(model.alpha_[j]), z, idx, lj
    )
    return z, {
        "li": li, "kzz": kzz, "g": g, "cm": cm, "b": b, "rho_b": rho_b, "err": e_norm,
        "ek": ek, "gnorm": np.linalg.norm(g), "bnorm": np.sum(np.abs(b)),
        "rho_err": rho_err, "rho": rho, "wnorm": wnorm, "cnorm": np.linalg.norm(cm),
    }  # fmt: skip


class InducingBand(Predictor):
    """A band evaluated from ``M`` inducing inputs per component (FastGP, SparseGP).

    With ``k = k_Z(x)``, ``c = Lj^-T Lj^-1 k``, ``q = amp^2 - 2 c.k + c.(K_ZZ c)`` and
    ``p = |G c|``: mean ``mu + b.k + c.rho_b``; std ``p + sqrt(q + allowance)`` plus the
    mean-error term ``(E sqrt(q + allowance) + mean rounding) / min_beta`` for a proven band
    (``proven``), ``sqrt(q + allowance + p^2)`` for SparseGP's DTC band
    (:func:`~safestab.learning._posterior.band_component`).

    Subclasses set ``model`` (a fitted :class:`GaussianProcessModel`: kernel, scaling,
    hyperparameters), ``min_beta``, ``n_states``, ``components_`` and call :meth:`_pack`.
    """

    model: GaussianProcessModel
    min_beta: float = 1.0
    n_states: int
    components_: Any
    #: FastGP's proven band, or SparseGP's DTC band.
    proven: bool = True
    #: Unit roundoff of the precision the band's evaluation is bounded for (:meth:`for_precision`).
    unit: float = _U

    def __init_subclass__(cls, **kwargs: Any) -> None:
        # a fitted cache is data: its arrays are the pytree's leaves (the closed loop takes
        # them as arguments); kernel, dimensions, sizes and the band's numbers are static
        super().__init_subclass__(**kwargs)
        register_model(cls, InducingBand._leaves, InducingBand._static)

    def _leaves(self) -> dict[str, Any]:
        if not hasattr(self, "_params"):
            return {}
        return {"_params": self._params, "_unpadded": self._unpadded, "_mu": self._mu}

    def _static(self) -> tuple:
        return (
            type(self), self.model.kernel, self.n_states, tuple(self.components_),
            float(self.min_beta), float(self.unit), self._m,
            tuple(int(m) for m in self.n_inducing_),
        )  # fmt: skip

    def _pack(self, model, zs, comps) -> None:
        """Pad the per-component arrays to a common ``M`` and stack them into ``_params``.

        ``comps``: per component, a dict of ``li``, ``kzz``, ``g``, ``cm`` (M, M), ``b``,
        ``rho_b`` (M,) and the scalars ``err``, ``ek``, ``gnorm``, ``bnorm``, ``rho_err``,
        ``rho``, ``wnorm``, ``cnorm``.
        """
        m_max = max(len(z) for z in zs)
        n = zs[0].shape[1]

        def pad(a, shape):
            return np.pad(a, [(0, s - d) for s, d in zip(shape, a.shape, strict=True)])

        # padded rows get zero kernel values (masked), zero weights and zero maps
        self._params = {
            "offset": device_array(model.x_offset_),
            "scale": device_array(model.x_scale_),
            "amp": device_array(model.amplitude_),
            "ls": device_array(model.lengthscale_std_),
            "z": device_array(np.stack([pad(z, (m_max, n)) for z in zs])),
            "mask": device_array(np.stack([np.arange(m_max) < len(z) for z in zs])),
            "mu": device_array(model.mean_, dtype=float),
        }
        for key in ("li", "kzz", "g", "cm"):
            self._params[key] = device_array(np.stack([pad(c[key], (m_max, m_max)) for c in comps]))
        for key in ("b", "rho_b"):
            self._params[key] = device_array(np.stack([pad(c[key], (m_max,)) for c in comps]))
        for key in ("err", "ek", "gnorm", "bnorm", "rho_err", "rho", "wnorm", "cnorm"):
            self._params[key] = device_array(np.array([float(c[key]) for c in comps]))
        self._mu = device_array(model.mean_, dtype=float)
        self._m = m_max
        self.n_inducing_ = np.array([len(z) for z in zs])
        self.inducing_ = np.asarray(self._params["z"]) * model.x_scale_ + model.x_offset_

    def for_precision(self, precision: str) -> InducingBand:
        """The cache with a band that holds when the step is evaluated in ``precision``.

        ``"double"`` returns ``self``. ``"float"`` returns an :meth:`unpadded` copy whose
        allowances (the rounding of ``q``, of ``|G c|``, of the mean and of the stored arrays)
        are bounded for float's unit roundoff ``2^-24`` instead of float64's. A float
        evaluation cannot resolve a posterior variance that is far below the prior one (``q``
        cancels digits that float does not have): this copy then reports the width float can
        vouch for, so the float step's GP-robust terms stay on the safe side of the exact ones
        (docs/export.md, "Float that stays safe"). For a :class:`~safestab.learning.SparseGP`,
        whose DTC band is not a proven bound, the same allowance keeps the float band no
        narrower than the double one.

        Raises
        ------
        RuntimeError
            Before a :class:`~safestab.learning.SparseGP` is fitted.
        """
        self._require_fit()
        if precision == "double":
            return self
        if precision != "float":
            raise ParameterError(f"precision must be 'double' or 'float', got {precision!r}")
        out = self.unpadded()
        out.unit = _U_FLOAT
        return out

    def unpadded(self) -> InducingBand:
        """A copy whose :meth:`mean_std` evaluates each component at its own size.

        The same values (to rounding) with fewer operations where components use fewer
        inducing inputs than the largest (no padded rows, no masks): what an exported step
        for a microcontroller wants (``safestab export --target``). Batched evaluation
        (:meth:`predict`) is unchanged.
        """
        self._require_fit()
        out = copy.copy(self)
        p, comps = self._params, []
        for j, m in enumerate(self.n_inducing_):
            comp = {key: p[key][j] for key in BAND_KEYS}
            comp.update(z=p["z"][j, :m], mask=None, b=p["b"][j, :m], rho_b=p["rho_b"][j, :m])
            for key in ("li", "kzz", "g", "cm"):
                comp[key] = p[key][j, :m, :m]
            comps.append(comp)
        out._unpadded = comps
        return out

    _unpadded: list | None = None

    def _require_fit(self) -> None:
        """Raise a RuntimeError naming the class before its arrays exist (SparseGP.fit)."""
        check_fitted(self, "_params")

    def _mean_std_parts(self, x: jax.Array):
        kind = self.model.kernel
        if self._unpadded is not None:
            return band_point_unpadded(
                self._params, self._unpadded, x, kind, self.unit, self.proven
            )
        return band_point(self._params, x, kind, self.unit, self.proven)

    def _parts_batch(self, x: np.ndarray):
        # the inducing axis padded to its bucket (masked rows add exact zeros): one program
        # per bucket, not per number of inducing inputs
        p = pad_inducing(self._params, size_bucket(self._params["z"].shape[1]))
        return band_batch(p, device_array(x), self.model.kernel, self.unit, self.proven)

    def arrays(self) -> dict[str, np.ndarray]:
        """Copies of the cache's arrays, for evaluating the same band elsewhere (batched).

        Keys: ``offset``, ``scale`` (n,): inputs are standardised as ``(x - offset) / scale``;
        per learned component (``k`` rows, padded to a common ``M``): ``amp`` (k,), ``ls``
        (k, n) lengthscales of the standardised inputs, ``z`` (k, M, n) inducing inputs,
        ``mask`` (k, M), ``li`` (k, M, M) ``Lj^-1``, ``kzz`` (k, M, M) ``K_ZZ``, ``g`` (k, M,
        M) ``G``, ``b`` and ``rho_b`` (k, M) the mean's weights and residual, and (k,) each:
        ``err`` (``E``), ``ek`` (the kernel values' rounding coefficient), ``gnorm``
        (``||G||_F``), ``bnorm`` (``|b|_1``), ``rho_err`` (a bound on ``rho_b``'s error),
        ``mu`` (the prior mean). The band is :func:`~safestab.learning._posterior.band_point`'s
        (module docstring); batched by :class:`~safestab.learning.InducingCache`.
        """
        self._require_fit()
        return {key: np.array(value) for key, value in self._params.items()}

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and guaranteed std at one state of shape (n,); jittable, O(M^2).

        The std is ``|G c| + r + (E r + mean rounding) / min_beta`` (module docstring): for
        every ``beta >= min_beta``, ``m~ +- beta std`` contains the exact ``m +- beta sigma``.
        Called on values (not inside a transformation), it runs as one compiled program with
        the cache as its argument, shared by every cache of the same structure and shapes.
        """
        self._require_fit()
        if is_concrete(x, *jax.tree_util.tree_leaves(self)):
            return _mean_std_program(self, x)
        return self._mean_std_traced(x)

    def _mean_std_traced(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        mean_c, sd_c, merr = self._mean_std_parts(x)
        comps = jnp.asarray(self.components_)
        mean = jnp.zeros(self.n_states).at[comps].set(mean_c + self._mu)
        std = jnp.zeros(self.n_states).at[comps].set(sd_c + merr / self.min_beta)
        return mean, std

    # predict(x, return_std=False): Predictor's, over these rows (compiled once per M)
    _legacy_predict = True

    def _check_fitted(self) -> None:
        self._require_fit()

    def _predict_rows(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (the guaranteed one for FastGP) at checked states (N, n)."""
        mean_c, sd_c, merr = (np.asarray(a) for a in self._parts_batch(x))
        comps = list(self.components_)
        mean = np.zeros(x.shape)
        std = np.zeros(x.shape)
        mean[:, comps] = mean_c + np.asarray(self.model.mean_)
        std[:, comps] = sd_c + merr / self.min_beta
        return mean, std

    def rounding_scales(self, x: Any) -> tuple[np.ndarray, np.ndarray]:
        """Magnitudes relative to which the mean and the std at ``x`` are rounded.

        A first-order running-error analysis of the cache's evaluation
        (``learning._posterior.band_magnitudes``): the kernel values and the products with
        them are rounded relative to the products of their absolute values (the projection
        weights ``c`` through ``|Lj^-T| |Lj^-1| |k|``, which an ill-conditioned ``K_ZZ``
        enlarges); ``q`` is a difference of terms of size ``amp^2 (1 + |c|_1)^2``. Two float64
        evaluations of :meth:`mean_std` (XLA's and the exported C, say) agree to a small
        multiple of the unit roundoff times these, not times the mean and the std. Where the
        posterior variance is far below the prior one (the stress preset's drag, Q = 2000:
        std 5e-5 from ``amp^2 = 1143``), the std's scale is far above the std: both
        evaluations carry that rounding, neither is more accurate; the cache's own allowance
        (a proven bound, in the band) is of the same order. A
        :class:`~safestab.learning.SparseGP` has no proof: these scales then say only how far
        two evaluations may differ.

        Parameters
        ----------
        x : array of shape (N, n)

        Returns
        -------
        (mean_scale, std_scale) : arrays of shape (N, n)
            Zero for components that are not learned.

        Raises
        ------
        RuntimeError
            Before a :class:`~safestab.learning.SparseGP` is fitted.
        """
        self._require_fit()
        x = np.asarray(x, float)
        if x.ndim != 2 or x.shape[1] != self.n_states:
            raise DimensionError(f"x must have shape (N, {self.n_states}), got {x.shape}")
        check_finite("x", x)
        p = pad_inducing(self._params, size_bucket(self._params["z"].shape[1]))
        parts = band_magnitudes_batch(p, device_array(x), self.model.kernel, self.unit, self.proven)
        mean_mag, sd_mag, merr_mag = (np.asarray(a) for a in parts)
        comps = list(self.components_)
        mean_scale, std_scale = np.zeros(x.shape), np.zeros(x.shape)
        mean_scale[:, comps] = mean_mag + np.abs(np.asarray(self.model.mean_))
        std_scale[:, comps] = sd_mag + merr_mag / self.min_beta
        return mean_scale, std_scale


@jax.jit
def _mean_std_program(band: InducingBand, x: Any) -> tuple[jax.Array, jax.Array]:
    """:meth:`InducingBand.mean_std` of a cache passed as data: one program per structure."""
    return band._mean_std_traced(x)


class FastGP(InducingBand):
    """Inducing-point cache of a fitted GP whose band contains the exact GP's band.

    Parameters
    ----------
    model : GaussianProcessModel
        A fitted model.
    n_inducing : int
        ``M``, inducing inputs per component at most (default 32).
    min_beta : float
        The band ``m~ +- beta sigma~`` contains the exact band for every ``beta >= min_beta``
        (default 1; the mean-error term of ``sigma~`` scales as ``1 / min_beta``).
    pivot_tol : float
        Stop adding inducing inputs once the largest residual prior variance is below
        ``pivot_tol * amplitude^2`` (default 1e-14). The band's rounding allowance does not
        grow with ``cond(K_ZZ)`` (module docstring), so the pivoted Cholesky may resolve the
        prior far below the amplitude: on the stress preset's drag (exact std 5e-5 of an
        amplitude 34) 1e-10 stopped at 8 inducing inputs and a band 3.2 times the exact std,
        1e-14 at 12 and 1.27 times. Any value >= 0 keeps the band proven: 0 adds inputs until
        the prior is resolved to rounding (or the cap), never a training row twice.
    std_tol : float
        Also stop (after the first inducing input) once the largest residual prior std at
        the training inputs is below ``std_tol`` times the exact posterior std there (its
        median over a sample of 128 training inputs; default 0.1; 0 turns this off). The
        projection then resolves the prior at the data to a tenth of what the data leave
        unknown, and the band's excess over the exact one near the data is of that order.
        Components whose GP learned next to nothing (amplitude near or below the noise, such
        as the exact kinematics of the ACC) stop after a few inputs. Where neither rule
        stops a component before the cap (``n_inducing``, or Q), its band there is more than
        ``STD_RATIO_WARN`` (1.5) times the exact std (median over the sample), and its cache
        with one inducing input already exceeds the exact std by at most ``EXCESS_WARN``
        (0.1) noise stds at every sampled training input, the component keeps that one
        input: its prior cannot be resolved at the data (a lengthscale far below their
        spacing), more inputs leave the band about as wide, and an excess below a tenth of
        the noise changes no decision (measured on the Monte Carlo stress data sets' second
        kinematic component: 1.98 times the exact std with 1 input and 1.95 with 32, an
        excess of 0.02 noise stds; a query cost the 32 inputs' four 32 x 32 products).
        ``std_tol = 0`` turns this rule off too.
    warn : bool
        Issue the :class:`InducingPointsWarning` (default). False only records its messages
        in ``width_warnings_``: for callers in threads, where ``warnings.catch_warnings`` is
        not safe (it swaps process-wide state).

    Attributes
    ----------
    inducing_ : array of shape (k, M, n)
        Inducing inputs per learned component (in the units of x); padded rows repeat zeros.
    n_inducing_ : array of shape (k,)
        Inducing inputs actually used per component.
    mean_error_norm_ : array of shape (k,)
        ``E``: the RKHS norm bounding ``|m - m~| <= E r(x)`` (rounding allowance included).
    std_over_exact_ : array of shape (k,)
        The cache's std over the exact std at a sample of training inputs (median).
    inflation_at_training_ : array of shape (k,)
        Fraction of training inputs where ``sigma~ > INFLATION_WARN * noise_``.
    width_warnings_ : tuple of str
        The messages of the :class:`InducingPointsWarning` (empty when the band is tight).

    Warns
    -----
    InducingPointsWarning
        When ``std_over_exact_`` exceeds ``STD_RATIO_WARN`` (1.5) for some component and the
        excess (median) is more than ``EXCESS_WARN`` (0.1) noise stds.

    Notes
    -----
    Each query costs ``M`` kernel evaluations and four ``M x M`` matrix-vector products per
    component (``M`` the largest number of inducing inputs of a component), independent of
    ``Q``. Building it costs ``O(Q^2 M)`` for ``Cov(f_Z | data)`` and ``O(Q^2)`` extended
    precision kernel values for ``E``. docs/learning.md proves the two inequalities.
    """

    def __init__(
        self,
        model: GaussianProcessModel,
        n_inducing: int = 32,
        *,
        min_beta: float = 1.0,
        pivot_tol: float = 1e-14,
        std_tol: float = 0.1,
        warn: bool = True,
    ) -> None:
        check_fitted(model)
        if isinstance(n_inducing, bool) or not isinstance(n_inducing, int | np.integer):
            raise ParameterError(f"n_inducing must be an integer >= 1, got {n_inducing!r}")
        if int(n_inducing) < 1:
            raise ParameterError(f"n_inducing must be an integer >= 1, got {n_inducing!r}")
        check_scalar_range("min_beta", min_beta, lower=0.0, strict_lower=True)
        check_scalar_range("pivot_tol", pivot_tol, lower=0.0)
        check_scalar_range("std_tol", std_tol, lower=0.0)
        self.model = model
        self.min_beta = float(min_beta)
        self.n_states = model.n_states_
        self.components_ = model.components_
        comps = list(model.components_)
        with fit_threads():  # one BLAS thread (learning/_threads.py)
            xs = (model.x_train_ - model.x_offset_) / model.x_scale_
            q = xs.shape[0]
            sample = np.random.default_rng(0).choice(q, min(q, _STD_SAMPLE), replace=False)
            exact_sd = _exact_sd_at_training(model, sample)
            zs, packed = [], []
            for j in range(len(comps)):
                floor = std_tol * float(np.median(exact_sd[:, j]))
                z, comp = _component(model, j, xs, int(n_inducing), pivot_tol, floor)
                zs.append(z)
                packed.append(comp)
            cap = min(int(n_inducing), q)
            capped = [j for j, z in enumerate(zs) if cap > 1 and len(z) == cap]
            if capped and std_tol > 0:
                # where the cap stopped the pivoted Cholesky, a component keeps one input if
                # that band is as tight as the capped one (within 1 %), or if the capped band
                # is wider than STD_RATIO_WARN times the exact one and the one-input band is
                # within EXCESS_WARN noise stds of the exact band at every sampled input: more
                # inputs then change no decision and cost every query M^2 (the Monte Carlo
                # data sets' kinematic components, a lengthscale the data cannot resolve)
                self._pack(model, zs, packed)
                ratio = np.median(self._sd_at(model.x_train_[sample]) / exact_sd, axis=0)
                one = {j: _component(model, j, xs, 1, pivot_tol, 0.0) for j in capped}
                self._pack(
                    model,
                    [one[j][0] if j in one else z for j, z in enumerate(zs)],
                    [one[j][1] if j in one else c for j, c in enumerate(packed)],
                )
                sd1 = self._sd_at(model.x_train_[sample])
                ratio1 = np.median(sd1 / exact_sd, axis=0)
                excess1 = np.max(sd1 - exact_sd, axis=0) / model.noise_
                for j in one:
                    as_tight = ratio1[j] <= 1.01 * ratio[j]
                    no_decision = ratio[j] > STD_RATIO_WARN and excess1[j] <= EXCESS_WARN
                    if as_tight or no_decision:
                        zs[j], packed[j] = one[j]
            self._pack(model, zs, packed)
            self.mean_error_norm_ = np.array([c["err"] for c in packed])
            sd = self._sd_at(model.x_train_)
            self.inflation_at_training_ = np.mean(sd / model.noise_ > INFLATION_WARN, axis=0)
            self.std_over_exact_ = np.median(sd[sample] / exact_sd, axis=0)
            excess = np.median(sd[sample] - exact_sd, axis=0) / model.noise_
        notes = []
        for j, (comp, ratio) in enumerate(zip(comps, self.std_over_exact_, strict=True)):
            if ratio <= STD_RATIO_WARN:
                continue
            head = (
                f"FastGP with n_inducing={n_inducing}: for component {comp}, the cache's std "
                f"at the training inputs is {ratio:.3g} times the exact std (median over "
                f"{len(sample)} of them), used {self.n_inducing_[j]} inducing inputs"
            )
            if excess[j] > EXCESS_WARN:
                notes.append(f"{head}: the band is needlessly wide; increase n_inducing or "
                             "lower pivot_tol")  # fmt: skip
            else:
                notes.append(
                    f"{head}, an excess of {excess[j]:.2g} noise stds: the GP learned next to "
                    f"nothing here (amplitude {model.amplitude_[j]:.3g}, noise "
                    f"{model.noise_[j]:.3g}) and the bound on the mean's error "
                    f"(E = {self.mean_error_norm_[j]:.3g} times the residual) sets the width; "
                    "more inducing inputs do not narrow it"
                )
        self.width_warnings_ = tuple(notes)
        for note in notes if warn else ():
            warnings.warn(note, InducingPointsWarning, stacklevel=2)

    def _sd_at(self, x: np.ndarray) -> np.ndarray:
        """The packed cache's std at states ``x`` (N, n), per learned component (N, k)."""
        _, sd_c, merr = (np.asarray(a) for a in self._parts_batch(x))
        return sd_c + merr / self.min_beta

    def mean_error_bound(self, x: Any) -> np.ndarray:
        """Bound ``E r(x)`` on ``|m~ - m|`` at states ``x`` of shape (N, n); shape (N, k)."""
        x = np.asarray(x, float)
        if x.ndim != 2 or x.shape[1] != self.n_states:
            raise DimensionError(f"x must have shape (N, {self.n_states}), got {x.shape}")
        check_finite("x", x)
        return np.asarray(self._parts_batch(x)[2])

    def coverage_of_exact_band(self, x: Any, beta: Any) -> np.ndarray:
        """Fraction of states where the cache's band contains the exact band, per component.

        Parameters
        ----------
        x : array of shape (N, n)
        beta : float or array of shape (n,)

        Returns
        -------
        array of shape (k,)
            1 wherever ``beta >= min_beta`` (up to rounding of the exact predictor).
        """
        x = np.asarray(x, float)
        if x.ndim != 2 or x.shape[1] != self.n_states:
            raise DimensionError(f"x must have shape (N, {self.n_states}), got {x.shape}")
        check_finite("x", x)
        check_scalar_range("beta", beta, lower=0.0)
        comps = list(self.components_)
        b = np.broadcast_to(np.asarray(beta, float), (self.n_states,))[comps]
        m_ex, s_ex = (a[:, comps] for a in self.model.predict(x, return_std=True))
        m_fa, s_fa = (a[:, comps] for a in self.predict(x, return_std=True))
        lo_ok = m_fa - b * s_fa <= m_ex - b * s_ex
        hi_ok = m_fa + b * s_fa >= m_ex + b * s_ex
        return (lo_ok & hi_ok).mean(0)
