"""The obstacle study end to end: data, GP fit, three controllers with and without limits, maps.

For each controller (true model, mismatched model, GP-robust) and each limit setting (none,
the box ``|u_i| <= input_limit``) the closed loop is simulated from every start of the grid.
The formula is chosen per start where its theorem applies: the compatible formula (Theorem 1,
or Theorem 2 for the GP-robust controller) from starts inside that controller's certified
domain of attraction ``{V < doa_fraction c*}`` (``c*`` the smallest ``V`` at which its
conditions are incompatible in the safe set) in the runs without input limits, and the
relaxed formula (Theorem 3) elsewhere: outside that set, and everywhere in the runs with
limits, where the projection (eq. (26)) voids Theorem 1's guarantee. With
``controller.limit_method = "filter"`` the runs with limits solve the relaxed problem with the
box as constraints instead (:class:`~safestab.SafetyFilter`). Each trajectory ends
as ``converged``, ``stuck`` (at rest outside the goal ball), ``unsafe`` (``h < 0`` at some
sample) or ``moving`` (none of these at ``t_final``).
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._batching import in_threads
from .._io import with_finite_status
from ..certificates import LieTerms, lie_terms_point
from ..controller_names import (
    GP_CONTROLLERS,
    GP_ROBUST,
    MODEL_OF,
    STUDY_CONTROLLERS,
    build_compared,
)
from ..controllers import StepStatus, UniversalController
from ..errors import ParameterError
from ..filters import SafetyFilter
from ..formulas import clf_cbf, compatibility
from ..learning import FastGP, GaussianProcessModel, InputGain, fit_input_gain
from ..learning.bounds import mean_std_batch
from ..montecarlo.plugin import GP_MONTECARLO
from ..robust import probabilistic_compatibility, robust_margins
from ..simulation import simulate
from .kinds import with_overrides
from .obstacle import PRESETS, ObstacleScenario, load_obstacle_scenario
from .pipeline import (
    MetricsWriter,
    StepProgress,
    Study,
    Summary,
    collect_study_data,
    conformal_calibration,
    fit_study_gp,
    silent,
)

__all__ = [
    "CONTROLLERS",
    "STUDY",
    "fit_obstacle_gp",
    "obstacle_controller",
    "LIMIT_SETTINGS",
    "OUTCOMES",
    "CompatibilityMaps",
    "ObstacleRun",
    "ObstacleStudyResult",
    "classify_outcomes",
    "compatibility_maps",
    "doa_level",
    "run_obstacle_study",
    "study_controller",
    "verdict",
]

#: The three controllers, as in the ACC study.
CONTROLLERS = STUDY_CONTROLLERS
#: The controllers that use no data (the true and the nominal model): their part of the
#: study runs in a thread of its own once the GP is fitted, beside the GP-robust part.
MODEL_BASED = CONTROLLERS[:2]
#: The runs without and with the input box.
LIMIT_SETTINGS = ("no limits", "input limits")
#: GP-robust's two settings' closed loops run (and compile, on a first run) this many at once,
#: in threads, beside the model-based controllers' thread: JAX releases the GIL while it
#: compiles and runs. Results do not depend on it.
SIMULATION_THREADS = 2
#: How a trajectory ends, in order of precedence.
OUTCOMES = ("unsafe", "converged", "stuck", "moving")


def classify_outcomes(
    x: Any, h: Any, dt: float, ball_radius: float, rest_speed: float
) -> np.ndarray:
    """The outcome of each trajectory: ``unsafe``, ``converged``, ``stuck`` or ``moving``.

    Parameters
    ----------
    x : array of shape (N, T, 2)
        Positions, m (``T >= 2`` samples).
    h : array of shape (N, T)
        CBF values, m^2.
    dt : float
        Sample spacing, s.
    ball_radius : float
        Radius of the goal ball, m.
    rest_speed : float
        Speed below which the end state counts as at rest, m/s.

    Returns
    -------
    array of str of shape (N,)
        ``unsafe`` if ``h < 0`` at some sample (or is not finite); else ``converged`` if
        ``|x(T)| <= ball_radius``; else ``stuck`` if ``|x(T) - x(T-1)| / dt <= rest_speed``;
        else ``moving``.
    """
    x = np.asarray(x, float)
    h = np.asarray(h, float)
    unsafe = ~np.all(h >= 0, axis=-1)  # NaN counts as unsafe
    end = x[:, -1]
    speed = np.linalg.norm(x[:, -1] - x[:, -2], axis=-1) / dt
    converged = np.linalg.norm(end, axis=-1) <= ball_radius
    stuck = speed <= rest_speed
    return np.where(
        unsafe, "unsafe", np.where(converged, "converged", np.where(stuck, "stuck", "moving"))
    )


def _params(sc: ObstacleScenario) -> dict[str, Any]:
    return {"kappa": sc.kappa, "rho": sc.rho, "phi": sc.phi, "varphi": sc.varphi}


def verdict(
    sc: ObstacleScenario,
    controller: str,
    x: Any,
    uncertainty: Any = None,
) -> np.ndarray:
    """Whether the controller's CLF and CBF conditions are compatible at ``x``.

    ``"true model"`` and ``"mismatched model"``: :func:`~safestab.compatibility` (Lemma 1) on
    the true or nominal Lie terms. ``"GP-robust"``: the ``updated`` verdict (eq. (20),
    corrected) of :func:`~safestab.probabilistic_compatibility` on the terms of
    ``sc.system("learned")`` (the nominal ones unless a gain was learned) with the margins of
    ``uncertainty`` at ``beta = gp_beta``.

    Parameters
    ----------
    sc : ObstacleScenario
    controller : str
        One of :data:`CONTROLLERS`.
    x : array of shape (..., 2)
    uncertainty : UncertaintyModel, optional
        Required for ``"GP-robust"``.

    Returns
    -------
    bool array of shape (...,)

    Raises
    ------
    ParameterError
        If ``controller`` is not one of :data:`CONTROLLERS`, or is ``"GP-robust"`` without
        an uncertainty model.
    """
    if controller not in CONTROLLERS:
        raise ParameterError(f"controller must be one of {CONTROLLERS}, got {controller!r}")
    if controller == GP_ROBUST and uncertainty is None:
        raise ParameterError("the 'GP-robust' verdict needs uncertainty= (a model of omega)")
    x = jnp.asarray(x, dtype=float)
    which = MODEL_OF[controller]
    flat = x.reshape(-1, 2)
    terms = _terms(sc, which, flat)
    if controller != GP_ROBUST:
        out = compatibility(*terms, **_params(sc)).compatible
    else:
        out = _robust(sc, uncertainty, flat, terms).updated
    return np.asarray(out).reshape(x.shape[:-1])


def _terms(sc: ObstacleScenario, which: str, x: jax.Array) -> LieTerms:
    """Autodiff Lie terms at states (N, 2), compiled once per call."""
    system = sc.system(which)
    clf, cbf = sc.certificates()
    return jax.jit(jax.vmap(lambda s: lie_terms_point(system, clf, cbf, s)))(x)


def _robust(
    sc: ObstacleScenario, uncertainty: Any, x: jax.Array, terms: LieTerms, calibrated: bool = False
) -> Any:
    """:func:`probabilistic_compatibility` of the GP-robust terms at states (N, 2).

    ``calibrated``: ``sc.gp_beta`` is a conformal beta (:func:`calibrate_beta`), which holds
    for both components at once, so the stated probability is ``1 - delta``; otherwise it is
    Lemma 2's ``(1 - delta)^2``, nominal unless ``gp_beta`` meets the lemma's bound.
    """
    clf, cbf = sc.certificates()

    @jax.jit
    def margins(x):
        mean, std = jax.vmap(uncertainty.mean_std)(x)
        beta = jnp.full(2, sc.gp_beta)
        # the controller's own CLF term: with its boundary layer, if any
        return robust_margins(
            clf.gradient(x), cbf.gradient(x), mean, std, beta, sc.robust_clf_layer
        )

    n_bounds = 1 if calibrated else 2
    return probabilistic_compatibility(
        terms, margins(x), **_params(sc), delta=sc.delta, n_components=n_bounds
    )


def doa_level(
    sc: ObstacleScenario, controller: str, uncertainty: Any = None, verdicts: Any = None
) -> float:
    """``c*``: the smallest ``V`` at which the controller's conditions are incompatible in C.

    Incompatibility needs ``b`` and ``d`` pointing the same way, which happens only on
    :meth:`ObstacleScenario.parallel_set`; ``c*`` is the minimum of ``V`` over the points of
    that set with ``h >= 0`` that :func:`verdict` calls incompatible (``inf`` if none).
    Theorem 1's hypothesis holds on ``{V < c*} ∩ C``. ``verdicts`` (shape (K,), on
    ``sc.parallel_set()``) may be passed when already computed.
    """
    pts = sc.parallel_set()
    if verdicts is None:
        verdicts = verdict(sc, controller, pts, uncertainty)
    bad = ~np.asarray(verdicts) & (np.asarray(sc.h(pts)) >= 0)
    return float(np.min(np.asarray(sc.V(pts[bad])))) if np.any(bad) else float("inf")


def _status_summary(status: np.ndarray) -> str:
    """``"ok"``, or the count of steps per :class:`~safestab.StepStatus` other than OK."""
    names, counts = np.unique(np.asarray(status)[np.asarray(status) != 0], return_counts=True)
    if not names.size:
        return "ok"
    return ", ".join(f"{StepStatus(int(v)).name} {int(n)}" for v, n in zip(names, counts))


@dataclasses.dataclass(frozen=True)
class ObstacleRun:
    """The closed loops of one controller with one limit setting, from every start.

    Attributes
    ----------
    controller, limits : str
        From :data:`CONTROLLERS` and :data:`LIMIT_SETTINGS`.
    x0 : array of shape (N, 2)
    compatible_formula : bool array of shape (N,)
        True where the compatible formula was used (start inside the certified domain of
        attraction, no input limits), False where the relaxed formula was.
    t : array of shape (T,)
    x, u : arrays of shape (N, T, 2)
    V, h : arrays of shape (N, T)
    compatible : bool array of shape (N, T)
        The controller's own compatibility flag per step. For a safety filter (the runs with
        limits under ``controller.limit_method = "filter"``) it says that the filter's whole
        problem (soft CLF, CBF, box) was solved; its slack absorbs a CLF-CBF conflict, so
        it is not Lemma 1's verdict (``end_verdict`` is).
    status : int array of shape (N, T)
    outcome : str array of shape (N,)
        See :func:`classify_outcomes`.
    end_verdict : bool array of shape (N,)
        :func:`verdict` recomputed at each end point.
    """

    controller: str
    limits: str
    x0: np.ndarray
    compatible_formula: np.ndarray
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    V: np.ndarray
    h: np.ndarray
    compatible: np.ndarray
    status: np.ndarray
    outcome: np.ndarray
    end_verdict: np.ndarray

    def stopped(self, ball_radius: float, rest_speed: float) -> np.ndarray:
        """Runs at rest outside the goal ball at the end, safe or not; bool (N,)."""
        speed = np.linalg.norm(self.x[:, -1] - self.x[:, -2], axis=-1) / (self.t[1] - self.t[0])
        return (speed <= rest_speed) & (np.linalg.norm(self.x[:, -1], axis=-1) > ball_radius)

    def input_variation(self) -> np.ndarray:
        """Total variation of ``u`` per second of each run, ``sum_k |u_k+1 - u_k| / T``, m/s^2.

        ``|.|`` the Euclidean norm; ``T`` the run's horizon. A run whose input chatters
        between samples scores high even when ``|u|`` stays small. Shape (N,).
        """
        jumps = np.linalg.norm(np.diff(self.u, axis=1), axis=-1).sum(axis=1)
        return jumps / (self.t[-1] - self.t[0])

    def variation_in_ball_share(self, ball_radius: float) -> float:
        """Share of all runs' input variation made at states within ``ball_radius`` of the goal.

        The jump ``|u_k+1 - u_k|`` counts where ``x_k`` is; 0 when no input varies.
        """
        jumps = np.linalg.norm(np.diff(self.u, axis=1), axis=-1)
        near = np.linalg.norm(self.x[:, :-1], axis=-1) <= ball_radius
        total = float(jumps.sum())
        return float(jumps[near].sum()) / total if total > 0 else 0.0

    def variation_in_ball(self, ball_radius: float) -> np.ndarray:
        """Each run's input variation made within ``ball_radius`` of the goal, m/s^2.

        Per second of the horizon; the jump ``|u_k+1 - u_k|`` counts where ``x_k`` is; shape
        (N,). Chattering at the goal scores high here; a transient far from it does not.
        """
        jumps = np.linalg.norm(np.diff(self.u, axis=1), axis=-1)
        near = np.linalg.norm(self.x[:, :-1], axis=-1) <= ball_radius
        return np.where(near, jumps, 0.0).sum(axis=1) / (self.t[-1] - self.t[0])

    def converge_time(self, ball_radius: float) -> np.ndarray:
        """Time after which each run stays within ``ball_radius`` of the goal, s.

        NaN where the run is outside the ball at the end. Shape (N,).
        """
        inside = np.linalg.norm(self.x, axis=-1) <= ball_radius
        # index of the last sample outside, + 1 (0 when always inside)
        last_out = np.where(inside.all(1), 0, inside.shape[1] - np.argmax(~inside[:, ::-1], 1))
        return np.where(inside[:, -1], self.t[np.minimum(last_out, len(self.t) - 1)], np.nan)

    def summary(self, ball_radius: float | None = None) -> dict[str, Any]:
        """Counts per outcome, min h, stuck end points with their verdicts, largest |u|.

        The largest |u| of all starts, and of the starts off the x1 axis (None when none).

        With ``ball_radius``, also the median input variation (:meth:`input_variation`)
        over all starts, the share of it made within the ball, the largest variation within
        the ball of any start (:meth:`variation_in_ball`) and the median time to converge
        (:meth:`converge_time`) over the converged starts (``None`` when none converged).
        """
        stuck = np.flatnonzero(self.outcome == "stuck")
        unsafe = np.flatnonzero(self.outcome == "unsafe")
        converged = self.outcome == "converged"  # inside the ball at the end: a finite time
        off_axis = self.x0[:, 1] != 0.0
        return {
            "n_starts": int(len(self.x0)),
            "outcomes": {o: int(np.sum(self.outcome == o)) for o in OUTCOMES},
            "compatible_formula_starts": int(np.sum(self.compatible_formula)),
            "min_h_m2": float(np.min(self.h)),
            "max_abs_u_mps": float(np.max(np.abs(self.u))),
            # the starts on the x1 axis stay on it by symmetry, where b and d are parallel
            # (docs/obstacle.md, "The axis starts"); the largest input of the others
            "max_abs_u_off_axis_mps": (
                float(np.max(np.abs(self.u[off_axis]))) if np.any(off_axis) else None
            ),
            **(
                {}
                if ball_radius is None
                else {
                    "median_input_variation_mps2": float(np.median(self.input_variation())),
                    "input_variation_in_ball_share": self.variation_in_ball_share(ball_radius),
                    "max_input_variation_in_ball_mps2": float(
                        np.max(self.variation_in_ball(ball_radius))
                    ),
                    "median_converge_time_s": (
                        float(np.median(self.converge_time(ball_radius)[converged]))
                        if np.any(converged)
                        else None
                    ),
                }
            ),
            "status": _status_summary(self.status),
            "stuck": [
                {
                    "x0_m": self.x0[i].tolist(),
                    "end_m": self.x[i, -1].tolist(),
                    "end_h_m2": float(self.h[i, -1]),
                    "end_V_m2": float(self.V[i, -1]),
                    "end_flag_compatible": bool(self.compatible[i, -1]),
                    "end_verdict_compatible": bool(self.end_verdict[i]),
                }
                for i in stuck
            ],
            "unsafe": [
                {"x0_m": self.x0[i].tolist(), "min_h_m2": float(np.min(self.h[i]))} for i in unsafe
            ],
        }


@dataclasses.dataclass(frozen=True)
class CompatibilityMaps:
    """Compatibility verdicts over the map grid.

    Attributes
    ----------
    x1 : array of shape (n1,)
    x2 : array of shape (n2,)
    nominal_region : int array of shape (n1, n2)
        :class:`~safestab.formulas.Region` of the compatible formula on the nominal terms.
    nominal_compatible : bool array of shape (n1, n2)
        Lemma 1 (:func:`~safestab.compatibility`) on the nominal terms.
    robust_updated : bool array of shape (n1, n2)
        Eq. (20), corrected, for the GP-robust terms
        (:func:`~safestab.probabilistic_compatibility`).
    robust_lemma4 : bool array of shape (n1, n2)
        Lemma 4's sufficient condition (nominal compatibility and eqs. (18), (19)).
    probability : float
        The probability stated with the robust verdict: ``(1 - delta)^2`` (Lemma 2, per
        component), or ``1 - delta`` for a calibrated beta (:func:`compatibility_maps`).
    """

    x1: np.ndarray
    x2: np.ndarray
    nominal_region: np.ndarray
    nominal_compatible: np.ndarray
    robust_updated: np.ndarray
    robust_lemma4: np.ndarray
    probability: float


def compatibility_maps(
    sc: ObstacleScenario, uncertainty: Any, *, calibrated: bool = False
) -> CompatibilityMaps:
    """Evaluate the Lemma 1 and the probabilistic verdicts over the map grid.

    Parameters
    ----------
    sc : ObstacleScenario
    uncertainty : UncertaintyModel
        The model of ``omega`` the GP-robust controller uses.
    calibrated : bool
        True when ``sc.gp_beta`` came from :func:`calibrate_beta`: the stated probability
        is then ``1 - delta`` (about the calibration's excitation trajectories), else
        ``(1 - delta)^2``.
    """
    x1, x2 = sc.map_axes()
    grid = jnp.asarray(np.stack(np.meshgrid(x1, x2, indexing="ij"), -1).reshape(-1, 2))
    terms = _terms(sc, "nominal", grid)
    params = _params(sc)
    comp = compatibility(*terms, **params)
    region = clf_cbf(*terms, **params).region
    learned = terms if sc.learned_gain is None else _terms(sc, "learned", grid)
    pc = _robust(sc, uncertainty, grid, learned, calibrated)
    shape = (len(x1), len(x2))
    return CompatibilityMaps(
        x1=x1,
        x2=x2,
        nominal_region=np.asarray(region).reshape(shape),
        nominal_compatible=np.asarray(comp.compatible).reshape(shape),
        robust_updated=np.asarray(pc.updated).reshape(shape),
        robust_lemma4=np.asarray(pc.lemma4).reshape(shape),
        probability=pc.probability,
    )


@dataclasses.dataclass
class ObstacleStudyResult(MetricsWriter):
    """Everything the obstacle study produced."""

    scenario: ObstacleScenario
    gp: GaussianProcessModel
    uncertainty: Any  #: the model the GP-robust controller used (the GP or a FastGP)
    coverage: dict[str, Any]
    doa: dict[str, float]  #: c* per controller, m^2
    runs: dict[tuple[str, str], ObstacleRun]
    maps: CompatibilityMaps
    parallel_set: np.ndarray  #: (K, 2) points where b, d point the same way
    parallel_verdicts: dict[str, np.ndarray]  #: per controller, (K,) bool
    timings: dict[str, float]

    def metrics_document(self) -> dict[str, Any]:
        """Outcomes per run, ``c*``, GP coverage, map counts and timings, as strict JSON data.

        Non-finite numbers become ``None`` (JSON ``null``), listed under ``non_finite`` with
        ``status = "non-finite"``; otherwise ``status = "ok"``.
        """
        sc = self.scenario
        doc = {
            "scenario": sc.name,
            "kind": "obstacle",
            "settings": {
                "seed": sc.seed,
                "n_samples": sc.n_samples,
                "t_final_s": sc.t_final,
                "dt_s": sc.dt,
                "n_starts": int(len(sc.start_states())),
                "gp_controller": (
                    "exact" if sc.n_inducing == 0 else f"FastGP n_inducing<={sc.n_inducing}"
                ),  # the inputs used per component: gp.cache.n_inducing
                "robust_clf_layer_m": sc.robust_clf_layer,
                "limit_method": sc.limit_method,  # the runs with input limits
            },
            "doa_c_star_m2": self.doa,
            "doa_level_m2": {k: sc.doa_fraction * v for k, v in self.doa.items()},
            "runs": {
                f"{c} / {lim}": run.summary(sc.ball_radius) for (c, lim), run in self.runs.items()
            },
            "gp": self.coverage,
            "maps": {
                "grid": [len(self.maps.x1), len(self.maps.x2)],
                "nominal_incompatible_points": int(np.sum(~self.maps.nominal_compatible)),
                "robust_incompatible_points": int(np.sum(~self.maps.robust_updated)),
                "robust_lemma4_points": int(np.sum(self.maps.robust_lemma4)),
                "stated_probability": self.maps.probability,
            },
            "timings_s": self.timings,
        }
        return with_finite_status(doc)


def _coverage(sc: ObstacleScenario, model: Any, x: np.ndarray, calibrated: bool) -> dict[str, Any]:
    """Held-out coverage of ``|omega_i - m_i| <= beta sigma_i`` against the true current."""
    mean, std = mean_std_batch(model, x)
    err = np.abs(np.asarray(sc.omega(x)) - mean)
    inside = err <= sc.gp_beta * np.asarray(std)
    return {
        "n_held_out": int(len(x)),
        "per_component": inside.mean(0).tolist(),
        "joint": float(np.all(inside, -1).mean()),
        "rmse_mps": np.sqrt((err**2).mean(0)).tolist(),
        "beta": sc.gp_beta,
        "beta_method": "conformal" if calibrated else "chosen",
        "delta": sc.delta,
        # chosen: Lemma 2's (1 - delta)^2, nominal unless beta meets the lemma's bound;
        # conformal: the calibrated joint probability (calibrate_beta)
        "stated_probability": (1 - sc.delta) ** (1 if calibrated else 2),
    }


def _cache_width(gp: GaussianProcessModel, cache: FastGP) -> dict[str, Any]:
    """The cache's inducing inputs, and its std over the exact std at the training inputs."""
    x = gp.x_train_
    comps = list(gp.components_)
    exact = gp.predict(x, return_std=True)[1][:, comps]
    ratio = cache.predict(x, return_std=True)[1][:, comps] / exact
    return {
        "n_inducing": cache.n_inducing_.tolist(),
        "std_over_exact_at_training_median": np.median(ratio, 0).tolist(),
        "std_over_exact_at_training_max": np.max(ratio, 0).tolist(),
    }


#: Fewest calibration trajectories for ``beta_method = "conformal"`` (also ``ceil(1/delta)``).
CONFORMAL_MIN_TRAJECTORIES = 100


def calibrate_beta(sc: ObstacleScenario, model: Any) -> dict[str, Any]:
    """Split conformal ``beta`` of ``model`` on fresh trajectories, per trajectory.

    :func:`~safestab.scenarios.pipeline.conformal_calibration` with
    ``max(CONFORMAL_MIN_TRAJECTORIES, ceil(1 / delta))`` excitation trajectories of the
    scenario's horizon, collected with the seed ``SeedSequence([seed, 1])`` (a stream
    independent of the fitting and held-out rows) and thinned to one state per second (0 and
    1 s of the preset's 2 s runs). The guarantee: a new trajectory of the same excitation lies
    inside ``m +- beta sigma`` (both components) at its kept states with probability at least
    ``1 - delta``. States of the plane off those trajectories, and closed-loop states, are
    other distributions, which the guarantee does not cover.

    Parameters
    ----------
    sc : ObstacleScenario
    model : uncertainty model
        The GP or the cache the GP-robust controller uses.

    Returns
    -------
    dict
        ``beta``, ``chosen_beta`` (``gp_beta``), ``delta``, ``probability``,
        ``n_trajectories``, ``states_per_trajectory``, ``statement``: strict JSON data.
    """
    n_traj = max(CONFORMAL_MIN_TRAJECTORIES, int(np.ceil(1.0 / sc.delta)))
    cal_seed = int(np.random.SeedSequence([sc.seed, 1]).generate_state(1)[0])
    return conformal_calibration(sc, model, n_trajectories=n_traj, seed=cal_seed, delta=sc.delta)


def fit_obstacle_gp(
    sc: ObstacleScenario,
    *,
    timings: dict[str, float] | None = None,
    report: StepProgress | None = None,
) -> tuple[Any, GaussianProcessModel, Any, InputGain | None]:
    """Collect the scenario's data and fit its GP as the study does (the pipeline's steps).

    Returns
    -------
    (held_out, gp, uncertainty, gain)
        The held-out :class:`~safestab.learning.Dataset` (``max(50, Q // 4)`` rows), the
        fitted GP, what the GP-robust controller uses (the GP's
        :class:`~safestab.learning.FastGP` cache when ``n_inducing > 0``, else the GP), and
        the learned :class:`~safestab.learning.InputGain` when ``input_gain = "learned"``
        (the GP then learns ``y - D u``, :func:`~safestab.learning.fit_input_gain`), else
        None. The training rows are ``gp.x_train_``.
    """
    timings = {} if timings is None else timings
    report = report or silent
    t0 = time.perf_counter()
    train, held_out = collect_study_data(sc)
    timings["collect_data"] = time.perf_counter() - t0

    report(f"fitting the GP (Q = {sc.n_samples}, n = 2)", 0.1)
    t0 = time.perf_counter()
    gain = None
    if sc.input_gain == "learned":
        gp, gain = fit_input_gain(
            lambda x, y: fit_study_gp(sc, dataclasses.replace(train, x=x, y=y)),
            train.x, train.u, train.y, seed=sc.seed,
        )  # fmt: skip
    else:
        gp = fit_study_gp(sc, train)
    uncertainty: Any = gp
    if sc.n_inducing > 0:
        # the cache's band provably contains the exact band for beta >= min_beta (1.0)
        uncertainty = FastGP(gp, sc.n_inducing)
    timings["fit_gp"] = time.perf_counter() - t0
    return held_out, gp, uncertainty, gain


def obstacle_controller(
    sc: ObstacleScenario,
    name: str,
    uncertainty: Any = None,
    *,
    limits: bool = False,
    hard: bool = False,
) -> UniversalController | SafetyFilter:
    """The study's controller ``name`` (one of :data:`CONTROLLERS`).

    ``uncertainty`` is used by ``"GP-robust"`` only; ``limits`` adds the input limits;
    ``hard`` gives Theorem 1's formula (used inside the certified sublevel set), else the
    relaxed one with the scenario's slack weight (with limits and the filter, ``hard`` gives
    the filter hard CLF rows, dropped where the box and the CBF leave no room; the study
    never asks for it). With limits and
    ``controller.limit_method = "filter"`` it is a :class:`~safestab.SafetyFilter` solving
    the same problem with the box as constraints (exactly; a CBF is relaxed only where the box
    and the CBF conflict, reported by its ``formula_status``), else a
    :class:`~safestab.UniversalController` that projects its input onto the box (eq. (26)).
    """
    if name not in CONTROLLERS:
        raise ParameterError(f"controller must be one of {list(CONTROLLERS)}, got {name!r}")
    return _controller(sc, name, sc.system(MODEL_OF[name]), uncertainty, limits, hard)


def _controller(sc, name, system, uncertainty, limits, hard):
    """:func:`obstacle_controller` on ``system`` (the model itself or the parametric family)."""
    clf, cbf = sc.certificates()
    if name in GP_CONTROLLERS and uncertainty is None:
        raise ParameterError(f"the {name} controller needs an uncertainty model")
    robust = {"robust_clf_layer": sc.robust_clf_layer} if sc.robust_clf_layer > 0 else {}
    options = {"slack_weight": None if hard else sc.slack_weight, **_params(sc)}

    def build(model: Any, **kwargs: Any) -> Any:
        if not limits:
            return UniversalController(model, clf, cbf, **kwargs)
        u_min, u_max = sc.input_limits()
        return sc.limited_controller(model, clf, cbf, u_min=u_min, u_max=u_max, **kwargs)

    return build_compared(
        name, build, {MODEL_OF[name]: system}, uncertainty=uncertainty, gp_beta=sc.gp_beta,
        robust_options=robust, **options,
    )  # fmt: skip


def study_controller(
    sc: ObstacleScenario, name: str, uncertainty: Any = None, *, limits: bool, hard: bool
) -> tuple[UniversalController | SafetyFilter, dict[str, float] | None]:
    """The study's controller ``name`` and the run-time parameters its closed loop needs.

    The true-model and mismatched-model controllers stand on one parametric model
    (:meth:`~safestab.scenarios.obstacle.ObstacleScenario.model_family`): the same program
    with other data (:func:`~safestab.simulate` reuses the first's compiled loop for a
    controller built alike, and the study gives both the same object). Their inputs are those of
    :func:`obstacle_controller`'s, bit for bit. The GP-robust one is
    :func:`obstacle_controller`'s, with no parameters (None).

    Parameters
    ----------
    sc : ObstacleScenario
    name : str
        One of :data:`CONTROLLERS`.
    uncertainty : uncertainty model or None
        Used by ``"GP-robust"`` only.
    limits, hard : bool
        As in :func:`obstacle_controller`.

    Returns
    -------
    (controller, params)
        ``params`` goes to :func:`~safestab.simulate`'s ``params``.
    """
    if name == GP_ROBUST:
        return obstacle_controller(sc, name, uncertainty, limits=limits, hard=hard), None
    if name not in CONTROLLERS:
        raise ParameterError(f"controller must be one of {list(CONTROLLERS)}, got {name!r}")
    which = MODEL_OF[name]
    return _controller(sc, name, sc.model_family(), None, limits, hard), sc.model_params(which)


def run_obstacle_study(
    scenario: ObstacleScenario,
    *,
    seed: int | None = None,
    progress: StepProgress | None = None,
    n_samples: int | None = None,
    t_final: float | None = None,
) -> ObstacleStudyResult:
    """Run the obstacle study for a scenario.

    Parameters
    ----------
    scenario : ObstacleScenario
    seed : int, optional
        Overrides the scenario's seed (data collection, GP subset).
    progress : callable, optional
        Called as ``progress(message, fraction_done)``.
    n_samples, t_final : optional
        Override ``Q`` and the horizon; checked like the file, recorded in the result.

    Returns
    -------
    ObstacleStudyResult

    Raises
    ------
    ScenarioError
        If an override is invalid; raised before any work.
    """
    report = progress or silent
    sc = with_overrides(scenario, seed=seed, n_samples=n_samples, t_final=t_final)
    true_sys = sc.system("true")
    timings: dict[str, float] = {}
    x0 = sc.start_states()
    v0 = np.asarray(sc.V(x0))
    pset = sc.parallel_set()
    # the true and mismatched models of a setting share one controller (on the parametric
    # model): simulate then reuses the first one's compiled loop for the second, untraced
    shared: dict[tuple[str, bool], Any] = {}

    def controller_of(scn, name, unc, limits, hard) -> tuple[Any, Any]:
        ctrl, params = study_controller(scn, name, unc, limits=limits == "input limits", hard=hard)
        if params is None:
            return ctrl, params
        return shared.setdefault((limits, hard), ctrl), params

    def run(scn, setting, level, unc) -> tuple[ObstacleRun, float]:
        name, limits = setting
        t0 = time.perf_counter()
        # Theorem 1 (2) applies inside the certified sublevel set and without limits
        inside = (v0 < scn.doa_fraction * level) & (limits == "no limits")
        parts = {}
        for hard, sel in ((True, inside), (False, ~inside)):
            if not np.any(sel):
                continue
            ctrl, params = controller_of(scn, name, unc, limits, hard)
            # a shared model runs every start, whatever the selection: the batch, hence the
            # program, is then the same for the true and the mismatched model (their
            # certified sets differ). GP-robust runs its selection only: its GP's products
            # round by the batch's size, and its results stay those of a run on its own.
            run_all = params is not None
            starts = x0 if run_all else x0[sel]
            tr = simulate(
                ctrl, starts, t_final=scn.t_final, dt=scn.dt, plant=true_sys, params=params
            )
            parts[hard] = (sel, tr, run_all)
        return _merge(scn, name, limits, x0, inside, parts, unc), time.perf_counter() - t0

    def model_based(scn: ObstacleScenario) -> tuple[dict, dict, dict]:
        # the true and mismatched models use no data: their verdicts on the parallel set,
        # certified levels and closed loops (each setting's mismatched loop after its true
        # one: it reuses that program)
        verdicts = {c: verdict(scn, c, pset, None) for c in MODEL_BASED}
        levels = {c: doa_level(scn, c, verdicts=verdicts[c]) for c in MODEL_BASED}
        done = {
            (c, lim): run(scn, (c, lim), levels[c], None)
            for lim in LIMIT_SETTINGS
            for c in MODEL_BASED
        }
        return verdicts, levels, done

    report("collecting data", 0.0)
    held_out, gp, uncertainty, gain = fit_obstacle_gp(sc, timings=timings, report=report)
    # the model-based part runs in a thread of its own from here, beside the calibration,
    # the maps and the GP-robust runs (mostly compilation on a first run: JAX releases the
    # GIL while it compiles and runs). Not during the fit: that already uses every core, and
    # a third thread only made both slower.
    background = ThreadPoolExecutor(max_workers=1)
    models_job = background.submit(model_based, sc)
    try:
        # every GP-robust use below (verdicts, maps, controllers) reads sc.system("learned")
        sc = sc.with_learned_gain(gain)
        calibrated = None
        if sc.beta_method == "conformal":
            report("calibrating beta on fresh trajectories", 0.15)
            t0 = time.perf_counter()
            calibrated = calibrate_beta(sc, uncertainty)
            # every GP-robust use below (verdicts, maps, controllers, coverage) reads gp_beta
            sc = sc.replace(gp_beta=calibrated["beta"])
            timings["calibrate_beta"] = time.perf_counter() - t0
        coverage = _coverage(sc, uncertainty, held_out.x, calibrated is not None)
        if calibrated is not None:
            coverage["calibration"] = calibrated
        if isinstance(uncertainty, FastGP):
            coverage["cache"] = _cache_width(gp, uncertainty)
        # the fitted noise std per learned component (with a gain error not learned, D u)
        coverage["noise_mps"] = np.asarray(gp.noise_).tolist()
        if gain is not None:
            coverage["input_gain"] = {
                **gain.as_dict(),
                "true": ((sc.gain_true - sc.gain_nominal) * np.eye(2)).tolist(),
            }
        goal_mean, goal_std = uncertainty.mean_std(jnp.zeros(2))
        coverage["at_goal"] = {  # the model the controller uses, at the goal x = 0
            "mean_mps": np.asarray(goal_mean).tolist(),
            "std_mps": np.asarray(goal_std).tolist(),
            "omega_mps": np.asarray(sc.omega(jnp.zeros(2))).tolist(),
        }

        report("domains of attraction and maps", 0.2)
        t0 = time.perf_counter()
        robust_verdicts = verdict(sc, GP_ROBUST, pset, uncertainty)
        robust_level = doa_level(sc, GP_ROBUST, verdicts=robust_verdicts)
        maps = compatibility_maps(sc, uncertainty, calibrated=calibrated is not None)
        timings["doa_and_maps"] = time.perf_counter() - t0

        report(f"simulating GP-robust, {SIMULATION_THREADS} settings at once", 0.3)
        finished = in_threads(
            lambda lim: run(sc, (GP_ROBUST, lim), robust_level, uncertainty),
            LIMIT_SETTINGS, SIMULATION_THREADS,
            lambda k: report(f"simulated {k} of {len(LIMIT_SETTINGS)} GP-robust settings",
                             0.3 + 0.6 * k / len(LIMIT_SETTINGS)),
        )  # fmt: skip
        report("finishing the true-model and mismatched-model runs", 0.9)
        model_verdicts, model_levels, done = models_job.result()
    except BaseException as exc:
        # on an error above, raise at once (not after the model-based part): that thread
        # finishes on its own and its result is dropped. An error it already raised is
        # named on this one, not lost
        if models_job.done() and not models_job.cancelled():
            other = models_job.exception()
            if other is not None and other is not exc:
                exc.add_note(
                    "the true-model and mismatched-model runs (in another thread) failed "
                    f"too: {type(other).__name__}: {other}"
                )
        raise
    finally:
        background.shutdown(wait=False, cancel_futures=True)
    done.update({(GP_ROBUST, lim): r for lim, r in zip(LIMIT_SETTINGS, finished, strict=True)})
    # in the order of CONTROLLERS: the model-based ones (MODEL_BASED), then GP-robust
    pverd = {**model_verdicts, GP_ROBUST: robust_verdicts}
    doa = {**model_levels, GP_ROBUST: robust_level}
    runs: dict[tuple[str, str], ObstacleRun] = {}
    for setting in [(name, limits) for name in CONTROLLERS for limits in LIMIT_SETTINGS]:
        one, seconds = done[setting]
        runs[setting] = one
        # wall time, with other work running beside it
        timings[f"simulate {setting[0]}, {setting[1]}"] = seconds
    report("done", 1.0)
    return ObstacleStudyResult(
        scenario=sc,
        gp=gp,
        uncertainty=uncertainty,
        coverage=coverage,
        doa=doa,
        runs=runs,
        maps=maps,
        parallel_set=pset,
        parallel_verdicts=pverd,
        timings=timings,
    )


def _merge(sc, name, limits, x0, inside, parts, uncertainty) -> ObstacleRun:
    """Put the compatible-formula and relaxed-formula batches back in start order.

    ``parts`` holds ``(selection, trajectory, run_all)`` per formula: ``run_all`` when the
    trajectory holds every start (its selected ones are kept), else the selection only.
    """
    n = len(x0)
    fields: dict[str, np.ndarray] = {}
    t = None
    for sel, tr, run_all in parts.values():
        t = np.asarray(tr.t)
        for f in ("x", "u", "V", "h", "compatible", "status"):
            arr = np.asarray(getattr(tr, f))
            if f in ("V", "h") and arr.ndim == 3:  # a safety filter's: one CLF, one CBF
                arr = arr[..., 0]
            if f not in fields:
                fields[f] = np.empty((n,) + arr.shape[1:], arr.dtype)
            fields[f][sel] = arr[sel] if run_all else arr
    assert t is not None  # at least one part: x0 is not empty
    outcome = classify_outcomes(fields["x"], fields["h"], sc.dt, sc.ball_radius, sc.rest_speed)
    end = fields["x"][:, -1]
    finite = np.all(np.isfinite(end), -1)
    end_verdict = np.zeros(n, bool)
    if np.any(finite):
        end_verdict[finite] = verdict(sc, name, end[finite], uncertainty)
    return ObstacleRun(
        controller=name,
        limits=limits,
        x0=x0,
        compatible_formula=inside,
        t=t,
        outcome=outcome,
        end_verdict=end_verdict,
        **fields,
    )


def summary(result: ObstacleStudyResult, document: dict[str, Any]) -> Summary:
    """The outcome table and coverage line a person reads after an obstacle run.

    Parameters
    ----------
    result : ObstacleStudyResult
    document : dict
        Its metrics document.

    Returns
    -------
    Summary
    """
    sc = result.scenario
    rows = []
    for (name, limits), run in result.runs.items():
        stuck = run.outcome == "stuck"
        rows.append(
            (
                name,
                limits,
                *(str(int((run.outcome == o).sum())) for o in OUTCOMES),
                f"{float(run.h.min()):.3f}",
                f"{int((~run.end_verdict[stuck]).sum())}/{int(stuck.sum())}",
                f"{result.doa[name]:.3g}",
            )
        )
    cov = result.coverage
    how = (
        f"conformal beta = {cov['beta']:.3g} (chosen {cov['calibration']['chosen_beta']:g}), "
        f"calibrated on {cov['calibration']['n_trajectories']} fresh trajectories; "
        f"stated probability 1 - delta = {cov['stated_probability']:.4f}"
        if cov["beta_method"] == "conformal"
        else f"chosen beta = {cov['beta']:g}; "
        f"stated probability (1 - delta)^2 = {cov['stated_probability']:.4f}"
    )
    limits_how = (
        "the safety filter with the box as constraints"
        if sc.limit_method == "filter"
        else "the relaxed formula's input projected onto the box (eq. (26))"
    )
    line = (
        f"GP held-out coverage: per component "
        f"{[round(float(c), 3) for c in cov['per_component']]}, joint {cov['joint']:.3f}; {how}"
    )
    return Summary(
        title=f"Obstacle study '{sc.name}' ({len(sc.start_states())} starts)",
        columns=(
            "controller",
            "limits",
            *OUTCOMES,
            "min h [m^2]",
            "stuck incompat.",
            "c* [m^2]",
        ),  # fmt: skip
        rows=rows,
        lines=[line, f"input limits +-{sc.input_limit:g} m/s: {limits_how}"],
    )


def _figures(result: ObstacleStudyResult) -> dict[str, Any]:
    from ..plotting import plot_compatibility_maps, plot_obstacle_plane

    return {"": plot_obstacle_plane(result), "_maps": plot_compatibility_maps(result)}


#: The obstacle study's place in the pipeline (:mod:`safestab.scenarios.pipeline`).
STUDY = Study(
    kind="obstacle",
    scenario_type=ObstacleScenario,
    presets=PRESETS,
    load=load_obstacle_scenario,
    run=lambda scenario, progress: run_obstacle_study(scenario, progress=progress),
    figures=_figures,
    summary=summary,
    table_width=130,
    montecarlo=GP_MONTECARLO,
)
