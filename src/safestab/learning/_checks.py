"""Argument checks shared by the learning modules (internal)."""

from __future__ import annotations

import numbers
from typing import Any

from ..errors import ParameterError

__all__ = ["SEED_MAX", "check_fitted", "check_seed"]

#: Largest accepted seed: NumPy's generators take any non-negative integer, but JAX's
#: ``PRNGKey`` wraps negative seeds and overflows past 64 bits; one range for every seed keeps
#: "the same seed" meaning the same thing in both.
SEED_MAX = 2**32 - 1


def check_seed(name: str, seed: Any) -> int:
    """Return ``seed`` as an int after checking it is an integer in ``[0, 2**32 - 1]``.

    Raises
    ------
    ParameterError
        If ``seed`` is not an integer (bools and floats included) or is out of range.
    """
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ParameterError(
            f"{name} must be an integer in [0, {SEED_MAX}], got {seed!r} "
            f"of type {type(seed).__name__}"
        )
    if not 0 <= int(seed) <= SEED_MAX:
        raise ParameterError(f"{name} must be an integer in [0, {SEED_MAX}], got {int(seed)}")
    return int(seed)


def check_count(name: str, value: Any) -> int:
    """Return ``value`` as an int after checking it is an integer >= 1 (not a bool or float).

    Raises
    ------
    ParameterError
        Naming the argument and what it received.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 1:
        raise ParameterError(
            f"{name} must be an integer >= 1, got {value!r} of type {type(value).__name__}"
        )
    return int(value)


def check_fitted(model: Any, attribute: str = "alpha_") -> None:
    """Raise unless ``model`` has the fitted ``attribute`` (scikit-learn's ``check_is_fitted``).

    Raises
    ------
    RuntimeError
        If ``model`` has not been fitted: ``model.attribute`` does not exist.
    """
    if not hasattr(model, attribute):
        raise RuntimeError(f"this {type(model).__name__} is not fitted yet; call fit(x, y) first")
