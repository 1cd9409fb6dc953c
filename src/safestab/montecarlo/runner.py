"""Run a Monte Carlo study on one machine or on a Ray cluster.

The work is a list of tasks: one per data set (collect data, fit or condition the GP) and one
per chunk of trials of a data set. The local backend runs them in this process; the Ray
backend sends them to a cluster as Ray tasks. Both call the same pure functions
(:mod:`safestab.montecarlo.trials`) with the same chunk shapes, so their results are
identical, bit for bit, and so are results for any ``chunk_size``.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from .._batching import in_threads
from .._cache import child_cache_environment, compilation_cache_dir
from .._xla_flags import xla_flag_environment
from ..controller_names import GP_ROBUST_CONFORMAL
from ..errors import InducingPointsWarning, ParameterError
from ..learning._fit_cache import fit_cache_dir
from ..learning.batched import one_blas_thread
from ..scenarios import MonteCarloSpec
from .loop import RECORD_FIELDS
from .protocol import TrialStudy
from .trials import (
    DataSetModel,
    compile_chunk,
    conformal_beta_function,
    fit_dataset,
    run_chunk,
)

__all__ = ["BACKENDS", "MonteCarloRun", "plan_chunks", "run_montecarlo", "start_ray"]

BACKENDS = ("local", "ray")
#: Called after each finished chunk as ``progress(chunks_done, chunks_total)``.
CountProgress = Callable[[int, int], None]


@dataclasses.dataclass
class MonteCarloRun:
    """The raw outcome of a study: per-trial records and the data sets.

    Attributes
    ----------
    scenario : object
        The scenario (ACC, obstacle or any with ``trial_study``).
    study : TrialStudy
        The scenario's trial study for ``spec`` (what the trials ran).
    spec : MonteCarloSpec
    seed : int
    controllers : tuple of str
    records : dict of str to array of shape (N, C)
        Trial ``i`` is row ``i``; keys :data:`~safestab.montecarlo.loop.RECORD_FIELDS`.
    dataset_index : int array of shape (N,)
        The data set of each trial (``i mod K``).
    datasets : list of DataSetModel
    backend : str
    timings : dict of str to float
        Wall-clock seconds: ``"datasets"``, ``"trials"``, ``"total"``.
    """

    scenario: Any
    study: TrialStudy
    spec: MonteCarloSpec
    seed: int
    controllers: tuple[str, ...]
    records: dict[str, np.ndarray]
    dataset_index: np.ndarray
    datasets: list[DataSetModel]
    backend: str
    timings: dict[str, float]


def plan_chunks(n_trials: int, n_datasets: int, chunk_size: int) -> list[tuple[int, np.ndarray]]:
    """``(data set, trial indices)`` per chunk: trial ``i`` belongs to data set ``i mod K``."""
    chunks = []
    for j in range(n_datasets):
        idx = np.arange(j, n_trials, n_datasets)
        for start in range(0, idx.size, chunk_size):
            chunks.append((j, idx[start : start + chunk_size]))
    return chunks


def _check(
    scenario: Any, spec: Any, trials: int, datasets: int, seed: int, backend: str, workers: Any
) -> None:
    if not callable(getattr(scenario, "trial_study", None)):
        raise ParameterError(
            "scenario must provide trial_study(spec) (the Monte Carlo protocol, "
            "safestab.montecarlo.protocol.TrialStudy: the ACC and obstacle scenarios do), got "
            f"{type(scenario).__name__}"
        )
    if not isinstance(spec, MonteCarloSpec):
        raise ParameterError(f"spec must be a MonteCarloSpec, got {type(spec).__name__}")
    for name, value, low in (("trials", trials, 1), ("datasets", datasets, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            raise ParameterError(f"{name} must be an integer >= {low}, got {value!r}")
    if seed > 2**32 - 1:
        raise ParameterError(f"seed must be <= 2**32 - 1 (a JAX key word), got {seed!r}")
    if datasets > trials:
        raise ParameterError(
            f"datasets must be <= trials (each data set needs a trial), got datasets={datasets} "
            f"and trials={trials}"
        )
    if backend not in BACKENDS:
        raise ParameterError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int | np.integer) or workers < 1
    ):
        raise ParameterError(f"workers must be an integer >= 1 or None, got {workers!r}")
    if GP_ROBUST_CONFORMAL in spec.controllers and conformal_beta_function() is None:
        raise ParameterError(
            f"the controller {GP_ROBUST_CONFORMAL!r} needs safestab.learning.conformal_beta "
            "(the split conformal beta), which this installation does not provide; remove it from "
            "montecarlo.controllers"
        )


def run_montecarlo(
    scenario: Any,
    *,
    trials: int | None = None,
    datasets: int | None = None,
    seed: int = 0,
    backend: str = "local",
    spec: MonteCarloSpec | None = None,
    chunk_size: int | None = None,
    address: str | None = None,
    progress: CountProgress | None = None,
    workers: int | None = None,
    dataset_progress: CountProgress | None = None,
) -> MonteCarloRun:
    """Run ``trials`` closed loops of every controller over ``datasets`` fitted GPs.

    Parameters
    ----------
    scenario : ACCScenario, ObstacleScenario or any scenario with ``trial_study(spec)``
        Its trial study (:class:`~safestab.montecarlo.protocol.TrialStudy`) gives the
        systems, certificates, data collection and trial draws.
    trials, datasets : int, optional
        ``N`` and ``K``; default from the spec.
    seed : int
        Trial ``i`` depends on ``(seed, i)`` only, data set ``j`` on ``(seed, j)``.
    backend : {"local", "ray"}
    spec : MonteCarloSpec, optional
        Defaults to the scenario's ``[montecarlo]`` table, or :class:`MonteCarloSpec()`.
    chunk_size : int, optional
        Overrides the spec's; results do not depend on it.
    address : str, optional
        Ray cluster address; defaults to ``RAY_ADDRESS``, else a local cluster is started.
    progress : callable, optional
        ``progress(chunks_done, chunks_total)``: after each chunk (local backend), after each
        task's ``workers`` chunks (Ray).
    dataset_progress : callable, optional
        ``dataset_progress(sets_done, sets_total)``: after each fitted data set.
    workers : int, optional
        Chunks run at once in threads of one process (XLA releases the GIL); the loop is
        compiled first, then every chunk runs in the threads. Local backend: threads of this
        process; default 2 where the machine has 2 or more CPUs, else 1 (on the 2-core
        development machine two chunks at once took 0.73 of the time of two in turn). Ray
        backend: each task runs ``workers`` chunks in threads of its worker process and asks
        for ``workers`` CPUs, so a machine compiles the loop once, not once per CPU; default
        the CPUs of the cluster's smallest node. Results do not depend on it.

    Returns
    -------
    MonteCarloRun

    Raises
    ------
    ParameterError
        For a bad count, seed or backend, ``datasets > trials``, a controller whose beta
        cannot be computed here, or (Ray) more ``workers`` than the largest node has CPUs;
        raised before any data set or trial (Ray is started or connected first for the
        last).
    ImportError
        For ``backend="ray"`` without Ray installed (``pip install "safestab[ray]"``).
    """
    spec = spec or getattr(scenario, "montecarlo", None) or MonteCarloSpec()
    trials = spec.trials if trials is None else trials
    datasets = spec.datasets if datasets is None else datasets
    if chunk_size is not None:
        spec = spec.replace(chunk_size=chunk_size)
    _check(scenario, spec, trials, datasets, seed, backend, workers)
    study = scenario.trial_study(spec)
    if not isinstance(study, TrialStudy):
        raise ParameterError(
            f"{type(scenario).__name__}.trial_study(spec) must return a TrialStudy "
            f"(safestab.montecarlo.protocol), got {type(study).__name__}"
        )
    if study.spec != spec:
        raise ParameterError(
            f"{type(scenario).__name__}.trial_study(spec) must keep the spec it was given "
            "(the runner plans the chunks and the record columns from it)"
        )
    chunks = plan_chunks(trials, datasets, spec.chunk_size)
    pad = min(spec.chunk_size, -(-trials // datasets))
    report = progress or (lambda done, total: None)
    report_sets = dataset_progress or (lambda done, total: None)
    t0 = time.perf_counter()
    if backend == "local":
        if workers is None:
            workers = 2 if (os.cpu_count() or 1) >= 2 else 1
        models, results, t_data = _local(
            study, seed, datasets, chunks, pad, report, report_sets, int(workers)
        )
    else:
        models, results, t_data = _ray(
            study, seed, datasets, chunks, pad, report, report_sets, address,
            None if workers is None else int(workers),
        )  # fmt: skip
    t_total = time.perf_counter() - t0
    wide = [m.index for m in models if m.cache_warnings]
    if wide:
        warnings.warn(
            f"data sets {wide}: {next(m for m in models if m.cache_warnings).cache_warnings[0]} "
            "(the band still contains "
            "the exact band; messages per data set in the metrics JSON, cache_warnings)",
            InducingPointsWarning,
            stacklevel=2,
        )
    records = {k: np.empty((trials, len(spec.controllers)), dtype=results[0][k].dtype)
               for k in RECORD_FIELDS}  # fmt: skip
    for (_, idx), res in zip(chunks, results, strict=True):
        for k in RECORD_FIELDS:
            records[k][idx] = res[k]
    return MonteCarloRun(
        scenario=scenario, study=study, spec=spec, seed=seed, controllers=tuple(spec.controllers),
        records=records, dataset_index=np.arange(trials) % datasets, datasets=models,
        backend=backend,
        timings={"datasets": t_data, "trials": t_total - t_data, "total": t_total},
    )  # fmt: skip


def _local(study, seed, datasets, chunks, pad, report, report_sets, workers):
    t0 = time.perf_counter()
    # one BLAS thread for the whole phase (threadpoolctl's limit is process-wide: set once
    # here, it is not undone by one thread's fit_dataset while another's runs)
    with one_blas_thread():
        first = fit_dataset(study, seed, 0)
        report_sets(1, datasets)
        hyper = first.hyper if study.spec.hyperparameters == "reuse" else None
        models = [first, *in_threads(
            lambda j: fit_dataset(study, seed, j, hyper), range(1, datasets), workers,
            lambda done: report_sets(done + 1, datasets),
        )]  # fmt: skip
    t_data = time.perf_counter() - t0
    results = _run_chunks(study, seed, chunks, models, pad, workers, report)
    return models, results, t_data


def _run_chunks(study, seed, chunks, models, pad, workers, report):
    """The records of each of ``chunks``, in order, ``workers`` chunks at once in threads.

    ``chunks`` holds ``(data set, indices)`` pairs; ``models[j]`` is data set ``j``'s model.
    """

    def run(chunk: tuple[int, np.ndarray]) -> dict[str, np.ndarray]:
        j, idx = chunk
        return run_chunk(study, models[j], seed, idx, pad_to=pad)

    if workers > 1 and len(chunks) > 1:
        # compile the loop first (in this thread), so every chunk, the first included, can
        # run in the threads; a data set whose cache has other shapes compiles on its first
        # chunk
        j0, idx0 = chunks[0]
        compile_chunk(study, models[j0], seed, idx0, pad_to=pad)
    total = len(chunks)
    return in_threads(run, chunks, workers, lambda done: report(done, total))


def _chunk_group(study, seed, pad, workers, group, sets, *models):
    """One Ray task: the chunks ``group`` in ``workers`` threads of the worker process.

    ``models[i]`` is the model of data set ``sets[i]`` (Ray resolves object references passed
    as arguments, not inside a list).
    """
    by_set = dict(zip(sets, models, strict=True))
    return _run_chunks(study, seed, group, by_set, pad, workers, lambda d, t: None)


def start_ray(
    address: str | None = None, num_cpus: int | None = None, runtime_env: dict | None = None
) -> Any:
    """Connect to a Ray cluster (``address``, else ``RAY_ADDRESS``) or start a local one.

    A local cluster listens on the loopback interface only, with no dashboard. ``runtime_env``
    is passed to ``ray.init`` (for example ``{"env_vars": {"SAFESTAB_COMPILATION_CACHE": d}}``
    with ``d`` a folder every machine of a cluster shares, so that their workers load compiled
    loops instead of compiling them).

    Notes
    -----
    Ray gives each worker ``OMP_NUM_THREADS=1`` by default; BLAS then sums in another order
    than in this process, and the GP's hyperparameter optimiser can end elsewhere (measured:
    amplitudes differing by 1e-2 at Q = 800). So the workers get this process's
    ``OMP_NUM_THREADS`` (default: the CPU count, BLAS's own default), which makes their
    results identical to the local backend's on the same machine. On a cluster of other
    machines, give the workers the same thread settings (and hardware) for identical bits.
    Where this process compiles without safestab's XLA flag (``safestab/_xla_flags.py``),
    the workers get ``SAFESTAB_XLA_FLAGS=off`` so that they compile as it does.

    The workers of a local cluster that this call starts get this process's caches, whatever
    set them (``SAFESTAB_COMPILATION_CACHE`` and ``SAFESTAB_FIT_CACHE``: a folder, or
    ``off``): they load the programs this process compiled (the chunk loops) instead of
    compiling them again, as ``safestab run``'s other processes do. ``runtime_env``'s own
    ``env_vars`` take precedence (a ``JAX_COMPILATION_CACHE_DIR`` there leaves the compilation
    cache to it); nothing is passed for a cluster at an address (its machines have their own
    folders), nor when Ray was already started.
    """
    try:
        import ray
    except ImportError:
        raise ImportError(
            'backend="ray" needs Ray: pip install "safestab[ray]" (or "ray>=2.9")'
        ) from None
    if ray.is_initialized():
        return ray
    address = address or os.environ.get("RAY_ADDRESS")
    env = dict(runtime_env or {})
    given = env.get("env_vars", {})
    # folders of this machine: for a local cluster only
    caches = {} if address else child_cache_environment(compilation_cache_dir(), fit_cache_dir())
    if "JAX_COMPILATION_CACHE_DIR" in given:  # the caller's folder, which "off" would override
        caches.pop("SAFESTAB_COMPILATION_CACHE")
    env["env_vars"] = {
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", str(os.cpu_count() or 1)),
        **xla_flag_environment(os.environ),
        **caches,
        **given,
    }
    runtime_env = env
    if address:
        ray.init(address=address, runtime_env=runtime_env)
    else:
        ray.init(
            num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1",
            log_to_driver=False, runtime_env=runtime_env,
        )  # fmt: skip
    return ray


def _node_cpus(ray: Any) -> list[int]:
    """CPUs of each alive node of the cluster (nodes without CPUs left out)."""
    nodes = [node for node in ray.nodes() if node.get("Alive")]
    cpus = [int(node.get("Resources", {}).get("CPU", 0)) for node in nodes]
    return [c for c in cpus if c > 0]


def _ray(study, seed, datasets, chunks, pad, report, report_sets, address, workers):
    ray = start_ray(address)
    cpus = _node_cpus(ray)
    if workers is None:
        workers = min(cpus) if cpus else 1
    elif not cpus or workers > max(cpus):
        largest = max(cpus, default=0)
        raise ParameterError(
            f"workers (--workers) must be at most the CPUs of the cluster's largest node "
            f"({largest}), got {workers}: a Ray task runs `workers` chunks at once and asks for "
            "that many CPUs"
        )
    fit_task = ray.remote(fit_dataset)
    group_task = ray.remote(_chunk_group)
    t0 = time.perf_counter()
    first = fit_task.remote(study, seed, 0)
    if study.spec.hyperparameters == "reuse":
        hyper_ref = ray.remote(lambda m: m.hyper).remote(first)
        rest = [fit_task.remote(study, seed, j, hyper_ref) for j in range(1, datasets)]
    else:
        rest = [fit_task.remote(study, seed, j) for j in range(1, datasets)]
    model_refs = [first] + rest
    # A task runs `workers` chunks at once in threads: the loop is compiled once per task's
    # process (a worker reused for later tasks keeps it), where one task per chunk compiled it
    # in every worker process of a machine (measured: 1.4x the local backend's wall time).
    # The progress callback hears of a task's chunks when the task ends.
    groups = [list(range(k, min(k + workers, len(chunks)))) for k in range(0, len(chunks), workers)]
    pending = {}
    for ks in groups:
        group = [chunks[k] for k in ks]
        sets = sorted({j for j, _ in group})
        task = group_task.options(num_cpus=len(ks))  # the last group may be smaller
        refs = [model_refs[j] for j in sets]
        pending[task.remote(study, seed, pad, len(ks), group, sets, *refs)] = ks
    models = []
    for j, ref in enumerate(model_refs):  # the chunks already submitted run as sets finish
        models.append(ray.get(ref))
        report_sets(j + 1, datasets)
    t_data = time.perf_counter() - t0
    results: list[Any] = [None] * len(chunks)
    done = 0
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            ks = pending.pop(ref)
            for k, res in zip(ks, ray.get(ref), strict=True):
                results[k] = res
            done += len(ks)
            report(done, len(chunks))
    return models, results, t_data
