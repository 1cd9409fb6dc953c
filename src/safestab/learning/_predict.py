"""The one ``predict`` of the GP classes: scikit-learn's contract, written once.

``predict(x)`` returns the posterior mean of ``omega`` and ``predict(x, return_std=True)`` the
mean and the standard deviation, each of shape (..., n), for every GP class of
:mod:`safestab.learning` (``GaussianProcessModel.predict`` returned the variance and the band
classes' the std: the same call meant two things). A class supplies its mean and spread at
checked states of shape (N, n) through :meth:`Predictor._predict_rows`; the checks, the
reshaping and the meaning live here.
"""

from __future__ import annotations

import warnings
from typing import Any, ClassVar

import numpy as np

from .._validation import check_finite, check_real
from ..errors import DimensionError, InputTypeError

__all__ = ["Predictor"]


class Predictor:
    """``predict(x, return_std=False)`` over a class's batched mean and spread.

    Subclasses define ``n_states`` and :meth:`_predict_rows`, and may set :attr:`_spread`
    (what :meth:`_predict_rows` returns beside the mean), :attr:`_legacy_predict` (the old
    return of ``predict(x)``, kept for one release) and :meth:`_check_fitted`.
    """

    #: What :meth:`_predict_rows` returns beside the mean: ``"std"`` or ``"variance"``.
    _spread: ClassVar[str] = "std"
    #: Whether ``predict(x)`` without ``return_std`` still returns ``(mean, spread)`` (the
    #: class's old return), with a DeprecationWarning, for one release.
    _legacy_predict: ClassVar[bool] = False

    n_states: int

    def _check_fitted(self) -> None:
        """Raise if the model cannot predict yet."""

    def _predict_rows(self, x: np.ndarray) -> tuple[Any, Any]:
        """Mean and spread (:attr:`_spread`) at checked states of shape (N, n), each (N, n)."""
        raise NotImplementedError

    def predict(self, x: Any, return_std: bool | None = None) -> Any:
        """Posterior mean of ``omega`` at states ``x``; with ``return_std``, also its std.

        Parameters
        ----------
        x : array of shape (..., n)
        return_std : bool, optional
            ``False``: return the mean. ``True``: return ``(mean, std)``. Not given: the mean,
            except for a class whose ``predict(x)`` returned a pair before (the exact GP:
            mean and variance; FastGP and SparseGP: mean and std), which returns that pair
            for one more release, with a DeprecationWarning.

        Returns
        -------
        mean : ndarray of shape (..., n)
        std : ndarray of shape (..., n)
            Only with ``return_std=True``: the standard deviation of the latent ``omega_i``
            (without the noise; for FastGP the guaranteed std, for SparseGP its DTC band's);
            0 for components that are not learned.

        Raises
        ------
        InputTypeError
            If ``x`` is bool, complex, a string or not an array, or ``return_std`` is not a
            bool.
        DimensionError
            If the last axis of ``x`` is not ``n``.
        NonFiniteError
            If ``x`` contains NaN or inf.
        """
        legacy = return_std is None and self._legacy_predict
        if return_std is not None and not isinstance(return_std, bool | np.bool_):
            raise InputTypeError(f"return_std must be True or False, got {return_std!r}")
        self._check_fitted()
        check_real("x", x)
        x = np.asarray(x, dtype=float)
        n = self.n_states
        if x.ndim == 0 or x.shape[-1] != n:
            raise DimensionError(f"x must have shape (..., {n}), got shape {x.shape}")
        check_finite("x", x)
        mean, spread = self._predict_rows(x.reshape((-1, n)))
        mean = np.asarray(mean, dtype=float).reshape(x.shape)
        spread = np.asarray(spread, dtype=float).reshape(x.shape)
        if legacy:
            old = "(mean, variance)" if self._spread == "variance" else "(mean, std)"
            warnings.warn(
                f"{type(self).__name__}.predict(x) returns {old} for one more release only; "
                "it will return the mean, as scikit-learn's does: pass return_std=True for "
                "(mean, std), or return_std=False for the mean",
                DeprecationWarning,
                stacklevel=2,
            )
            return mean, spread
        if not return_std:
            return mean
        std = np.sqrt(spread) if self._spread == "variance" else spread
        return mean, std
