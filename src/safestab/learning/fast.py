"""A prediction cache for the control loop, cost O(M^2) per query, with a proven band.

From a fitted :class:`~safestab.learning.GaussianProcessModel`, pick ``M`` inducing inputs
``Z`` among the training inputs (greedy pivoted Cholesky of the prior kernel matrix). With
``Kj = K_ZZ + eps I`` (``eps = jitter amplitude^2``), ``Lj Lj^T = Kj``, ``a(x) = Lj^-1 k_Z(x)``,
``Phi = Lj^-1 K_ZX``, ``P = I + eps (Lj^T Lj)^-1``, ``B = P Phi`` and the exact model's
``K + s^2 I = L L^T`` (``s = noise_``, the effective noise), the cache returns

    m~(x)     = mu + (B alpha) . a(x)
    r(x)^2    = k(x, x) - |a(x)|^2                     (prior residual given f_Z, >= 0)
    v~(x)     = r(x)^2 + a^T (I - H) a + 2 |A a| rho r(x)
    sigma~(x) = sqrt(v~(x)) + E r(x) / min_beta

with ``H = B (K + s^2 I)^-1 B^T``, ``A = (K + s^2 I)^-1 B^T``, ``rho = ||r(X)||_2`` over the
training inputs and ``E = min(sum_i |alpha_i| r(x_i), ||m - h||_k)``. docs/learning.md proves
``v~(x) >= sigma^2(x)`` (the exact posterior variance, from its variational form
``sigma^2(x) = min_c ||k_x - sum_i c_i k_{x_i}||^2 + s^2 |c|^2``) and
``|m~(x) - m(x)| <= E r(x)`` at every ``x``. Hence for every ``beta >= min_beta`` the cache's
band ``m~ +- beta sigma~`` contains the exact band ``m +- beta sigma``, far from the data too,
with no held-out states. The first two terms of ``v~`` are the projected posterior of the
previous cache; the third is the cross term it lacked.
"""

from __future__ import annotations

import copy
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._validation import check_finite, check_real, check_scalar_range
from .._values import register_model
from ..errors import DimensionError, InducingPointsWarning, ParameterError
from ._checks import check_fitted
from ._posterior import (
    BAND_KEYS,
    band_batch,
    band_magnitudes_batch,
    band_point,
    band_point_unpadded,
    kernel_matrix,
)
from .gp import GaussianProcessModel

__all__ = ["FastGP", "INFLATION_WARN"]

#: :class:`InducingPointsWarning` when, at more than 1 % of the training inputs, the cache's
#: std exceeds this many times the noise std (an upper bound of the exact posterior std at
#: a training input), i.e. the cache's band is at least this much wider than the exact one.
INFLATION_WARN = 3.0
_U = np.finfo(float).eps / 2  # unit roundoff of float64


def pivoted_cholesky(kfn, xs: np.ndarray, amp2: float, m: int, tol: float, floor: float = 0.0):
    """Greedy choice of ``m`` rows maximising the residual prior variance (pivoted Cholesky).

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
    return np.array(chosen), diag


def _round(m: int, amp: float, cond: float) -> float:
    """Rounding allowance on ``r^2 = amp^2 - |a|^2``: ``2 (M + 2 + cond(Lj)) u amp^2``.

    ``a = Lj^-1 k`` is formed with a precomputed inverse, whose relative error grows with
    ``cond(Lj)``; ``|a| <= amp``, so ``| |a~|^2 - |a|^2 | <= 2 amp |a~ - a|`` is bounded by this.
    """
    return float(2 * (m + 2 + cond) * _U * amp * amp)


def _psd_root(mat: np.ndarray) -> np.ndarray:
    """``G`` with ``G^T G = mat`` after clipping negative eigenvalues to 0 (never smaller)."""
    evals, evecs = np.linalg.eigh(0.5 * (mat + mat.T))
    return (evecs * np.sqrt(np.maximum(evals, 0.0))).T


def _rkhs_gap(kfn, xs, alpha, z, b, kzz, chunk: int = 1024) -> tuple[float, float]:
    """``||m - h||_k^2`` and a bound on its rounding error.

    ``m = sum_i alpha_i k(x_i, .)``, ``h = sum_j b_j k(z_j, .)``:
    ``||m - h||^2 = alpha^T K alpha - 2 b^T K_ZX alpha + b^T K_ZZ b``. The rounding bound uses
    the standard dot-product error ``n u sum |terms|`` (kernels here are positive), doubled.
    """
    q = xs.shape[0]
    ka = np.zeros(q)
    ka_abs = np.zeros(q)
    for s in range(0, q, chunk):  # K alpha by blocks: no Q x Q matrix in memory
        kb = np.asarray(kfn(xs[s : s + chunk], xs))
        ka[s : s + chunk] = kb @ alpha
        ka_abs[s : s + chunk] = kb @ np.abs(alpha)
    kzx = np.asarray(kfn(z, xs))
    m_z = kzx @ alpha
    a_term = alpha @ ka
    b_term = b @ m_z
    c_term = b @ kzz @ b
    m = z.shape[0]
    err = (
        2
        * _U
        * (
            (q + 2) * (np.abs(alpha) @ ka_abs)
            + 2 * (q + m + 2) * (np.abs(b) @ (kzx @ np.abs(alpha)))
            + (m + 2) * (np.abs(b) @ kzz @ np.abs(b))
        )
    )
    return float(a_term - 2 * b_term + c_term), float(err)


def inducing_inputs(model, j, xs, n_inducing, pivot_tol, noise_tol):
    """Component ``j``'s kernel, its inducing inputs and the Cholesky factor of ``K_ZZ``.

    The inputs are the pivots of :func:`pivoted_cholesky` over the standardised rows ``xs``
    (at most ``n_inducing``; stopping at ``pivot_tol amp^2`` or, for the residual, at
    ``(noise_tol noise)^2``), as FastGP and SparseGP choose them.

    Returns
    -------
    kfn : callable
        ``kfn(x1, x2)``: the component's kernel matrix of standardised inputs.
    z : array of shape (M, n)
    kzz : array of shape (M, M)
    lj : array of shape (M, M)
        Lower Cholesky factor of ``K_ZZ + eps I``.
    eps : float
        0, or the model's jitter times ``amp^2`` where ``K_ZZ`` alone did not factor.
    """
    amp = float(model.amplitude_[j])
    ls_j = jnp.asarray(model.lengthscale_std_[j])

    def kfn(x1, x2):
        return kernel_matrix(amp, ls_j, jnp.asarray(x1), jnp.asarray(x2), kind=model.kernel)

    floor = (noise_tol * float(model.noise_[j])) ** 2
    idx, _ = pivoted_cholesky(kfn, xs, amp * amp, n_inducing, pivot_tol, floor)
    z = xs[idx]
    kzz = np.asarray(kfn(z, z))
    # The pivoted Cholesky kept pivots >= pivot_tol amp^2, so K_ZZ is positive definite as it
    # is: eps = 0 resolves residuals below the model's jitter (with eps = 1e-10 amp^2 the
    # cache could not see below r ~ 1e-5 amp, 100 times the exact std of the ACC drag at
    # Q = 2000); the jitter is the fallback.
    eps = 0.0
    try:
        lj = np.linalg.cholesky(kzz)
    except np.linalg.LinAlgError:
        eps = model.jitter * amp * amp
        lj = np.linalg.cholesky(kzz + eps * np.eye(len(z)))
    return kfn, z, kzz, lj, eps


class InducingBand:
    """A band evaluated from ``M`` inducing inputs per component (FastGP, SparseGP).

    With ``[a; G a; C a] = maps k_Z(x)`` and ``r^2 = amp^2 - |a|^2 + round``: mean
    ``mu + k . wk``, std ``sqrt(r^2 + |G a|^2 + 2 |C a| rho r) + err r / min_beta``
    (:meth:`arrays`).

    Subclasses set ``model`` (a fitted :class:`GaussianProcessModel`: kernel, scaling,
    hyperparameters), ``min_beta``, ``n_states``, ``components_`` and call :meth:`_pack`.
    """

    model: GaussianProcessModel
    min_beta: float = 1.0
    n_states: int
    components_: Any

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
            float(self.min_beta), float(self.work_unit), self._m,
            tuple(int(m) for m in self.n_inducing_),
        )  # fmt: skip

    def _pack(self, model, zs, maps_, ws, errs, rhos, rnds) -> None:
        """Pad the per-component arrays to a common ``M`` and stack them into ``_params``."""
        m_max = max(len(z) for z in zs)
        n = zs[0].shape[1]

        def pad(a, shape):
            return np.pad(a, [(0, s - d) for s, d in zip(shape, a.shape, strict=True)])

        # Pad to a common M (padded rows get zero kernel values and zero weights), then stack
        # the three maps of a query's kernel vector k so that a query is one small product.
        maps = [np.concatenate([pad(p_, (m_max, m_max)) for p_ in trio], 0) for trio in maps_]
        self._z = jnp.asarray(np.stack([pad(z, (m_max, n)) for z in zs]))
        self._maps = jnp.asarray(np.stack(maps))
        self._wk = jnp.asarray(np.stack([pad(w, (m_max,)) for w in ws]))
        self._mask = jnp.asarray(np.stack([np.arange(m_max) < len(z) for z in zs]))
        self._err = jnp.asarray(np.array(errs))
        self._rho = jnp.asarray(np.array(rhos))
        self._round = jnp.asarray(rnds)
        self._params = {
            "offset": jnp.asarray(model.x_offset_),
            "scale": jnp.asarray(model.x_scale_),
            "amp": jnp.asarray(model.amplitude_),
            "ls": jnp.asarray(model.lengthscale_std_),
            "z": self._z,
            "wk": self._wk,
            "maps": self._maps,
            "mask": self._mask,
            "err": self._err,
            "rho": self._rho,
            "round": self._round,
        }
        self._mu = jnp.asarray(model.mean_, dtype=float)
        self._m = m_max
        self.n_inducing_ = np.array([len(z) for z in zs])
        self.inducing_ = np.asarray(self._z) * model.x_scale_ + model.x_offset_

    #: Rounding allowance per query for a lower working precision (``for_precision``).
    work_unit = 0.0

    def for_precision(self, precision: str) -> InducingBand:
        """The cache with a band that holds when the step is evaluated in ``precision``.

        ``"double"`` returns ``self``. ``"float"`` returns an :meth:`unpadded` copy whose band
        adds, per query, ``gamma u`` (``u = 2^-24`` the unit roundoff of float,
        ``gamma = 4 (M + 4)``) times the running magnitudes of the cache's evaluation
        (:meth:`rounding_scales`) to ``r^2``, to the variance and to the mean-error term. A
        float evaluation cannot resolve a posterior variance that is far below the prior one
        (``amp^2 - |a|^2`` cancels digits that float does not have): this copy then reports
        the width float can vouch for instead of a rounding artefact, so the float step's
        GP-robust terms stay on the safe side of the exact ones (docs/export.md, "Float that
        stays safe"). For a :class:`~safestab.learning.SparseGP`, whose DTC band is not a
        proven bound, the same allowance keeps the float band no narrower than the double
        one.

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
        out.work_unit = float(4 * (self._m + 4) * np.finfo(np.float32).eps / 2)
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
        p, mm, comps = self._params, self._m, []
        for j, m in enumerate(self.n_inducing_):
            rows = np.concatenate([np.arange(b * mm, b * mm + m) for b in range(3)])
            comp = {key: p[key][j] for key in BAND_KEYS}
            comp.update(z=p["z"][j, :m], wk=p["wk"][j, :m], mask=None)
            comp["maps"] = p["maps"][j][rows][:, :m]
            comps.append(comp)
        out._unpadded = comps
        return out

    _unpadded: list | None = None

    def _require_fit(self) -> None:
        """Raise a RuntimeError naming the class before its arrays exist (SparseGP.fit)."""
        check_fitted(self, "_params")

    def _mean_std_parts(self, x: jax.Array):
        if self._unpadded is not None:
            return band_point_unpadded(
                self._params, self._unpadded, x, self.model.kernel, self.work_unit
            )
        return band_point(self._params, x, self.model.kernel, self.work_unit)

    def _parts_batch(self, x: np.ndarray):
        return band_batch(self._params, jnp.asarray(x), self.model.kernel, self.work_unit)

    def arrays(self) -> dict[str, np.ndarray]:
        """Copies of the cache's arrays, for evaluating the same band elsewhere (batched).

        Keys: ``offset``, ``scale`` (n,): inputs are standardised as ``(x - offset) / scale``;
        per learned component (``k`` rows, padded to a common ``M``): ``amp`` (k,), ``ls``
        (k, n) lengthscales of the standardised inputs, ``z`` (k, M, n) inducing inputs,
        ``maps`` (k, 3M, M) ``[Lj^-1; G Lj^-1; C Lj^-1]``, ``wk`` (k, M) mean weights,
        ``mask`` (k, M), ``err`` (k,) ``E``, ``rho`` (k,), ``round`` (k,) the rounding
        allowance of ``r^2``. With ``[a; G a; C a] = maps k_Z(x)``, ``r^2 = amp^2 - |a|^2 +
        round``, the cache's mean is ``k . wk + mean_`` and its std ``sqrt(r^2 + |G a|^2 +
        2 |C a| rho r) + err r / min_beta`` (module docstring); batched by
        :class:`~safestab.learning.InducingCache`.
        """
        self._require_fit()
        return {key: np.array(value) for key, value in self._params.items()}

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and guaranteed std at one state of shape (n,); jittable, O(M^2).

        The std is ``sqrt(v_Z) + E r / min_beta`` (module docstring): for every
        ``beta >= min_beta``, ``m~ +- beta std`` contains the exact ``m +- beta sigma``.
        """
        self._require_fit()
        mean_c, sd_c, merr = self._mean_std_parts(x)
        comps = jnp.asarray(self.components_)
        mean = jnp.zeros(self.n_states).at[comps].set(mean_c + self._mu)
        std = jnp.zeros(self.n_states).at[comps].set(sd_c + merr / self.min_beta)
        return mean, std

    def predict(self, x: Any) -> tuple[np.ndarray, np.ndarray]:
        """Mean and guaranteed std at states of shape (N, n), each (N, n); compiled once.

        Raises
        ------
        InputTypeError
            If ``x`` is bool, complex, a string or not an array.
        DimensionError
            If ``x`` is not of shape (N, n).
        NonFiniteError
            If ``x`` contains NaN or inf.
        """
        self._require_fit()
        check_real("x", x)
        x = np.asarray(x, float)
        if x.ndim != 2 or x.shape[1] != self.n_states:
            raise DimensionError(f"x must have shape (N, {self.n_states}), got {x.shape}")
        check_finite("x", x)
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
        (``learning._posterior.band_magnitudes``): the kernel values and the products of the
        cache's maps with them are rounded relative to ``|maps| |k|``; the std is then formed
        from the differences ``r^2 = amp^2 - |a|^2`` and ``v~ = r^2 + ...`` and a square
        root. Two float64
        evaluations of :meth:`mean_std` (XLA's and the exported C, say) agree to a small
        multiple of the unit roundoff times these, not times the mean and the std. Where the
        posterior variance is far below the prior one (the stress preset's drag, Q = 2000:
        std 0.01 from ``amp^2 = 1143``), the std's scale is about 1e5 times the std: both
        evaluations carry that rounding, neither is more accurate. The cache's allowance
        ``round`` (cond(Lj)-based, a proven bound) is far larger still (docs/export.md). A
        :class:`~safestab.learning.SparseGP` has no such allowance (its band is not proven):
        these scales then say only how far two evaluations may differ.

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
        parts = band_magnitudes_batch(
            self._params, jnp.asarray(x), self.model.kernel, self.work_unit
        )
        mean_mag, sd_mag, merr_mag = (np.asarray(a) for a in parts)
        comps = list(self.components_)
        mean_scale, std_scale = np.zeros(x.shape), np.zeros(x.shape)
        mean_scale[:, comps] = mean_mag + np.abs(np.asarray(self.model.mean_))
        std_scale[:, comps] = sd_mag + merr_mag / self.min_beta
        return mean_scale, std_scale


class FastGP(InducingBand):
    """Inducing-point cache of a fitted GP whose band contains the exact GP's band.

    Parameters
    ----------
    model : GaussianProcessModel
        A fitted model.
    n_inducing : int
        ``M``, inducing inputs per component (default 32).
    min_beta : float
        The band ``m~ +- beta sigma~`` contains the exact band for every ``beta >= min_beta``
        (default 1; the mean-error term of ``sigma~`` scales as ``1 / min_beta``).
    pivot_tol : float
        Stop adding inducing inputs once the largest residual prior variance is below
        ``pivot_tol * amplitude^2`` (default 1e-10). Smaller values resolve more but make
        ``K_ZZ`` worse conditioned, and the rounding allowance grows with ``cond(Lj)``; on the
        ACC data 1e-10 gave the narrowest band of 1e-8, 1e-10 and 1e-12.
    noise_tol : float
        Also stop (after the first inducing input) once the largest residual prior variance
        at the training inputs is below ``(noise_tol * noise_)^2`` (default 0.1; 0 turns
        this off): the prior is then resolved at the data to a tenth of the measurement
        noise, and the band's excess over the exact band near the data is of that order.
        This keeps components whose GP learned next to nothing (amplitude near or below the
        noise, such as the exact kinematics of the ACC) from costing ``n_inducing`` points
        each: there M went from 32 and 32 to 1 and 11, the cached step's arithmetic about
        eightfold down, and the band of the second kinematic component (exact std 0.09 of
        the noise) from 1.00 to 2.0 times the exact std (0.03 gives 1.08 with M = 17).
        Components with a signal far above the noise are governed by ``pivot_tol`` as
        before. For any choice of inducing inputs the band is proven to contain the exact
        band.
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
    inflation_at_training_ : array of shape (k,)
        Fraction of training inputs where ``sigma~ > INFLATION_WARN * noise_``.
    width_warnings_ : tuple of str
        The messages of the :class:`InducingPointsWarning` (empty when the band is tight).

    Warns
    -----
    InducingPointsWarning
        When ``inflation_at_training_`` exceeds 1 % for some component: increase
        ``n_inducing``.

    Notes
    -----
    Each query costs ``M`` kernel evaluations and a ``3M x M`` matrix-vector product per
    component (``M`` the largest number of inducing inputs of a component), independent of
    ``Q``. docs/learning.md proves the two inequalities.
    """

    def __init__(
        self,
        model: GaussianProcessModel,
        n_inducing: int = 32,
        *,
        min_beta: float = 1.0,
        pivot_tol: float = 1e-10,
        noise_tol: float = 0.1,
        warn: bool = True,
    ) -> None:
        check_fitted(model)
        if isinstance(n_inducing, bool) or not isinstance(n_inducing, int | np.integer):
            raise ParameterError(f"n_inducing must be an integer >= 1, got {n_inducing!r}")
        if int(n_inducing) < 1:
            raise ParameterError(f"n_inducing must be an integer >= 1, got {n_inducing!r}")
        check_scalar_range("min_beta", min_beta, lower=0.0, strict_lower=True)
        check_scalar_range("pivot_tol", pivot_tol, lower=0.0)
        check_scalar_range("noise_tol", noise_tol, lower=0.0)
        self.model = model
        self.min_beta = float(min_beta)
        self.n_states = model.n_states_
        self.components_ = model.components_
        xs = (model.x_train_ - model.x_offset_) / model.x_scale_
        zs, maps_, ws, errs, rhos, rnds = [], [], [], [], [], []
        for j in range(len(model.components_)):
            amp = float(model.amplitude_[j])
            kfn, z, kzz, lj, eps = inducing_inputs(
                model, j, xs, int(n_inducing), pivot_tol, noise_tol
            )
            m = len(z)
            li = np.linalg.solve(lj, np.eye(m))  # Lj^-1
            kzx = np.asarray(kfn(z, xs))
            # (M, Q): a(x_i) in columns, by a triangular solve (the explicit inverse amplifies
            # rounding by cond(Lj), up to 1e6 for smooth kernels, into the residuals r(x_i))
            phi = scipy.linalg.solve_triangular(lj, kzx, lower=True)
            pmat = np.eye(m) + eps * (li @ li.T)
            bmat = pmat @ phi
            chol = jnp.asarray(model.chol_[j])
            v = np.asarray(jax.scipy.linalg.solve_triangular(chol, bmat.T, lower=True))
            u = np.asarray(jax.scipy.linalg.solve_triangular(chol.T, v, lower=False))  # A
            g = _psd_root(np.eye(m) - v.T @ v)  # G^T G >= I - H (negative parts clipped)
            c = _psd_root(u.T @ u)  # C^T C = A^T A
            alpha = model.alpha_[j]
            rnd = _round(m, amp, float(np.linalg.cond(lj)))
            rnds.append(rnd)
            r_train = np.sqrt(np.maximum(amp * amp - np.sum(phi * phi, 0), 0.0) + rnd)
            rho = float(np.sqrt(np.sum(r_train**2)))
            e_sum = float(np.abs(alpha) @ r_train)
            b = li.T @ (li @ (kzx @ alpha))
            gap, err = _rkhs_gap(kfn, xs, alpha, z, b, kzz)
            e_rkhs = float(np.sqrt(max(gap, 0.0) + err))
            errs.append(min(e_sum, e_rkhs))
            rhos.append(rho)
            # per query: [a; G a; C a] = maps @ k, and m~ = mu + (Lj^-T B alpha) . k
            maps_.append((li, g @ li, c @ li))
            ws.append(li.T @ (bmat @ alpha))
            zs.append(z)
        self._pack(model, zs, maps_, ws, errs, rhos, rnds)
        self.mean_error_norm_ = np.array(errs)
        _, sd_c, merr = self._parts_batch(model.x_train_)
        comps = list(model.components_)
        ratio = (np.asarray(sd_c) + np.asarray(merr) / self.min_beta) / model.noise_
        self.inflation_at_training_ = np.mean(ratio > INFLATION_WARN, axis=0)
        notes = []
        for j, (comp, frac) in enumerate(zip(comps, self.inflation_at_training_, strict=True)):
            if frac > 0.01:
                floor = np.sqrt(rnds[j]) * (1.0 + errs[j] / self.min_beta)
                limited = floor > INFLATION_WARN * model.noise_[j]
                remedy = (
                    "the float64 rounding floor of the residual dominates (its allowance alone "
                    f"gives a std of {floor:.2g}): more inducing points will not help; use the "
                    "exact GP or a calibrated beta"
                    if limited
                    else "increase n_inducing"
                )
                notes.append(
                    f"FastGP with n_inducing={n_inducing}: for component {comp}, at "
                    f"{frac:.0%} of the training inputs the cache's std exceeds "
                    f"{INFLATION_WARN:g} times the noise std, which bounds the exact posterior "
                    f"std there: the cache's band is needlessly wide; {remedy}"
                )
        self.width_warnings_ = tuple(notes)
        for note in notes if warn else ():
            warnings.warn(note, InducingPointsWarning, stacklevel=2)

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
        mean_ex, var_ex = self.model.predict(x)
        m_fa, s_fa = (a[:, comps] for a in self.predict(x))
        m_ex, s_ex = np.asarray(mean_ex)[:, comps], np.sqrt(np.asarray(var_ex))[:, comps]
        lo_ok = m_fa - b * s_fa <= m_ex - b * s_ex
        hi_ok = m_fa + b * s_fa >= m_ex + b * s_ex
        return (lo_ok & hi_ok).mean(0)
