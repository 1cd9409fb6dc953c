"""The study pipeline, written once: what a scenario kind plugs in and the steps it shares.

A study kind is a :class:`Study`: the ``kind`` key of its scenario files, its presets and
loader, the function that runs it, its figures and the summary a person reads. Each study
module (``acc_study``, ``obstacle_study``, ``swarm_study``) defines one as ``STUDY``, and
:mod:`safestab.scenarios.kinds` lists them, loads a scenario by its kind and runs it. The
steps every kind shares live here:

* **learn**, for the kinds that learn ``omega`` (:func:`collect_study_data`,
  :func:`fit_study_gp`): the scenario's excitation on the true system, ``Q`` training rows
  and ``max(50, Q // 4)`` held-out rows, and the GP with the scenario's kernel;
* **calibrate** (:func:`conformal_calibration`): a split conformal ``beta`` on fresh
  excitation trajectories, one calibration unit per trajectory;
* **Monte Carlo** (:class:`StudyMonteCarlo`, a kind's optional ``montecarlo`` member): what
  ``safestab mc`` runs for the kind, checked before any work (:class:`MonteCarloOptions`);
* **outputs** (:func:`write_files`, the one writer): a study's ``<out>/<kind>_<name>``
  figures as PNG and PDF, the metrics as strict JSON (:class:`MetricsWriter`) and a run
  record (:func:`write_outputs`), a Monte Carlo's ``<out>/mc_<name>`` figure, metrics,
  per-trial records and run record (``kinds.run_mc``), all or none, each atomically;
  :func:`other_runs` names the other runs' files in the folder.

The shared schema machinery (reading, checks, overrides) is :mod:`safestab.scenarios._schema`.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import shlex
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "MetricsWriter",
    "MonteCarloOptions",
    "StepProgress",
    "Study",
    "StudyMonteCarlo",
    "Summary",
    "TaskProgress",
    "collect_study_data",
    "conformal_calibration",
    "fit_study_gp",
    "held_out_rows",
    "other_runs",
    "record_writer",
    "silent",
    "write_files",
    "write_outputs",
]

#: ``progress(message, fraction_done)``, fraction in [0, 1].
StepProgress = Callable[[str, float], None]
#: ``progress(task, done, total)``: a Monte Carlo's counted work, ``task`` one of its
#: :attr:`StudyMonteCarlo.tasks`.
TaskProgress = Callable[[str, int, int], None]


def silent(message: str, fraction: float) -> None:
    """A :data:`StepProgress` that reports nothing.

    Parameters
    ----------
    message : str
    fraction : float
    """


class MetricsWriter:
    """What every study result shares: writing its ``metrics_document()``.

    A subclass defines ``metrics_document() -> dict`` (strict JSON data: non-finite numbers
    already replaced and named, :func:`~safestab._io.with_finite_status`).
    """

    def write_metrics(self, path: str | Path) -> None:
        """Write :meth:`metrics_document` as strict JSON (no NaN or Infinity tokens), atomically.

        Parameters
        ----------
        path : str or Path
            The file; its folder must exist.

        Raises
        ------
        OutputError
            If the file cannot be written (an older file there is left as it was).
        """
        from .._io import atomic_write_json

        atomic_write_json(path, self.metrics_document())  # type: ignore[attr-defined]


@dataclasses.dataclass(frozen=True)
class Summary:
    """What a person reads after a run: a table and a few lines (plain text, no markup).

    Attributes
    ----------
    title : str
    columns : tuple of str
    rows : list of tuple of str
        One per controller or run, as many cells as ``columns``.
    lines : list of str
        Sentences printed after the table (calibration, solver gaps).
    """

    title: str
    columns: tuple[str, ...]
    rows: list[tuple[str, ...]]
    lines: list[str] = dataclasses.field(default_factory=list)


@dataclasses.dataclass(frozen=True)
class MonteCarloOptions:
    """What ``safestab mc`` was asked for; ``None`` means the kind's default.

    Attributes
    ----------
    trials, datasets : int or None
        ``--trials``, ``--datasets`` (the data sets of a kind that learns).
    backend : str
        ``--backend``, ``"local"`` or ``"ray"``.
    address : str or None
        ``--address`` of a Ray cluster.
    chunk_size : int or None
        ``--chunk-size``: trials per compiled batch.
    controllers : tuple of str or None
        ``--controllers``: the compared controllers (the swarm: its modes).
    workers : int or None
        ``--workers``.
    seed : int
        ``--seed``: trial ``i`` depends on ``(seed, i)`` only.
    """

    trials: int | None = None
    datasets: int | None = None
    backend: str = "local"
    address: str | None = None
    chunk_size: int | None = None
    controllers: tuple[str, ...] | None = None
    workers: int | None = None
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class StudyMonteCarlo:
    """A study kind's Monte Carlo: what ``safestab mc`` runs for it.

    Attributes
    ----------
    tasks : tuple of str
        The counted parts of a run, in order (one progress bar each).
    plan : callable
        ``plan(scenario, options) -> plan``: checks ``options`` (a
        :class:`MonteCarloOptions`) against the scenario before any work; raises
        ``ParameterError`` or ``ScenarioError`` naming the option (``--controllers``).
    run : callable
        ``run(plan, progress) -> result``, ``progress`` a :data:`TaskProgress`; the result
        has ``scenario``.
    document : callable
        ``document(result) -> dict``: the metrics, strict JSON data.
    figure : callable
        ``figure(result) -> matplotlib Figure``.
    trials_npz : callable
        ``trials_npz(result) -> bytes``: every trial's records, as ``.npz``.
    table : callable
        ``table(result, document)``: the summary a person reads, a rich renderable.
    """

    tasks: tuple[str, ...]
    plan: Callable[[Any, MonteCarloOptions], Any]
    run: Callable[[Any, TaskProgress], Any]
    document: Callable[[Any], dict[str, Any]]
    figure: Callable[[Any], Any]
    trials_npz: Callable[[Any], bytes]
    table: Callable[[Any, dict[str, Any]], Any]


@dataclasses.dataclass(frozen=True)
class Study:
    """A study kind: what a scenario plugs into the pipeline.

    Attributes
    ----------
    kind : str
        The scenario files' ``kind`` key, and the prefix of the output files.
    scenario_type : type
        The kind's scenario class (a frozen dataclass with a checked ``replace``).
    presets : tuple of str
        Preset names, each a ``<name>.toml`` of this package.
    load : callable
        ``load(name_or_path, *, overrides=None) -> scenario``, checking every key.
    run : callable
        ``run(scenario, progress) -> result``; the result has ``metrics_document()`` (strict
        JSON data) and ``scenario`` (the scenario it ran, overrides included).
    figures : callable
        ``figures(result) -> {suffix: matplotlib Figure}``; the files are
        ``<kind>_<name><suffix>.png`` and ``.pdf``.
    summary : callable
        ``summary(result, document) -> Summary``, from the result and its metrics document.
    table_width : int
        The terminal width the summary table needs, in columns.
    montecarlo : StudyMonteCarlo or None
        The kind's Monte Carlo (``safestab mc``); ``None``: the kind has none.
    """

    kind: str
    scenario_type: type
    presets: tuple[str, ...]
    load: Callable[..., Any]
    run: Callable[[Any, StepProgress], Any]
    figures: Callable[[Any], dict[str, Any]]
    summary: Callable[[Any, dict[str, Any]], Summary]
    table_width: int = 100
    montecarlo: StudyMonteCarlo | None = None

    def stem(self, scenario: Any) -> str:
        """The outputs' common name, ``<kind>_<scenario name>``."""
        return f"{self.kind}_{scenario.name}"


# -- learning: the steps of every scenario that learns omega ------------------------------


def held_out_rows(n_samples: int) -> int:
    """Rows held out from the fit to check the GP.

    Parameters
    ----------
    n_samples : int
        ``Q``, the training rows.

    Returns
    -------
    int
        ``max(50, Q // 4)``.
    """
    return max(50, n_samples // 4)


def collect_study_data(
    scenario: Any, *, seed: int | None = None, n_samples: int | None = None
) -> tuple[Any, Any]:
    """Collect the study's data on the true system: ``Q`` training rows and held-out rows.

    The rows come from the scenario's excitation as its Monte Carlo data sets collect them
    (``scenario.trial_study().collect``): one stream of ``Q + held_out_rows(Q)`` rows from
    ``seed``, split in that order (the first rows of a stream do not depend on its length).

    Parameters
    ----------
    scenario : ACCScenario or ObstacleScenario
    seed : int, optional
        Overrides the scenario's seed.
    n_samples : int, optional
        Overrides ``Q``.

    Returns
    -------
    train, held_out : Dataset
        ``Q`` and ``held_out_rows(Q)`` rows.
    """
    seed = scenario.seed if seed is None else int(seed)
    q = scenario.n_samples if n_samples is None else int(n_samples)
    n_test = held_out_rows(q)
    data = scenario.trial_study().collect(q + n_test, seed)
    return data.take(np.arange(q)), data.take(np.arange(q, q + n_test))


def fit_study_gp(scenario: Any, train: Any, *, seed: int | None = None) -> Any:
    """Fit the study's GP to ``train``, with the scenario's kernel.

    The hyperparameters come from ``min(hyper_subset, len(train))`` rows drawn with ``seed``
    (default the scenario's); the GP is then conditioned on all rows. The fit runs with one
    BLAS thread (:func:`~safestab.learning.batched.one_blas_thread`), its optimiser's starts
    in threads (``GaussianProcessModel``'s ``n_threads``).

    Parameters
    ----------
    scenario : ACCScenario or ObstacleScenario
    train : Dataset
        The training rows (:func:`collect_study_data`).
    seed : int, optional
        Overrides the scenario's seed.

    Returns
    -------
    GaussianProcessModel
    """
    from ..learning import GaussianProcessModel
    from ..learning.batched import one_blas_thread

    seed = scenario.seed if seed is None else int(seed)
    model = GaussianProcessModel(kernel=scenario.kernel)
    # with one BLAS thread the optimiser's starts run at once in threads, one per CPU (the
    # same fit for any thread count): faster than two BLAS threads inside each call
    with one_blas_thread():
        return model.fit(
            train.x, train.y, hyper_subset=min(scenario.hyper_subset, len(train)), seed=seed
        )


def conformal_calibration(
    scenario: Any, model: Any, *, n_trajectories: int, seed: int, delta: float
) -> dict[str, Any]:
    """Split conformal ``beta`` of ``model`` on fresh excitation trajectories, per trajectory.

    ``n_trajectories`` excitation trajectories of the scenario's horizon are collected with
    ``seed`` (a stream independent of the fitting rows) and thinned to one state per second,
    the same times in every trajectory (``Dataset.thin``); each trajectory is one
    calibration unit. The score of a unit is its largest ``|omega_i - m_i| / sigma_i`` over
    its states and the learned components, against the true ``omega``; ``beta`` is the
    ``ceil((N + 1)(1 - delta))``-th smallest score
    (:func:`~safestab.learning.conformal_beta`). The guarantee: a new trajectory of the same
    excitation lies inside ``m +- beta sigma`` at its kept states with probability at least
    ``1 - delta``; closed-loop states are another distribution, which it does not cover.

    Parameters
    ----------
    scenario : ACCScenario or ObstacleScenario
    model : uncertainty model
        The fitted GP or the cache the controller uses (the guarantee is about it).
    n_trajectories : int
        Calibration units (at least ``1 / delta - 1`` for a finite beta).
    seed : int
        Seed of the calibration trajectories.
    delta : float
        The allowed miss probability, in (0, 1).

    Returns
    -------
    dict
        ``beta``, ``chosen_beta`` (the scenario's ``gp_beta``), ``delta``, ``probability``,
        ``n_trajectories``, ``states_per_trajectory``, ``statement``: strict JSON data.
    """
    from ..learning import conformal_beta

    study = scenario.trial_study()
    per_traj, stride = study.calibration_shape()
    cal = study.collect(n_trajectories * per_traj, seed).thin(stride)
    omega = np.asarray(scenario.omega(cal.x))
    rep = conformal_beta(model, cal.x, omega, delta, groups=cal.trajectory)
    return {
        "beta": float(np.max(rep.beta)),  # applied to every learned component
        "chosen_beta": scenario.gp_beta,
        "delta": delta,
        "probability": float(rep.probability),
        "n_trajectories": int(rep.n_calibration),
        "states_per_trajectory": len(range(0, per_traj, stride)),
        "statement": rep.statement,
    }


# -- run and outputs --------------------------------------------------------------------


def _with_layout_kept(fig: Any, writer: Any) -> Any:
    """``writer``, run with ``fig``'s layout as its previous save left it (call it after one).

    A constrained layout is computed again at every save: for the PDF after the PNG that is
    about a third of the save, for nearly the same positions (the PDF's text metrics differ
    from Agg's by a little). It switches the figure's layout engine off: :func:`write_outputs`
    writes the PNG first and closes the figures afterwards.
    """

    def write(fh: Any) -> Any:
        fig.set_layout_engine("none")
        return writer(fh)

    return write


def write_files(
    out_dir: Path,
    stem: str,
    scenario: Any,
    *,
    figures: dict[str, Any],
    formats: tuple[str, ...],
    dpi: int,
    files: dict[str, Any],
    command: str | None = None,
) -> list[Path]:
    """The one writer of a run's outputs: figures, other files and a run record, all or none.

    The files are ``<out>/<stem><suffix>.<format>`` per figure and format (in that order),
    ``<out>/<stem><suffix>`` per entry of ``files`` and ``<stem>_run.json``: the record of
    which run made these files (command line, scenario name, seed, safestab version, UTC
    time, the files), so that outputs of different runs in one folder can be told apart
    (:func:`other_runs`). The figures are closed afterwards, written or not.

    Parameters
    ----------
    out_dir : Path
        An existing, writable folder.
    stem : str
        The files' common name.
    scenario : scenario
        Its ``name`` and ``seed`` go into the record.
    figures : dict of str to matplotlib Figure
        ``{suffix: figure}``.
    formats : tuple of str
        File formats of every figure (``"png"``, ``"pdf"``), the first drawn first.
    dpi : int
    files : dict of str to writer
        ``{suffix: writer}`` (:func:`~safestab._io.json_writer`, ``bytes_writer``).
    command : str, optional
        The command line for the record (default: this process's arguments).

    Returns
    -------
    list of Path
        The files written, the record last.

    Raises
    ------
    OutputError
        If a file cannot be written; none of the set is then left behind, and older files of
        the same names are as they were.
    """
    import matplotlib.pyplot as plt

    from .._io import figure_writer, write_all

    try:
        outputs = {}
        for suffix, fig in figures.items():
            for i, fmt in enumerate(formats):
                path = out_dir / f"{stem}{suffix}.{fmt}"
                writer = figure_writer(fig, path, dpi=dpi)
                outputs[path] = writer if i == 0 else _with_layout_kept(fig, writer)
        for suffix, writer in files.items():
            outputs[out_dir / f"{stem}{suffix}"] = writer
        record = out_dir / f"{stem}_run.json"
        outputs[record] = record_writer(record, scenario, list(outputs), command=command)
        return write_all(outputs)
    finally:
        for fig in figures.values():
            plt.close(fig)


def write_outputs(
    study: Study,
    result: Any,
    document: dict[str, Any],
    out_dir: Path,
    *,
    command: str | None = None,
) -> list[Path]:
    """Write a study's figures (PNG and PDF), metrics and run record, all or none.

    The files are ``<out>/<kind>_<name><suffix>.png`` and ``.pdf`` per figure,
    ``<kind>_<name>_metrics.json`` and ``<kind>_<name>_run.json`` (:func:`write_files`).

    Parameters
    ----------
    study : Study
    result : study result
        What ``study.run`` returned.
    document : dict
        Its metrics document.
    out_dir : Path
        An existing, writable folder.
    command : str, optional
        The command line for the record (default: this process's arguments).

    Returns
    -------
    list of Path
        The files written, the record last.

    Raises
    ------
    OutputError
        If a file cannot be written (none of the set is then left behind).
    """
    from .._io import json_writer

    return write_files(
        out_dir, study.stem(result.scenario), result.scenario, figures=study.figures(result),
        formats=("png", "pdf"), dpi=200, files={"_metrics.json": json_writer(document)},
        command=command,
    )  # fmt: skip


def record_writer(
    record: Path, scenario: Any, paths: list[Path], *, command: str | None = None
) -> Any:
    """The writer of a run record (:func:`~safestab._io.json_writer`).

    The record names the command line (``command``, default this process's arguments), the
    scenario's name and seed, the safestab version, the UTC time and the files: ``paths``
    and the record itself.

    Parameters
    ----------
    record : Path
        The record's own path.
    scenario : scenario
        Its ``name`` and ``seed`` are recorded.
    paths : list of Path
        The run's other files.
    command : str, optional

    Returns
    -------
    callable
        A writer for :func:`~safestab._io.write_all`.
    """
    from .._io import json_writer
    from .._version import __version__

    return json_writer(
        {
            "command": command or shlex.join(["safestab", *sys.argv[1:]]),
            "scenario": scenario.name,
            "seed": getattr(scenario, "seed", None),
            "safestab": __version__,
            "finished_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "files": sorted(p.name for p in [*paths, record]),
        }
    )


def other_runs(out_dir: Path, record: Path) -> str | None:
    """A line naming the other runs' records and the unrecorded files in ``out_dir``.

    Parameters
    ----------
    out_dir : Path
        The output folder.
    record : Path
        This run's ``*_run.json``.

    Returns
    -------
    str or None
        The line; ``None`` when the folder holds nothing else.
    """
    ours = set(json.loads(record.read_text())["files"])
    others, recorded = [], set(ours)
    for path in sorted(out_dir.glob("*_run.json")):
        if path == record or path.name.startswith("."):
            continue
        prefix = path.name[: -len("_run.json")]
        try:
            doc = json.loads(path.read_text())
            recorded |= set(doc["files"])
            others.append(f"{prefix} ({doc.get('finished_utc')})")
        except (OSError, ValueError, KeyError, TypeError):
            others.append(f"{prefix} (unreadable record)")
    # hidden names are a writer's temporaries (another process writing its outputs now)
    loose = [
        p.name
        for p in out_dir.glob("*_*.*")
        if p.is_file() and not p.name.startswith(".") and p.name not in recorded
    ]
    parts = []
    if others:
        parts.append(
            f"{out_dir} also holds the outputs of {len(others)} other run(s): "
            + ", ".join(others)
            + " (their *_run.json name the command and the files)"
        )
    if loose:
        parts.append(f"{len(loose)} file(s) there come from no recorded run (an older safestab)")
    return " ".join(parts) or None
