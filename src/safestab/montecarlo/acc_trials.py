"""The ACC Monte Carlo study's pieces: trial draws, data sets, controllers, chunks.

Every piece is a pure function of its arguments (the scenario, the seed, trial indices and a
fitted data set), so the local and the Ray backend call the same functions and get the same
bits.

Randomness: trial ``i`` draws its initial state and lead profile from
``jax.random.fold_in(PRNGKey(seed), i)`` alone; data set ``j`` collects its data with the seed
``SeedSequence([seed, j])``. Trial ``i`` uses data set ``i mod K``.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..controllers import UniversalController
from ..errors import InducingPointsWarning, ParameterError
from ..learning import (
    BatchedUncertainty,
    ExactPosterior,
    GaussianProcessModel,
    Hyperparameters,
    beta_lemma2,
    collect_data,
    condition,
    inducing_cache,
    information_gain,
)
from ..learning.batched import one_blas_thread
from ..scenarios import ACCScenario, MonteCarloSpec
from .loop import trial_function

__all__ = [
    "CONFORMAL_MIN_TRAJECTORIES",
    "DataSetModel",
    "calibration_draw",
    "conformal_beta_function",
    "draw_trials",
    "fit_dataset",
    "lead_acceleration",
    "run_chunk",
]

#: Fewest calibration trajectories of the conformal beta (more when ``1 / delta`` is larger).
CONFORMAL_MIN_TRAJECTORIES = 100

_GP_CONTROLLERS = ("GP mean", "GP-robust", "GP-robust Lemma 2", "GP-robust conformal")


def conformal_beta_function() -> Any:
    """``safestab.learning.conformal_beta`` (issue 14), or ``None`` where it is missing.

    The ``"GP-robust conformal"`` controller is enabled exactly when this returns a function;
    it is called as ``conformal_beta(model, x_cal, omega_cal, delta, groups=trajectory)`` with
    the data set's cache (``mean_std``, one state), the states of :func:`calibration_draw`
    (N, n), their true ``omega`` (N, n) and their trajectory labels, and returns a report
    whose ``beta`` has shape (n,).
    """
    import safestab.learning as learning

    return getattr(learning, "conformal_beta", None)


def draw_trials(
    scenario: ACCScenario, spec: MonteCarloSpec, seed: int, indices: Any
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Initial states and lead profiles of the trials ``indices``, from ``(seed, i)`` alone.

    Parameters
    ----------
    scenario, spec : the study's settings
    seed : int
    indices : int array of shape (B,)

    Returns
    -------
    x0 : array of shape (B, 3)
    params : dict
        ``"ends"`` (B, S): segment end times, s; ``"acc"`` (B, S): lead accelerations, m/s^2.
    """
    return _draw_fn(scenario, spec)(jnp.asarray(seed, jnp.uint32), jnp.asarray(indices))


@functools.lru_cache(maxsize=8)
def _draw_fn(scenario: ACCScenario, spec: MonteCarloSpec) -> Any:
    profile = np.asarray(scenario.lead_profile, float).reshape(-1, 2)
    g = scenario.gravity

    def one(seed, i):
        key = jax.random.fold_in(jax.random.PRNGKey(seed), i)
        k_x, k_d, k_a = jax.random.split(key, 3)
        if spec.initial_distribution == "box":
            low, high = jnp.asarray(spec.initial_low), jnp.asarray(spec.initial_high)
            x0 = jax.random.uniform(k_x, (3,), minval=low, maxval=high)
        elif spec.initial_distribution == "normal":
            std = jnp.asarray(spec.initial_std)
            x0 = jnp.asarray(spec.initial_mean) + std * jax.random.normal(k_x, (3,))
        else:
            x0 = jnp.asarray(scenario.x0, float)
        if spec.lead_kind == "random":
            s = spec.lead_segments
            durations = jax.random.uniform(
                k_d, (s,), minval=spec.lead_duration_min, maxval=spec.lead_duration_max
            )
            acc = jax.random.uniform(
                k_a, (s,), minval=-spec.lead_decel_max * g, maxval=spec.lead_accel_max * g
            )
            ends = jnp.cumsum(durations)
        else:
            ends, acc = jnp.asarray(profile[:, 0]), jnp.asarray(profile[:, 1])
        return x0, {"ends": ends, "acc": acc}

    return jax.jit(jax.vmap(one, in_axes=(None, 0)))


def lead_acceleration(t: jax.Array, x: jax.Array, params: dict[str, jax.Array]) -> jax.Array:
    """``e(t, x) = (0, a_L, 0)``: the segment containing ``t``, 0 after the last.

    Segments are ``t <= ends[0]``, then ``(ends[j-1], ends[j]]`` (the scenario file's
    convention). A lead that has stopped (``v_l <= 0``) does not brake further: it stops
    rather than reverses (a choice; docs/montecarlo.md).
    """
    ends, acc = params["ends"], params["acc"]
    # the segment index is the number of ends before t (ends increase: the scenario file's
    # profile is validated so, random ones are sums of positive durations); a count fuses
    # with the rest, where searchsorted was a while loop per RK4 stage
    j = jnp.sum(ends < t)
    a = jnp.where(j < ends.shape[0], acc[jnp.minimum(j, ends.shape[0] - 1)], 0.0)
    a = jnp.where((x[1] <= 0.0) & (a < 0.0), 0.0, a)
    return jnp.array([0.0, 1.0, 0.0]) * a


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
    """

    index: int
    hyper: Hyperparameters
    cache: Any
    betas: dict[str, np.ndarray]
    information_gain: np.ndarray
    held_out_coverage: dict[str, float]
    cache_warnings: tuple[str, ...] = ()


def _collect(scenario: ACCScenario, spec: MonteCarloSpec, n_samples: int, seed: int) -> Any:
    """``collect_data`` with the scenario's true and nominal ACC and excitation settings."""
    span = scenario.excitation_limit * scenario.mass * scenario.gravity / scenario.input_scale
    noise = scenario.noise_std if spec.noise_std is None else spec.noise_std
    return collect_data(
        scenario.system("true"), scenario.system("nominal"),
        x0=(scenario.x0_low, scenario.x0_high), u_low=-span, u_high=span,
        n_samples=n_samples, rate=scenario.sample_rate, horizon=scenario.sample_horizon,
        noise_std=noise, seed=seed,
    )  # fmt: skip


def calibration_draw(scenario: ACCScenario, spec: MonteCarloSpec, seed: int, index: int) -> Any:
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
    per_traj = max(1, int(round(scenario.sample_horizon * scenario.sample_rate)))
    n_traj = max(CONFORMAL_MIN_TRAJECTORIES, int(np.ceil(1.0 / spec.delta)))
    cal_seed = int(np.random.SeedSequence([seed, index, 1]).generate_state(1)[0])
    cal = _collect(scenario, spec, n_traj * per_traj, cal_seed)
    stride = max(1, int(round(scenario.sample_rate)))
    return cal.take(np.arange(0, len(cal), stride))


def dataset_draw(scenario: ACCScenario, spec: MonteCarloSpec, seed: int, index: int) -> Any:
    """The rows of data set ``index``: ``Q`` fitting rows, then ``max(50, Q // 4)`` held out.

    Drawn with the seed ``SeedSequence([seed, index])`` (:func:`fit_dataset` fits on it).

    Returns
    -------
    Dataset
    """
    data_seed = int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
    q = scenario.n_samples
    return _collect(scenario, spec, q + max(50, q // 4), data_seed)


def fit_dataset(
    scenario: ACCScenario,
    spec: MonteCarloSpec,
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
        return _fit_dataset(scenario, spec, seed, index, hyper)


def _fit_dataset(scenario, spec, seed, index, hyper):
    data_seed = int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
    q = scenario.n_samples
    data = dataset_draw(scenario, spec, seed, index)
    x, y, x_test = data.x[:q], data.y[:q], data.x[q:]
    if hyper is None:
        gp = GaussianProcessModel(kernel=scenario.kernel)  # type: ignore[arg-type]
        gp.fit(x, y, hyper_subset=min(scenario.hyper_subset, q), seed=data_seed)
        hyper = Hyperparameters.from_model(gp)
    else:
        gp = condition(hyper, x, y, seed=data_seed)
    gain = information_gain(gp)
    n, comps = hyper.n_states, list(hyper.components)

    def per_state(b):
        out = np.zeros(n)
        out[comps] = b
        return out

    betas = {
        "GP mean": per_state(0.0),
        "GP-robust": per_state(scenario.gp_beta),
        "GP-robust Lemma 2": per_state(beta_lemma2(spec.rkhs_norm, gain, q, spec.delta)),
    }
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InducingPointsWarning)
        cache: Any = (
            inducing_cache(gp, spec.n_inducing)
            if spec.gp == "fast"
            else ExactPosterior.from_model(gp)
        )
    notes = []
    for w in caught:  # a needlessly wide band is recorded with the data set (and reported)
        if issubclass(w.category, InducingPointsWarning):
            notes.append(str(w.message))
        else:
            warnings.warn(w.message, w.category, stacklevel=2)
    del gp  # the (k, Q, Q) factor is not shipped with the data set
    batch = jax.jit(cache.mean_std_batch)
    if "GP-robust conformal" in spec.controllers:
        conformal = conformal_beta_function()
        if conformal is None:
            raise ParameterError(
                "the controller 'GP-robust conformal' needs safestab.learning.conformal_beta "
                "(issue 14), which this installation does not provide"
            )
        cal = calibration_draw(scenario, spec, seed, index)
        omega_cal = np.asarray(scenario.omega(cal.x))
        report = conformal(
            BatchedUncertainty(cache), cal.x, omega_cal, spec.delta, groups=cal.trajectory
        )
        betas["GP-robust conformal"] = np.asarray(getattr(report, "beta", report), float)
    omega_test = np.asarray(scenario.omega(x_test))
    mean, std = (np.asarray(v) for v in batch(jnp.asarray(x_test)))
    coverage = {
        name: float(np.mean(np.all(np.abs(omega_test - mean) <= b * std, axis=1)))
        for name, b in betas.items()
    }
    cache = jax.tree_util.tree_map(np.asarray, cache)
    return DataSetModel(index, hyper, cache, betas, np.asarray(gain), coverage, tuple(notes))


@functools.lru_cache(maxsize=8)
def _compiled_chunk(scenario: ACCScenario, spec: MonteCarloSpec) -> Any:
    """The jitted chunk runner; cached per process so each worker compiles once per shape."""
    true_sys, nominal = scenario.system("true"), scenario.system("nominal")
    clf, cbf = scenario.certificates()
    u_min, u_max = scenario.input_limits()
    common: dict[str, Any] = dict(
        kappa=scenario.kappa, rho=scenario.rho, phi=scenario.phi, varphi=scenario.varphi,
        slack_weight=scenario.slack_weight, u_min=u_min, u_max=u_max,
    )  # fmt: skip
    n_steps = int(round(scenario.t_final / scenario.dt))

    def omega(x, params):
        return scenario.omega(x)

    def chunk(cache, betas, x0, params):
        model = BatchedUncertainty(cache)
        ctrls, checks = [], []
        for name in spec.controllers:
            if name == "true model":
                ctrls.append(UniversalController(true_sys, clf, cbf, **common))
                checks.append(None)
            elif name == "mismatched model":
                ctrls.append(UniversalController(nominal, clf, cbf, **common))
                checks.append(None)
            else:
                beta = betas[name]
                ctrls.append(
                    UniversalController(
                        nominal, clf, cbf, uncertainty=model, gp_beta=beta, **common
                    )
                )
                checks.append((model, beta))
        run = trial_function(
            ctrls, plant=true_sys, n_steps=n_steps, dt=scenario.dt,
            exogenous=lead_acceleration, omega=omega, lemma2=checks,
        )  # fmt: skip
        return jax.vmap(run)(x0, params)

    return jax.jit(chunk)


def run_chunk(
    scenario: ACCScenario,
    spec: MonteCarloSpec,
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
    args = _chunk_args(scenario, spec, model, seed, indices, pad_to)
    out = _compiled_chunk(scenario, spec)(*args)
    return {k: np.asarray(v)[:b] for k, v in out.items()}


def compile_chunk(
    scenario: ACCScenario,
    spec: MonteCarloSpec,
    model: DataSetModel,
    seed: int,
    indices: Any,
    pad_to: int | None = None,
) -> None:
    """Compile the loop :func:`run_chunk` runs for these arguments, without running it.

    Later chunks of the same shapes reuse the compiled loop, so they can all start at once
    (the local backend's threads) instead of waiting for a first chunk that compiles.
    """
    _compiled_chunk(scenario, spec).lower(
        *_chunk_args(scenario, spec, model, seed, indices, pad_to)
    ).compile()


def _chunk_args(scenario, spec, model, seed, indices, pad_to):
    idx = np.asarray(indices, dtype=np.int64)
    b = idx.size
    if pad_to is not None and pad_to > b:
        idx = np.concatenate([idx, np.full(pad_to - b, idx[0])])
    x0, params = draw_trials(scenario, spec, seed, idx)
    betas = {k: jnp.asarray(v) for k, v in model.betas.items() if k in spec.controllers}
    return model.cache, betas, x0, params
