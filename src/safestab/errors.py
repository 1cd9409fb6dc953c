"""Exception and warning classes of safestab.

Every class also inherits the built-in exception a caller would catch without knowing
safestab, so ``except ValueError`` keeps working.
"""

from __future__ import annotations

__all__ = [
    "SafeStabError",
    "DimensionError",
    "ParameterError",
    "NonFiniteError",
    "NumericalError",
    "ScenarioError",
    "InfeasibleError",
    "RelativeDegreeError",
    "InputTypeError",
    "ModelError",
    "OutputError",
    "UnsupportedPrimitiveError",
    "CompilationError",
    "SafeStabWarning",
    "ConvergenceWarning",
    "DataWarning",
    "InducingPointsWarning",
]


class SafeStabError(Exception):
    """Base class of every error raised by safestab."""


class DimensionError(SafeStabError, ValueError):
    """An array has the wrong shape or number of dimensions."""


class ParameterError(SafeStabError, ValueError):
    """A parameter is outside its admissible range."""


class NonFiniteError(SafeStabError, ValueError):
    """An input contains NaN or infinity."""


class NumericalError(SafeStabError, ArithmeticError):
    """A numerical procedure failed (for example a Cholesky factorisation)."""


class ScenarioError(SafeStabError, ValueError):
    """A scenario file is invalid; the message names the offending key."""


class RelativeDegreeError(SafeStabError, ValueError):
    """A barrier the input cannot move: its ``L_g h`` is zero wherever it was probed.

    Such a barrier (relative degree 2 or more: a distance when the input is an acceleration)
    cannot be kept by choosing the input; build it with
    :func:`~safestab.certificates.high_order_cbf`.
    """


class InfeasibleError(SafeStabError, RuntimeError):
    """No input satisfies the requested conditions and ``strict=True`` was asked for."""


class InputTypeError(SafeStabError, TypeError):
    """An argument has the wrong type: a bool, complex or string array, or a list for an array."""


class ModelError(SafeStabError, ValueError):
    """A user-supplied model returned an invalid value (a negative standard deviation, say)."""


class OutputError(SafeStabError, OSError):
    """An output cannot be written: the folder is missing, not a folder, or not writable."""


class UnsupportedPrimitiveError(SafeStabError, NotImplementedError):
    """A function uses a JAX primitive (or dtype) that the C export cannot translate.

    The message names the primitive and the ``file:line`` of the code that produced it.
    """


class CompilationError(SafeStabError, RuntimeError):
    """The C compiler is missing or rejected the exported code; the message has its output."""


class SafeStabWarning(UserWarning):
    """Base class of every warning issued by safestab."""


class ConvergenceWarning(SafeStabWarning, UserWarning):
    """An optimiser stopped before converging, or a fitted value sits at a bound."""


class DataWarning(SafeStabWarning, UserWarning):
    """The data cannot support a trustworthy fit as given (too few rows, duplicates, ...)."""


class InducingPointsWarning(SafeStabWarning, UserWarning):
    """A fast GP cache has too few inducing points: its guaranteed band is much wider."""
