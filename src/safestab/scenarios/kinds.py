"""The scenario kinds: load a scenario by its kind and run its study through the pipeline.

Each kind is a study module of this package with a ``STUDY`` attribute
(:class:`~safestab.scenarios.pipeline.Study`), listed in :func:`studies`. A preset is
found by name among the kinds' presets, a file by its top-level ``kind`` key (none: the first
kind, ``"acc"``). :func:`run` runs any scenario's study and writes its outputs;
:func:`plan_mc` and :func:`run_mc` do the same for its Monte Carlo (the study's
``montecarlo`` member), for every kind alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..errors import ParameterError, ScenarioError
from .pipeline import (
    MonteCarloOptions,
    StepProgress,
    Study,
    Summary,
    TaskProgress,
    silent,
    write_files,
    write_outputs,
)

__all__ = [
    "MonteCarloPlan",
    "StudyOutputs",
    "check_mc_options",
    "kind_of",
    "load",
    "plan_mc",
    "run",
    "run_mc",
    "studies",
    "study_of",
    "with_overrides",
]


def studies() -> dict[str, Study]:
    """Every study kind, in order.

    Returns
    -------
    dict of str to Study
        ``{kind: Study}``; importing the study modules on the first call.
    """
    # the kinds, in order (the first is a file's without a kind key); imported when first
    # asked for, so that loading a scenario does not import every study
    from . import acc_study, obstacle_study, swarm_study

    return {m.STUDY.kind: m.STUDY for m in (acc_study, obstacle_study, swarm_study)}


def study_of(scenario: Any) -> Study:
    """The study kind of a scenario object.

    Parameters
    ----------
    scenario : ACCScenario, ObstacleScenario or SwarmScenario

    Returns
    -------
    Study

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

    Parameters
    ----------
    name_or_path : str or Path
        A preset name (of any kind) or a TOML file.

    Returns
    -------
    Study

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

    The presets are ``paper``, ``stress``, ``stress-ood`` (ACC), ``obstacle`` and ``swarm``.

    Parameters
    ----------
    name_or_path : str or Path
    overrides : mapping of str to value, optional
        ``{"table.key": value}`` set before the document is checked (``--set``).

    Returns
    -------
    ACCScenario, ObstacleScenario or SwarmScenario

    Raises
    ------
    ScenarioError
        As the kind's loader (:func:`~safestab.scenarios.load_scenario`,
        :func:`~safestab.scenarios.load_obstacle_scenario`,
        :func:`~safestab.scenarios.swarm.load_swarm_scenario`), or for an unknown ``kind``.
    """
    return kind_of(name_or_path).load(name_or_path, overrides=overrides)


def with_overrides(scenario: Any, **changes: Any) -> Any:
    """``scenario.replace(**changes)`` for the changes that are not ``None``, checked.

    Parameters
    ----------
    scenario : ACCScenario, ObstacleScenario or SwarmScenario
    **changes
        Field names and new values (``seed``, ``n_samples``, ``t_final`` from the command
        line); ``None`` means unchanged.

    Returns
    -------
    scenario
        A new scenario of the same kind, or ``scenario`` itself when nothing changes.

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
        got = ", ".join(f"{k} = {changes[k]!r} (--{k.replace('_', '-')})" for k in unknown)
        raise ScenarioError(
            f"a {kind} scenario has no {', '.join(unknown)} to override, got {got}; a {kind} "
            f"scenario's fields are {', '.join(sorted(fields - {'name'}))}"
        )
    return scenario.replace(**changes) if changes else scenario


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

    def montecarlo_table(self) -> Any:
        """The kind's Monte Carlo summary table of this run (:func:`run_mc`), a rich renderable."""
        return self.study.montecarlo.table(self.result, self.document)  # type: ignore[union-attr]


def run(
    scenario: Any,
    out_dir: str | Path,
    *,
    progress: StepProgress | None = None,
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


@dataclasses.dataclass(frozen=True)
class MonteCarloPlan:
    """A Monte Carlo checked before any work: the study kind and what its ``plan`` gave."""

    study: Study
    checked: Any


def check_mc_options(options: MonteCarloOptions) -> None:
    """The checks every kind's Monte Carlo options share, named as the command line names them.

    Counts (``--trials``, ``--datasets``, ``--workers``, ``--chunk-size``) are at least 1
    where given, ``--seed`` is a JAX key word (``[0, 2**32 - 1]``) and ``--backend`` one of
    the Monte Carlo backends. What applies to one kind only, its ``plan`` checks.

    Raises
    ------
    ParameterError
        Naming the option, what was received and what is expected.
    """
    from ..montecarlo import BACKENDS

    if options.backend not in BACKENDS:
        raise ParameterError(f"--backend must be one of {BACKENDS}, got {options.backend!r}")
    for name, value in (
        ("--trials", options.trials), ("--datasets", options.datasets),
        ("--workers", options.workers), ("--chunk-size", options.chunk_size),
    ):  # fmt: skip
        if value is not None and value < 1:
            raise ParameterError(f"{name} must be >= 1, got {value}")
    if not 0 <= options.seed <= 2**32 - 1:
        raise ParameterError(f"--seed must be in [0, 2**32 - 1], got {options.seed}")


def plan_mc(scenario: Any, options: MonteCarloOptions, *, name: str = "scenario") -> MonteCarloPlan:
    """Check a Monte Carlo of ``scenario`` with ``options`` before any work, by its kind.

    Parameters
    ----------
    scenario : ACCScenario, ObstacleScenario or SwarmScenario
    options : MonteCarloOptions
    name : str
        The scenario argument's name for the messages (``"--scenario"`` on the command line).

    Returns
    -------
    MonteCarloPlan

    Raises
    ------
    ScenarioError
        If ``scenario`` is not a scenario, or its kind has no Monte Carlo (naming ``name``,
        the kind received and the kinds that have one); or as the kind's ``plan``.
    ParameterError
        As the kind's ``plan`` (an option that does not apply to the kind).
    """
    check_mc_options(options)
    study = study_of(scenario)
    if study.montecarlo is None:
        able = [s.kind for s in studies().values() if s.montecarlo is not None]
        raise ScenarioError(
            f"{name} must be a scenario of a kind with a Monte Carlo "
            f"({', '.join(repr(k) for k in able)}), got {scenario.name!r} of kind {study.kind!r}"
        )
    return MonteCarloPlan(study, study.montecarlo.plan(scenario, options))


def run_mc(
    plan: MonteCarloPlan,
    out_dir: str | Path,
    *,
    progress: TaskProgress | None = None,
    command: str | None = None,
) -> StudyOutputs:
    """Run a checked Monte Carlo and write its outputs, for every kind alike.

    The files are ``<out>/mc_<name>.png``, ``mc_<name>_metrics.json``,
    ``mc_<name>_trials.npz`` and ``mc_<name>_run.json``, all or none
    (:func:`~safestab.scenarios.pipeline.write_files`).

    Parameters
    ----------
    plan : MonteCarloPlan
        From :func:`plan_mc`.
    out_dir : str or Path
        The output folder (created if needed), checked writable before any work.
    progress : callable, optional
        ``progress(task, done, total)``, ``task`` one of the member's ``tasks``.
    command : str, optional
        The command line recorded in the run record (default: this process's arguments).

    Returns
    -------
    StudyOutputs
        Its ``montecarlo_table()`` is the kind's summary table.

    Raises
    ------
    OutputError
        If ``out_dir`` is not a writable folder (before any work) or a file cannot be written.
    """
    from .._io import bytes_writer, ensure_writable_dir, json_writer

    folder = ensure_writable_dir(out_dir, name="out_dir")
    mc = plan.study.montecarlo
    assert mc is not None  # plan_mc made the plan
    result = mc.run(plan.checked, progress or (lambda task, done, total: None))
    document = mc.document(result)
    files = {
        "_metrics.json": json_writer(document),
        "_trials.npz": bytes_writer(mc.trials_npz(result)),
    }
    written = write_files(
        folder, f"mc_{result.scenario.name}", result.scenario,
        figures={"": mc.figure(result)}, formats=("png",), dpi=150, files=files,
        command=command,
    )  # fmt: skip
    return StudyOutputs(plan.study, result, document, written)
