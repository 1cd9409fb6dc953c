"""A prediction cache for the control loop whose cost per query does not grow with Q.

From a fitted :class:`~safestab.learning.GaussianProcessModel`, pick ``M`` inducing inputs
``Z`` among the training inputs (greedy pivoted Cholesky of the kernel matrix), take the
*exact* posterior of ``omega_i`` at ``Z`` (conditioned on all ``Q`` samples), and project it
to a query ``x`` through the prior conditional::

    a(x)  = Lz^-1 k_Zx                          (Lz: Cholesky factor of Kzz)
    m~(x) = a(x) . Lz^-1 mu_Z
    v~(x) = [k(x, x) - |a(x)|^2] + |G a(x)|^2,  G^T G = Lz^-1 S_Z Lz^-T

with ``mu_Z``, ``S_Z`` the exact posterior mean and covariance at ``Z``. The two terms of
``v~`` are each non-negative (prior residual given ``f_Z``; posterior spread at ``Z``); written
as ``k(x, x) - k^T B k`` the same quantity cancels catastrophically when the posterior
variance is many orders below the prior one, as in the ACC study.

so each query costs ``M`` kernel evaluations and an ``M x M`` product, independent of ``Q``.

The projected variance is not in general an upper bound of the exact one, so the cache does
not claim it is: :meth:`FastGP.calibrate` measures, on held-out states, the factor ``c_i``
by which ``beta sigma~_i`` must be widened so that the cache's band contains the exact band
``m_i +- beta sigma_i`` at every checked state, and :meth:`FastGP.mean_std` returns the
widened ``c_i sigma~_i``. The guarantee is therefore empirical, on the distribution of the
checked states (docs/performance.md reports the factors and a check on further states).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_finite, check_scalar_range
from ..errors import DimensionError, ParameterError
from .gp import GaussianProcessModel, _kernel

__all__ = ["FastGP"]


def _pivoted_cholesky_indices(kfn, xs: np.ndarray, amp2: float, m: int, tol: float) -> np.ndarray:
    """Greedy choice of ``m`` rows maximising the residual prior variance (pivoted Cholesky)."""
    q = xs.shape[0]
    m = min(m, q)
    diag = np.full(q, amp2)
    rows = np.zeros((m, q))
    chosen: list[int] = []
    for i in range(m):
        j = int(np.argmax(diag))
        if diag[j] <= tol * amp2:
            break
        chosen.append(j)
        col = np.asarray(kfn(xs, xs[j : j + 1]))[:, 0] - rows[:i].T @ rows[:i, j]
        rows[i] = col / np.sqrt(diag[j])
        diag = np.maximum(diag - rows[i] ** 2, 0.0)
    return np.array(chosen)


class FastGP:
    """Inducing-point cache of a fitted GP, with a measured widening of its uncertainty.

    Parameters
    ----------
    model : GaussianProcessModel
        A fitted model.
    n_inducing : int
        ``M``, inducing inputs per component (default 32).
    pivot_tol : float
        Stop adding inducing inputs once the largest residual prior variance is below
        ``pivot_tol * amplitude^2`` (default 1e-12: further points change nothing in float64).

    Attributes
    ----------
    inducing_ : array of shape (k, M, n)
        Inducing inputs per learned component (in the units of x).
    widening_ : array of shape (k,)
        Factors ``c_i >= 1`` applied to ``sigma~_i``; all 1 until :meth:`calibrate`.
    """

    def __init__(
        self, model: GaussianProcessModel, n_inducing: int = 32, *, pivot_tol: float = 1e-12
    ) -> None:
        model._check_fitted()
        if int(n_inducing) < 1:
            raise ParameterError(f"n_inducing must be >= 1, got {n_inducing!r}")
        self.model = model
        self.n_states = model.n_states_
        self.components_ = model.components_
        xs = (model.x_train_ - model.x_offset_) / model.x_scale_
        zs, ws, rs, ls_ = [], [], [], []
        for j in range(len(model.components_)):
            amp = float(model.amplitude_[j])
            kfn = _kernel(model.kernel, amp, jnp.asarray(model._lengthscale_std[j]))
            idx = _pivoted_cholesky_indices(kfn, xs, amp * amp, int(n_inducing), pivot_tol)
            z = xs[idx]
            kzz = np.asarray(kfn(z, z)) + model.jitter * amp * amp * np.eye(len(idx))
            kzx = np.asarray(kfn(z, xs))
            lz = np.linalg.cholesky(kzz)
            # exact posterior at Z, whitened by Lz: mean Lz^-1 mu_Z, covariance
            # T = Lz^-1 S_Z Lz^-T = I - W W^T with W = Lz^-1 K_ZX L^-T (L: chol of K + s^2 I)
            a_train = np.linalg.solve(lz, kzx)  # (M, Q)
            w = a_train @ model.alpha_[j]
            wmat = np.asarray(
                jax.scipy.linalg.solve_triangular(
                    jnp.asarray(model.chol_[j]), jnp.asarray(a_train.T), lower=True
                )
            )  # (Q, M)
            t = np.eye(len(idx)) - wmat.T @ wmat
            evals, evecs = np.linalg.eigh(0.5 * (t + t.T))
            rs.append((evecs * np.sqrt(np.maximum(evals, 0.0))).T)  # G^T G = T
            ls_.append(lz)
            zs.append(z)
            ws.append(w)
        m_max = max(len(z) for z in zs)
        pad = lambda a, shape: np.pad(a, [(0, s - d) for s, d in zip(shape, a.shape, strict=True)])  # noqa: E731
        n = xs.shape[1]

        def pad_chol(lz):  # identity on the padding keeps the triangular solve well posed
            out = np.eye(m_max)
            out[: lz.shape[0], : lz.shape[0]] = lz
            return out

        # Pad to a common M (padded rows get zero weight and zero columns), then precompute
        # the maps of a query's kernel vector k: a = Lz^-1 k and G a = (G Lz^-1) k, stacked so
        # that a query is one small matrix-vector product (a triangular solve per query costs
        # a LAPACK call, several times the arithmetic at M = 32).
        maps, means = [], []
        for lz, g, w in zip(ls_, rs, ws, strict=True):
            lz_inv = np.linalg.solve(pad_chol(lz), np.eye(m_max))
            g_pad = pad(g, (m_max, m_max))
            maps.append(np.concatenate([lz_inv, g_pad @ lz_inv], 0))  # (2M, M)
            means.append(lz_inv.T @ pad(w, (m_max,)))  # m~ = k . Lz^-T Lz^-1 mu_Z
        self._z = jnp.asarray(np.stack([pad(z, (m_max, n)) for z in zs]))
        self._maps = jnp.asarray(np.stack(maps))
        self._wk = jnp.asarray(np.stack(means))
        self._mask = jnp.asarray(np.stack([np.arange(m_max) < len(z) for z in zs]))
        self._m = m_max
        self.n_inducing_ = np.array([len(z) for z in zs])
        self.inducing_ = np.asarray(self._z) * model.x_scale_ + model.x_offset_
        self.widening_ = np.ones(len(model.components_))

    def _mean_std_raw(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        m = self.model
        z0 = (x - jnp.asarray(m.x_offset_)) / jnp.asarray(m.x_scale_)
        amp = jnp.asarray(m.amplitude_)
        ls = jnp.asarray(m._lengthscale_std)

        mm = self._m

        def per_comp(a, l_, z, wk, maps, mask):
            k = jnp.where(mask, _kernel(m.kernel, a, l_)(z, z0[None, :])[:, 0], 0.0)
            both = maps @ k
            v, gv = both[:mm], both[mm:]
            # prior residual given f_Z (>= 0) plus the projected posterior covariance at Z
            var = jnp.maximum(a * a - v @ v, 0.0) + gv @ gv
            return k @ wk, jnp.sqrt(var)

        mean_c, std_c = jax.vmap(per_comp)(amp, ls, self._z, self._wk, self._maps, self._mask)
        comps = jnp.asarray(self.components_)
        mean = jnp.zeros(self.n_states).at[comps].set(mean_c + jnp.asarray(m.mean_))
        std = jnp.zeros(self.n_states).at[comps].set(std_c)
        return mean, std

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and *widened* standard deviation at one state (n,), jittable, O(M^2)."""
        mean, std = self._mean_std_raw(x)
        c = (
            jnp.zeros(self.n_states)
            .at[jnp.asarray(self.components_)]
            .set(jnp.asarray(self.widening_))
        )
        return mean, c * std

    def calibrate(self, x_check: Any, beta: Any, *, margin: float = 1.05) -> np.ndarray:
        """Set :attr:`widening_` so the cache's band contains the exact band on ``x_check``.

        For each learned component, ``c_i = margin * max_x (|m~_i - m_i| + beta_i sigma_i) /
        (beta_i sigma~_i)`` over the check states, and at least 1.

        Parameters
        ----------
        x_check : array of shape (N, n)
            Held-out states from the region the controller will visit.
        beta : float or array of shape (n,)
            The confidence scaling the controller will use.
        margin : float
            Extra factor >= 1 for states not in the check set.

        Returns
        -------
        array of shape (k,)
            The widening factors.
        """
        x_check = np.asarray(x_check, float)
        if x_check.ndim != 2 or x_check.shape[1] != self.n_states:
            raise DimensionError(
                f"x_check must have shape (N, {self.n_states}), got {x_check.shape}"
            )
        check_finite("x_check", x_check)
        check_scalar_range("beta", beta, lower=0.0, strict_lower=True)
        check_scalar_range("margin", margin, lower=1.0)
        comps = list(self.components_)
        b = np.broadcast_to(np.asarray(beta, float), (self.n_states,))[comps]
        m_ex, v_ex = self.model.predict(x_check)
        m_fa, s_fa = jax.vmap(self._mean_std_raw)(jnp.asarray(x_check))
        need = np.abs(np.asarray(m_fa) - np.asarray(m_ex)) + b * np.sqrt(np.asarray(v_ex))
        need = need[:, comps]
        have = b * np.maximum(np.asarray(s_fa)[:, comps], 1e-300)
        self.widening_ = np.maximum(margin * np.max(need / have, axis=0), 1.0)
        return self.widening_

    def coverage_of_exact_band(self, x: Any, beta: Any) -> np.ndarray:
        """Fraction of states where the widened band contains the exact band, per component."""
        x = np.asarray(x, float)
        comps = list(self.components_)
        b = np.broadcast_to(np.asarray(beta, float), (self.n_states,))[comps]
        m_ex, v_ex = self.model.predict(x)
        m_fa, s_fa = jax.vmap(self.mean_std)(jnp.asarray(x))
        lo_ok = (np.asarray(m_fa) - b * np.asarray(s_fa))[:, comps] <= (
            np.asarray(m_ex) - b * np.sqrt(np.asarray(v_ex))
        )[:, comps] + 1e-12
        hi_ok = (np.asarray(m_fa) + b * np.asarray(s_fa))[:, comps] >= (
            np.asarray(m_ex) + b * np.sqrt(np.asarray(v_ex))
        )[:, comps] - 1e-12
        return (lo_ok & hi_ok).mean(0)
