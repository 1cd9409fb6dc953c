"""What a scenario provides to be studied by Monte Carlo: the trial-study protocol.

:func:`~safestab.montecarlo.run_montecarlo` takes any scenario with a method
``trial_study(spec) -> TrialStudy``; the Monte Carlo package reads the study through these
members only, so it knows no scenario by name. The ACC and obstacle scenarios provide theirs
in :mod:`safestab.scenarios.trial_studies`.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

__all__ = ["TrialStudy"]


@runtime_checkable
class TrialStudy(Protocol):
    """The members a Monte Carlo study reads (hashable and picklable: a frozen dataclass).

    Attributes
    ----------
    name : str
        Names the output files.
    spec : MonteCarloSpec
        The study's settings (counts, controllers, GP, delta, initial distribution).
    n_states, n_steps : int
        State dimension ``n``; closed-loop steps per trial.
    dt, t_final : float
        Step and horizon, s (``n_steps = round(t_final / dt)``).
    h_unit : str
        Unit of the CBF ``h``, for the summary and the figure.
    exogenous : callable or None
        ``e(t, x, params) -> (n,)``, a known term added to the true dynamics.
    """

    name: str
    spec: Any
    n_states: int
    n_steps: int
    dt: float
    t_final: float
    h_unit: str
    exogenous: Any

    def systems(self) -> tuple[Any, Any]:
        """``(true, nominal)`` control-affine systems."""
        ...

    def certificates(self) -> tuple[Any, Any]:
        """``(clf, cbf)`` shared by every compared controller."""
        ...

    def controller_options(self) -> dict[str, Any]:
        """Keyword arguments of every compared ``UniversalController`` (kappa, limits, ...).

        An optional member ``build_controller(system, clf, cbf, **options)`` builds each
        compared controller instead of ``UniversalController`` (the obstacle's
        ``controller.limit_method = "filter"``: a :class:`~safestab.SafetyFilter`).
        """
        ...

    # optional: ``controller_settings() -> dict``, the compared controllers' settings as JSON
    # data (numbers, lists, strings; ``limit_method`` among them), recorded in the Monte Carlo
    # and price documents
    # (:meth:`safestab.scenarios.trial_studies.ScenarioTrials.controller_settings`)

    def omega(self, x: Any) -> Any:
        """The true model error, shape (..., n)."""
        ...

    def gp_settings(self) -> dict[str, Any]:
        """``n_samples`` (Q), ``kernel``, ``hyper_subset``, ``gp_beta``; ``input_gain``.

        ``input_gain`` (optional, default ``"nominal"``): ``"learned"`` estimates a constant
        input-matrix error with each data set's GP (:func:`~safestab.learning.fit_input_gain`)
        and gives the GP controllers ``g + D``.
        """
        ...

    def calibration_shape(self) -> tuple[int, int]:
        """``(states per data trajectory, thinning stride)`` of the conformal calibration."""
        ...

    def collect(self, n_samples: int, seed: int) -> Any:
        """A ``Dataset`` of ``n_samples`` rows drawn with ``seed``."""
        ...

    def draw_trials(self, seed: int, indices: Any) -> tuple[Any, Any]:
        """Initial states (B, n) and per-trial data (a pytree) of the trials ``indices``."""
        ...
