"""The Monte Carlo study's pieces for any scenario: data sets, controllers, chunks.

Every piece is a pure function of its arguments (the trial study of
:mod:`~safestab.montecarlo.protocol`, the seed, trial indices and a fitted data set), so the
local and the Ray backend call the same functions and get the same bits. The scenario's side
(its systems, how it collects data, how a trial draws its initial state and exogenous data)
is the study's: :mod:`safestab.scenarios.trial_studies` for the ACC and the obstacle.

Randomness: trial ``i`` draws its initial state and per-trial data (the ACC's lead profile)
from ``jax.random.fold_in(PRNGKey(seed), i)`` alone; data set ``j`` collects its data with the
seed ``SeedSequence([seed, j])``. Trial ``i`` uses data set ``i mod K``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..controller_names import (
    GP_CONTROLLERS,
    GP_MEAN,
    GP_ROBUST,
    GP_ROBUST_CONFORMAL,
    GP_ROBUST_LEMMA2,
    build_compared,
)
from ..controllers import UniversalController
from ..errors import ParameterError
from ..learning import (
    BatchedUncertainty,
    ExactPosterior,
    FastGP,
    GaussianProcessModel,
    Hyperparameters,
    beta_lemma2,
    condition,
    information_gain,
)
from ..learning.batched import InducingCache, one_blas_thread
from ..learning.input_gain import estimate_input_gain, fit_input_gain, with_input_gain
from .loop import trial_function
from .protocol import TrialStudy

__all__ = [
    "CONFORMAL_MIN_TRAJECTORIES",
    "DataSetModel",
    "calibration_draw",
    "compile_chunk",
    "conformal_beta_function",
    "dataset_draw",
    "fit_dataset",
    "run_chunk",
]

#: Fewest calibration trajectories of the conformal beta (more when ``1 / delta`` is larger).
CONFORMAL_MIN_TRAJECTORIES = 100


def conformal_beta_function() -> Any:
    """``safestab.learning.conformal_beta`` (the split conformal beta), or ``None``.

    The ``"GP-robust conformal"`` controller is enabled exactly when this returns a function;
    it is called as ``conformal_beta(model, x_cal, omega_cal, delta, groups=trajectory)`` with
    the data set's cache (``mean_std``, one state), the states of :func:`calibration_draw`
    (N, n), their true ``omega`` (N, n) and their trajectory labels, and returns a report
    whose ``beta`` has shape (n,).
    """
    import safestab.learning as learning

    return getattr(learning, "conformal_beta", None)


@dataclasses.dataclass(frozen=True)
class DataSetModel:
    """One fitted data set: the GP cache and the betas of the GP controllers (plain arrays).

    Attributes
    ----------
    index : int
    hyper : Hyperparameters
    cache : InducingCache or ExactPosterior
    betas : dict of str to array of shape (n,)
        Per GP controller.
    information_gain : array of shape (C,)
    held_out_coverage : dict of str to float
        Per GP controller, fraction of held-out states inside every band (true omega).
    cache_warnings : tuple of str
        FastGP's :class:`~safestab.errors.InducingPointsWarning` messages for this data set
        (the band is valid but needlessly wide); :func:`run_montecarlo` repeats them.
    input_gain : array of shape (n, m) or None
        The learned input-matrix error ``D`` of this data set when the study's
        ``gp_settings()["input_gain"]`` is ``"learned"`` (the GP controllers then use
        ``g + D``, :func:`~safestab.learning.fit_input_gain`); None otherwise.
    std_over_exact : array of shape (C,) or None
        Per learned component, the cache's std over the exact posterior std at the training
        inputs (median over FastGP's sample of 128 of them: its ``std_over_exact_``, which
        it computes for its stopping rule and warning anyway); above
        :data:`~safestab.learning.STD_RATIO_WARN` the data set's ``cache_warnings`` name the
        component. None for the exact posterior (``gp = "exact"``).
    """

    index: int
    hyper: Hyperparameters
    cache: Any
    betas: dict[str, np.ndarray]
    information_gain: np.ndarray
    held_out_coverage: dict[str, float]
    cache_warnings: tuple[str, ...] = ()
    input_gain: np.ndarray | None = None
    std_over_exact: np.ndarray | None = None


def calibration_draw(study: TrialStudy, seed: int, index: int) -> Any:
    """The conformal calibration states of data set ``index``: fresh trajectories.

    Drawn with the seed ``SeedSequence([seed, index, 1])``, a stream independent of the data
    set's own (``SeedSequence([seed, index])``: fitting rows and held-out rows), so the
    calibration units are used neither to fit the GP nor to evaluate it (split conformal).
    ``max(CONFORMAL_MIN_TRAJECTORIES, ceil(1 / delta))`` trajectories of the data set's
    horizon, thinned to one state per second; each trajectory is one calibration unit.

    Returns
    -------
    Dataset
        With ``trajectory`` labels.
    """
    per_traj, stride = study.calibration_shape()
    n_traj = max(CONFORMAL_MIN_TRAJECTORIES, int(np.ceil(1.0 / study.spec.delta)))
    cal_seed = int(np.random.SeedSequence([seed, index, 1]).generate_state(1)[0])
    return study.collect(n_traj * per_traj, cal_seed).thin(stride)


def dataset_draw(study: TrialStudy, seed: int, index: int) -> Any:
    """The rows of data set ``index``: ``Q`` fitting rows, then ``max(50, Q // 4)`` held out.

    Drawn with the seed ``SeedSequence([seed, index])`` (:func:`fit_dataset` fits on it).

    Returns
    -------
    Dataset
    """
    data_seed = int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
    q = study.gp_settings()["n_samples"]
    return study.collect(q + max(50, q // 4), data_seed)


def fit_dataset(
    study: TrialStudy,
    seed: int,
    index: int,
    hyper: Hyperparameters | None = None,
) -> DataSetModel:
    """Collect data set ``index``, fit (or condition) its GP and build the controllers' betas.

    With ``hyper`` given (``hyperparameters = "reuse"``), the GP is conditioned on the new
    data with these hyperparameters; otherwise they are fitted (``hyper_subset`` rows). The
    data set's draw (seed ``SeedSequence([seed, index])``) gives ``Q`` fitting rows and
    ``max(50, Q // 4)`` held-out rows (``held_out_coverage``); the conformal beta, when asked
    for, is calibrated on a third, independent draw (:func:`calibration_draw`).
    """
    with one_blas_thread():  # faster on a busy machine, and the same bits in any worker
        return _fit_dataset(study, seed, index, hyper)


def _fit_dataset(study, seed, index, hyper):
    spec, gp_settings = study.spec, study.gp_settings()
    data_seed = int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
    q = gp_settings["n_samples"]
    data = dataset_draw(study, seed, index)
    x, y, u, x_test = data.x[:q], data.y[:q], data.u[:q], data.x[q:]
    # optional key of the protocol (a study written before it trusts its nominal g)
    learn_gain = gp_settings.get("input_gain", "nominal") == "learned"
    input_gain = None
    if hyper is None:

        def fit(x, y):
            gp = GaussianProcessModel(kernel=gp_settings["kernel"])
            return gp.fit(x, y, hyper_subset=min(gp_settings["hyper_subset"], q), seed=data_seed)

        if learn_gain:
            gp, found = fit_input_gain(fit, x, u, y, seed=data_seed)
            input_gain = found.matrix
        else:
            gp = fit(x, y)
        hyper = Hyperparameters.from_model(gp)
    else:
        gp = condition(hyper, x, y, seed=data_seed)
        if learn_gain:
            # K does not depend on y: this is fit_input_gain's estimate with these
            # hyperparameters, and the GP of y - D u
            input_gain = estimate_input_gain(gp, u).matrix
            gp = condition(hyper, x, y - u @ input_gain.T, seed=data_seed)
    gain = information_gain(gp)
    n, comps = hyper.n_states, list(hyper.components)

    def per_state(b):
        out = np.zeros(n)
        out[comps] = b
        return out

    betas = {
        GP_MEAN: per_state(0.0),
        GP_ROBUST: per_state(gp_settings["gp_beta"]),
        GP_ROBUST_LEMMA2: per_state(beta_lemma2(spec.rkhs_norm, gain, q, spec.delta)),
    }
    notes: tuple[str, ...] = ()
    ratio = None
    if spec.gp == "fast":
        # warn=False: the messages are kept with the data set (and reported once by the
        # runner); warnings.catch_warnings would swap process-wide state under the runner's
        # threads
        fast = FastGP(gp, spec.n_inducing, warn=False)
        cache: Any = InducingCache.from_fastgp(fast)
        notes = fast.width_warnings_
        ratio = np.asarray(fast.std_over_exact_, float)
    else:
        cache = ExactPosterior.from_model(gp)
    del gp  # the (k, Q, Q) factor is not shipped with the data set
    if GP_ROBUST_CONFORMAL in spec.controllers:
        conformal = conformal_beta_function()
        if conformal is None:
            raise ParameterError(
                f"the controller {GP_ROBUST_CONFORMAL!r} needs safestab.learning.conformal_beta "
                "(the split conformal beta), which this installation does not provide"
            )
        cal = calibration_draw(study, seed, index)
        omega_cal = np.asarray(study.omega(cal.x))
        report = conformal(
            BatchedUncertainty(cache), cal.x, omega_cal, spec.delta, groups=cal.trajectory
        )
        betas[GP_ROBUST_CONFORMAL] = np.asarray(getattr(report, "beta", report), float)
    omega_test = np.asarray(study.omega(x_test))
    mean, std = (np.asarray(v) for v in BatchedUncertainty(cache).mean_std_batch(x_test))
    coverage = {
        name: float(np.mean(np.all(np.abs(omega_test - mean) <= b * std, axis=1)))
        for name, b in betas.items()
    }
    cache = jax.tree_util.tree_map(np.asarray, cache)
    return DataSetModel(
        index, hyper, cache, betas, np.asarray(gain), coverage, notes, input_gain, ratio
    )


@functools.partial(jax.jit, static_argnames=("study",))
def _chunk(study: TrialStudy, cache, betas, input_gain, x0, params) -> dict[str, jax.Array]:
    """One chunk of trials for every compared controller: one program per study.

    A module-level jitted function (no cache of ours): the study is its static argument
    (hashable, frozen), the data set's GP cache, betas and input gain and the trials' draws
    are its arguments, so every data set and chunk of one shape runs the program compiled
    for the first, in every thread of the process.
    """
    spec = study.spec
    true_sys, nominal = study.systems()
    clf, cbf = study.certificates()
    common = study.controller_options()
    # optional member: extra arguments of the GP-robust controllers only (docs/montecarlo.md)
    robust = study.robust_options() if hasattr(study, "robust_options") else {}
    # optional member: the controller's class (default: UniversalController)
    build = getattr(study, "build_controller", UniversalController)

    def omega(x, params):
        return study.omega(x)

    model = BatchedUncertainty(cache)
    # the GP controllers' model: the nominal one, with the learned input gain if any
    learned = nominal if input_gain is None else with_input_gain(nominal, input_gain)
    models = {"true": true_sys, "nominal": nominal, "learned": learned}

    def make(system: Any, **options: Any) -> Any:
        return build(system, clf, cbf, **options)

    ctrls, checks = [], []
    for name in spec.controllers:
        uses_gp = name in GP_CONTROLLERS
        beta = betas[name] if uses_gp else None
        ctrls.append(
            build_compared(name, make, models, uncertainty=model if uses_gp else None,
                           gp_beta=beta, robust_options=robust, **common)
        )  # fmt: skip
        checks.append((model, beta) if uses_gp else None)
    # the reference of mean_input_gap: the true-model controller (price_metrics only)
    ref = build(true_sys, clf, cbf, **common) if spec.price_metrics else None
    run = trial_function(
        ctrls, plant=true_sys, n_steps=study.n_steps, dt=study.dt,
        exogenous=study.exogenous, omega=omega, lemma2=checks, reference=ref,
        substeps=spec.substeps,
    )  # fmt: skip
    return jax.vmap(run)(x0, params)


def run_chunk(
    study: TrialStudy,
    model: DataSetModel,
    seed: int,
    indices: Any,
    pad_to: int | None = None,
) -> dict[str, np.ndarray]:
    """Run the trials ``indices`` (all of data set ``model``) for every controller.

    Parameters
    ----------
    indices : int array of shape (B,)
    pad_to : int, optional
        Pad the batch to this size (with copies of its first trial, dropped afterwards), so
        every chunk has one shape and compiles once.

    Returns
    -------
    dict of str to array of shape (B, C)
        The records of :data:`~safestab.montecarlo.loop.RECORD_FIELDS`.
    """
    b = np.size(indices)
    args = _chunk_args(study, model, seed, indices, pad_to)
    out = _chunk(study, *args)
    return {k: np.asarray(v)[:b] for k, v in out.items()}


def compile_chunk(
    study: TrialStudy,
    model: DataSetModel,
    seed: int,
    indices: Any,
    pad_to: int | None = None,
) -> None:
    """Compile the loop :func:`run_chunk` runs for these arguments, without running it.

    Later chunks of the same shapes reuse the compiled loop, so they can all start at once
    (the local backend's threads) instead of waiting for a first chunk that compiles.
    """
    _chunk.lower(study, *_chunk_args(study, model, seed, indices, pad_to)).compile()


def _chunk_args(study, model, seed, indices, pad_to):
    idx = np.asarray(indices, dtype=np.int64)
    b = idx.size
    if pad_to is not None and pad_to > b:
        idx = np.concatenate([idx, np.full(pad_to - b, idx[0])])
    x0, params = study.draw_trials(seed, idx)
    betas = {k: jnp.asarray(v) for k, v in model.betas.items() if k in study.spec.controllers}
    gain = None if model.input_gain is None else jnp.asarray(model.input_gain)
    return model.cache, betas, gain, x0, params
