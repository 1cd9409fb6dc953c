"""The Monte Carlo of the kinds that learn ``omega``: the study plug-in's ``montecarlo`` member.

:data:`GP_MONTECARLO` is the :class:`~safestab.scenarios.pipeline.StudyMonteCarlo` of the ACC
and obstacle kinds: it checks ``safestab mc``'s options against the scenario's trial study
(the ``[montecarlo]`` table, ``--controllers``, ``--chunk-size``), runs
:func:`~safestab.montecarlo.run_montecarlo` and gives its document, figure, per-trial records
and summary table to the pipeline's writer.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ..scenarios import MonteCarloSpec, check_controllers
from ..scenarios.pipeline import MonteCarloOptions, StudyMonteCarlo, TaskProgress
from .report import counted, metrics_document, plot_montecarlo, trials_npz_bytes
from .runner import run_montecarlo

__all__ = ["GP_MONTECARLO", "GPPlan", "summary_table"]

#: The counted parts of a run: data sets (collect, fit or condition) and chunks of trials.
TASKS = ("data sets (collect, fit or condition)", "chunks of trials")


@dataclasses.dataclass(frozen=True)
class GPPlan:
    """A checked Monte Carlo of a scenario that learns: the scenario, its spec, the options."""

    scenario: Any
    spec: MonteCarloSpec
    options: MonteCarloOptions


def plan(scenario: Any, options: MonteCarloOptions) -> GPPlan:
    """Check ``options`` against ``scenario``'s trial study, before any work.

    The spec is the scenario's ``[montecarlo]`` table (else the defaults), with
    ``--chunk-size`` and ``--controllers`` applied and checked like the file.

    Raises
    ------
    ScenarioError
        For a bad chunk size or controller name (naming ``--controllers``), or a spec that
        does not fit the scenario's states.
    """
    spec = scenario.montecarlo or MonteCarloSpec()
    if options.chunk_size is not None:
        spec = spec.replace(chunk_size=options.chunk_size)  # checked like the file
    if options.controllers is not None:
        names = check_controllers("--controllers", list(options.controllers), "command line")
        spec = spec.replace(controllers=names)
    scenario.trial_study(spec)  # the spec's vectors against the scenario's states
    return GPPlan(scenario, spec, options)


def run(checked: GPPlan, progress: TaskProgress) -> Any:
    """:func:`~safestab.montecarlo.run_montecarlo` of a checked plan; a ``MonteCarloRun``."""
    o = checked.options
    return run_montecarlo(
        checked.scenario, spec=checked.spec, trials=o.trials, datasets=o.datasets, seed=o.seed,
        backend=o.backend, address=o.address, workers=o.workers,
        progress=lambda done, total: progress(TASKS[1], done, total),
        dataset_progress=lambda done, total: progress(TASKS[0], done, total),
    )  # fmt: skip


def summary_table(name: str, summary: dict[str, Any]) -> Any:
    """The Monte Carlo summary as a rich Table that fits an 80-column terminal.

    Each rate is on one line and its 95 % interval on the next; cells wrap (never cut with an
    ellipsis) where the terminal is narrower still. The claimed probability is printed only
    for the controllers whose beta carries one (Lemma 2 per data set, conformal per trial),
    with the rate that tests it; the caption says where its assumptions are listed.

    Parameters
    ----------
    name : str
        The scenario's name.
    summary : dict
        The metrics document's ``summary``.

    Returns
    -------
    rich.table.Table
    """
    from rich import box
    from rich.table import Table

    table = Table(
        title=f"Monte Carlo '{name}': {counted(summary['trials'], 'trial')}, "
        f"{counted(summary['datasets'], 'data set')}",
        caption="safe per data set: all of its trials safe. Claims and their assumptions: "
        "summary.controllers.<name>.guarantee in the metrics JSON, docs/montecarlo.md",
        # no vertical rules and no padding (the rules' places separate the columns): the
        # width goes to the numbers
        box=box.SIMPLE_HEAD,
        padding=(0, 0),
    )
    table.add_column("controller", justify="left", overflow="fold", max_width=12)
    for col in ("safe per\ndata set", "safe per\ntrial", "Lemma-2\nper data set"):
        table.add_column(col + "\n\\[95% CI]", justify="right", overflow="fold", min_width=15)
    table.add_column("claimed", justify="right", overflow="fold", max_width=9)
    unit = summary.get("h_unit", "")
    table.add_column(f"min h\n1%-q\n\\[{unit}]", justify="right", overflow="fold", max_width=8)

    def rate(entry):
        if entry is None:
            return "-"
        lo, hi = entry["ci95"]
        return f"{entry['rate']:.4f}\n[{lo:.3f}, {hi:.3f}]"

    for controller, e in summary["controllers"].items():
        q = e["min_h_quantiles"]["0.01"]
        q_text = "-" if q is None else f"{q:.3f}"
        g = e.get("guarantee")
        claim = "-" if g is None else f"{g['claimed_probability']:.4f}\n({g['unit']})"
        table.add_row(
            controller, rate(e["safe_per_dataset"]), rate(e["safe"]),
            rate(e.get("lemma2_per_dataset")), claim, q_text,
        )  # fmt: skip
    return table


#: The ACC's and the obstacle's Monte Carlo (:mod:`safestab.scenarios.pipeline`).
GP_MONTECARLO = StudyMonteCarlo(
    tasks=TASKS,
    plan=plan,
    run=run,
    document=metrics_document,
    figure=plot_montecarlo,
    trials_npz=trials_npz_bytes,
    table=lambda result, document: summary_table(result.scenario.name, document["summary"]),
)
