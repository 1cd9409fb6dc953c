"""The study pipeline, written once: a scenario kind plugs in its model, study, metrics and figure.

A study kind is a :class:`Study`: the ``kind`` key of its scenario files, its presets and
loader, the function that runs it, its figures and the summary a person reads. Every kind
goes through the same steps here:

* **load** (:func:`kind_of`, :func:`load`): a preset by name or a TOML file by its ``kind``
  key, checked before any work (the shared schema machinery is
  :mod:`safestab.scenarios._schema`);
* **learn**, for the kinds that learn ``omega`` (:func:`collect_study_data`,
  :func:`fit_study_gp`): the scenario's excitation on the true system, ``Q`` training rows
  and ``max(50, Q // 4)`` held-out rows, and the GP with the scenario's kernel;
* **run** (:func:`run`): the kind's own closed loops and metrics;
* **outputs** (:func:`write_outputs`): ``<out>/<kind>_<name>`` figures as PNG and PDF, the
  metrics as strict JSON and a run record, all or none, each atomically.

The kinds are :data:`STUDY_MODULES`, each a module of this package with a ``STUDY``
attribute: a new scenario is its model module, a study module and a line here.
"""

from __future__ import annotations

import dataclasses
import datetime
import importlib
import json
import shlex
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ScenarioError

__all__ = [
    "STUDY_MODULES",
    "Progress",
    "Study",
    "StudyOutputs",
    "Summary",
    "collect_study_data",
    "fit_study_gp",
    "held_out_rows",
    "kind_of",
    "load",
    "other_runs",
    "record_writer",
    "run",
    "silent",
    "studies",
    "study_of",
    "with_overrides",
    "write_outputs",
]

#: ``progress(message, fraction_done)``, fraction in [0, 1].
Progress = Callable[[str, float], None]

#: The modules (of this package) that define a study kind as their ``STUDY``, in the order
#: the kinds are listed; the first is the kind of a scenario file without a ``kind`` key.
STUDY_MODULES = ("acc_study", "obstacle_study", "swarm_study")


def silent(message: str, fraction: float) -> None:
    """A :data:`Progress` that reports nothing."""


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
    """

    kind: str
    scenario_type: type
    presets: tuple[str, ...]
    load: Callable[..., Any]
    run: Callable[[Any, Progress], Any]
    figures: Callable[[Any], dict[str, Any]]
    summary: Callable[[Any, dict[str, Any]], Summary]
    table_width: int = 100

    def stem(self, scenario: Any) -> str:
        """The outputs' common name, ``<kind>_<scenario name>``."""
        return f"{self.kind}_{scenario.name}"


def studies() -> dict[str, Study]:
    """Every study kind, ``{kind: Study}``, in the order of :data:`STUDY_MODULES`."""
    found = (importlib.import_module(f"{__package__}.{m}").STUDY for m in STUDY_MODULES)
    return {s.kind: s for s in found}


def study_of(scenario: Any) -> Study:
    """The study kind of a scenario object.

    Raises
    ------
    ScenarioError
        If ``scenario`` is not a scenario of any kind.
    """
    for study in studies().values():
        if isinstance(scenario, study.scenario_type):
            return study
    names = ", ".join(s.scenario_type.__name__ for s in studies().values())
    raise ScenarioError(f"scenario must be one of {names}, got {type(scenario).__name__}")


def kind_of(name_or_path: str | Path) -> Study:
    """The study kind of a preset (by name) or a scenario file (its ``kind`` key).

    A file without a ``kind`` key is of the first kind, ``"acc"``.

    Raises
    ------
    ScenarioError
        If the file cannot be read or parsed, or its ``kind`` is not a known kind.
    """
    from ._schema import read_document

    kinds = studies()
    for study in kinds.values():
        if str(name_or_path) in study.presets:
            return study
    every = tuple(p for s in kinds.values() for p in s.presets)
    doc, _, source = read_document(name_or_path, every, __package__)
    first = next(iter(kinds))
    kind = doc.get("kind", first)
    if not isinstance(kind, str) or kind not in kinds:
        raise ScenarioError(
            f"{source}: kind must be one of {', '.join(repr(k) for k in kinds)} "
            f"(or absent for {first!r}), got {kind!r}"
        )
    return kinds[kind]


def load(name_or_path: str | Path, *, overrides: Mapping[str, Any] | None = None) -> Any:
    """Load a scenario of any kind, by preset name or file (its ``kind`` key).

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"table.key": value}`` set before the document is checked (``--set``).

    Raises
    ------
    ScenarioError
        As the kind's loader, or for an unknown ``kind``.
    """
    return kind_of(name_or_path).load(name_or_path, overrides=overrides)


def with_overrides(scenario: Any, **changes: Any) -> Any:
    """``scenario.replace(**changes)`` for the changes that are not ``None``, checked.

    Raises
    ------
    ScenarioError
        If the scenario's kind has no such field (``n_samples`` of a kind that learns
        nothing), naming the field and the kind, or a new value is invalid.
    """
    changes = {k: v for k, v in changes.items() if v is not None}
    fields = {f.name for f in dataclasses.fields(scenario)}
    unknown = sorted(set(changes) - fields)
    if unknown:
        kind = study_of(scenario).kind
        raise ScenarioError(
            f"a {kind} scenario has no {', '.join(unknown)} to override (its fields: "
            f"{', '.join(sorted(fields - {'name'}))})"
        )
    return scenario.replace(**changes) if changes else scenario


# -- learning: the steps of every scenario that learns omega ------------------------------


def held_out_rows(n_samples: int) -> int:
    """Rows held out from the fit to check the GP: ``max(50, Q // 4)``."""
    return max(50, n_samples // 4)


def collect_study_data(
    scenario: Any, *, seed: int | None = None, n_samples: int | None = None, n_extra: int = 0
) -> tuple[Any, Any]:
    """Collect the study's data on the true system: ``Q`` training rows and held-out rows.

    The rows come from the scenario's excitation as its Monte Carlo data sets collect them
    (``scenario.trial_study().collect``): one stream of ``Q + held_out_rows(Q) + n_extra``
    rows from ``seed``, split in that order.

    Parameters
    ----------
    scenario : ACCScenario or ObstacleScenario
    seed : int, optional
        Overrides the scenario's seed.
    n_samples : int, optional
        Overrides ``Q``.
    n_extra : int
        Further rows drawn after the held-out ones and not returned (the obstacle study
        draws them so that its data stream stays that of its published runs).

    Returns
    -------
    train, held_out : Dataset
    """
    seed = scenario.seed if seed is None else int(seed)
    q = scenario.n_samples if n_samples is None else int(n_samples)
    n_test = held_out_rows(q)
    data = scenario.trial_study().collect(q + n_test + n_extra, seed)
    return data.take(np.arange(q)), data.take(np.arange(q, q + n_test))


def fit_study_gp(scenario: Any, train: Any, *, seed: int | None = None) -> Any:
    """Fit the study's GP to ``train``, with the scenario's kernel.

    The hyperparameters come from ``min(hyper_subset, len(train))`` rows drawn with ``seed``
    (default the scenario's); the GP is then conditioned on all rows.

    Returns
    -------
    GaussianProcessModel
    """
    from ..learning import GaussianProcessModel

    seed = scenario.seed if seed is None else int(seed)
    model = GaussianProcessModel(kernel=scenario.kernel)
    return model.fit(
        train.x, train.y, hyper_subset=min(scenario.hyper_subset, len(train)), seed=seed
    )


# -- run and outputs --------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class StudyOutputs:
    """One run of the pipeline: the study kind, its result, metrics document and files."""

    study: Study
    result: Any
    document: dict[str, Any]
    written: list[Path]

    def summary(self) -> Summary:
        """The kind's summary of this run."""
        return self.study.summary(self.result, self.document)


def run(
    scenario: Any,
    out_dir: str | Path,
    *,
    progress: Progress | None = None,
    command: str | None = None,
) -> StudyOutputs:
    """Run a scenario's study and write its outputs.

    The output folder is checked writable before any work; the files are written all or
    none (:func:`write_outputs`).

    Parameters
    ----------
    scenario : ACCScenario, ObstacleScenario or SwarmScenario
    out_dir : str or Path
        The output folder (created if needed).
    progress : callable, optional
        ``progress(message, fraction_done)``.
    command : str, optional
        The command line recorded in the run record (default: this process's arguments).

    Returns
    -------
    StudyOutputs

    Raises
    ------
    ScenarioError
        If ``scenario`` is not a scenario.
    OutputError
        If ``out_dir`` is not a writable folder (before any work) or a file cannot be written.
    """
    from .._io import ensure_writable_dir

    study = study_of(scenario)
    folder = ensure_writable_dir(out_dir, name="out_dir")
    result = study.run(scenario, progress or silent)
    document = result.metrics_document()
    written = write_outputs(study, result, document, folder, command=command)
    return StudyOutputs(study, result, document, written)


def write_outputs(
    study: Study,
    result: Any,
    document: dict[str, Any],
    out_dir: Path,
    *,
    command: str | None = None,
) -> list[Path]:
    """Write a run's figures (PNG and PDF), metrics and run record, all or none.

    The files are ``<out>/<kind>_<name><suffix>.png`` and ``.pdf`` per figure,
    ``<kind>_<name>_metrics.json`` and ``<kind>_<name>_run.json``: the record of which run
    made these files (command line, scenario name, seed, safestab version, UTC time, the
    files), so that outputs of different runs in one folder can be told apart
    (:func:`other_runs`). The figures are closed afterwards.

    Returns
    -------
    list of Path
        The files written, the record last.
    """
    import matplotlib.pyplot as plt

    from .._io import figure_writer, json_writer, write_all

    scenario = result.scenario
    stem = study.stem(scenario)
    figures = study.figures(result)
    try:
        outputs = {}
        for suffix, fig in figures.items():
            for ext in ("png", "pdf"):
                path = out_dir / f"{stem}{suffix}.{ext}"
                outputs[path] = figure_writer(fig, path, dpi=200)
        outputs[out_dir / f"{stem}_metrics.json"] = json_writer(document)
        record = out_dir / f"{stem}_run.json"
        outputs[record] = record_writer(record, scenario, list(outputs), command=command)
        return write_all(outputs)
    finally:
        for fig in figures.values():
            plt.close(fig)


def record_writer(
    record: Path, scenario: Any, paths: list[Path], *, command: str | None = None
) -> Any:
    """The writer of a run record (:func:`~safestab._io.json_writer`).

    The record names the command line (``command``, default this process's arguments), the
    scenario's name and seed, the safestab version, the UTC time and the files: ``paths``
    and the record itself.
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

    ``record`` is this run's ``*_run.json``; ``None`` when the folder holds nothing else.
    """
    ours = set(json.loads(record.read_text())["files"])
    others, recorded = [], set(ours)
    for path in sorted(out_dir.glob("*_run.json")):
        if path == record:
            continue
        prefix = path.name[: -len("_run.json")]
        try:
            doc = json.loads(path.read_text())
            recorded |= set(doc["files"])
            others.append(f"{prefix} ({doc.get('finished_utc')})")
        except (OSError, ValueError, KeyError, TypeError):
            others.append(f"{prefix} (unreadable record)")
    loose = [p.name for p in out_dir.glob("*_*.*") if p.is_file() and p.name not in recorded]
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
