"""Command line: a thin front end over the public functions.

Every command checks its inputs before any work: the scenario (every key, when the file is
loaded), the command-line overrides (checked like the file) and the output folder (created if
missing, and proved writable by creating and removing a probe file). Outputs are written all
or none, each atomically (``safestab._io.write_all``): a failed run leaves the output folder
as it was. An error prints one line, ``error: <class>: <message>``, to stderr and exits
non-zero (2 for bad input, 1 for a failure during the run); ``--debug`` adds the traceback.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="safestab: safe stabilization with GP learning.",
)

T = TypeVar("T")

#: Exit codes: bad input (scenario, options, output folder) and a failure during the run.
EXIT_BAD_INPUT, EXIT_RUN_FAILED = 2, 1
_MAX_MESSAGE = 400  # characters of an error message on the one line


@app.callback()
def _main() -> None:
    """Safe stabilization with closed-form CLF-CBF formulas and GP learning."""


def _one_line(exc: BaseException) -> str:
    """``<class>: <message>`` on one line (whitespace collapsed, long messages cut)."""
    message = " ".join(str(exc).split())
    if len(message) > _MAX_MESSAGE:
        message = message[: _MAX_MESSAGE - 40] + " ... (cut; --debug shows all)"
    return f"error: {type(exc).__name__}: {message}" if message else f"error: {type(exc).__name__}"


def _guard(step: Callable[[], T], *, debug: bool, code: int) -> T:
    """Run one step of a command; on an exception print one line (or the traceback) and exit."""
    try:
        return step()
    except Exception as exc:
        if debug:
            typer.echo(traceback.format_exc().rstrip(), err=True)
        typer.echo(_one_line(exc), err=True)
        raise typer.Exit(code=code) from None


def _console(width: int = 100):
    from rich.console import Console

    return Console(width=max(width, Console().width))


def _with_progress(console, work):
    """Run ``work(report)`` under a rich progress bar; ``report(message, fraction)``."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    ) as progress:
        task = progress.add_task("starting", total=1.0)

        def report(message: str, fraction: float) -> None:
            progress.update(task, description=message, completed=fraction)

        return work(report)


def _write_figures(figures: dict, documents: dict) -> list[Path]:
    """Write each figure as PNG and PDF and each JSON document, all or none; close figures."""
    import matplotlib.pyplot as plt

    from ._io import figure_writer, json_writer, write_all

    try:
        outputs = {}
        for stem, fig in figures.items():
            for ext in ("png", "pdf"):
                path = stem.with_name(f"{stem.name}.{ext}")
                outputs[path] = figure_writer(fig, path, dpi=200)
        for path, doc in documents.items():
            outputs[path] = json_writer(doc)
        return write_all(outputs)
    finally:
        for fig in figures.values():
            plt.close(fig)


def _acc_outputs(sc, out_dir: Path, debug: bool) -> None:
    """Run the ACC study and write its outputs (the body of ``acc`` and ``run``)."""
    from rich.table import Table

    from .scenarios import acc_study

    console = _console()
    result = _guard(
        lambda: _with_progress(console, lambda r: acc_study.run_study(sc, progress=r)),
        debug=debug,
        code=EXIT_RUN_FAILED,
    )

    def write():
        from .plotting import plot_acc_study

        stem = out_dir / f"acc_{sc.name}"
        return _write_figures(
            {stem: plot_acc_study(result)},
            {out_dir / f"acc_{sc.name}_metrics.json": result.metrics_document()},
        )

    written = _guard(write, debug=debug, code=EXIT_RUN_FAILED)

    table = Table(title=f"ACC study '{sc.name}' (Q = {len(result.dataset)})")
    columns = ("controller", "min h [m]", "h<0 [s]", "rms v_f-v_d", "max|h-h_true|", "incompat.")
    for col in columns:
        table.add_column(col, justify="right", no_wrap=True)
    for name, m in result.metrics.items():
        table.add_row(
            name,
            f"{m['min_h_m']:.3f}",
            f"{m['time_h_negative_s']:.2f}",
            f"{m['rms_speed_error_mps']:.3f}",
            f"{m.get('max_abs_h_gap_to_true_m', 0.0):.4f}",
            str(m["incompatible_steps"]),
        )
    console.print(table)
    cal = result.calibration
    console.print(
        f"GP held-out coverage at beta = {sc.gp_beta}: per component "
        f"{[round(float(c), 3) for c in cal.per_component]}, joint {cal.joint:.3f}; "
        f"RMSE {[float(f'{r:.2e}') for r in cal.rmse]} m/s^2"
    )
    console.print(f"wrote {', '.join(str(p) for p in written)}", markup=False, soft_wrap=True)


def _obstacle_outputs(sc, out_dir: Path, debug: bool) -> None:
    """Run the obstacle study and write its figures, metrics and summary table."""
    from rich.table import Table

    from .scenarios import obstacle_study

    console = _console(width=130)
    result = _guard(
        lambda: _with_progress(
            console, lambda r: obstacle_study.run_obstacle_study(sc, progress=r)
        ),
        debug=debug,
        code=EXIT_RUN_FAILED,
    )

    def write():
        from .plotting import plot_compatibility_maps, plot_obstacle_plane

        base = f"obstacle_{sc.name}"
        return _write_figures(
            {
                out_dir / base: plot_obstacle_plane(result),
                out_dir / f"{base}_maps": plot_compatibility_maps(result),
            },
            {out_dir / f"{base}_metrics.json": result.metrics_document()},
        )

    written = _guard(write, debug=debug, code=EXIT_RUN_FAILED)

    table = Table(title=f"Obstacle study '{sc.name}' ({len(sc.start_states())} starts)")
    columns = ("controller", "limits", *obstacle_study.OUTCOMES, "min h [m^2]",
               "stuck incompat.", "c* [m^2]")  # fmt: skip
    for col in columns:
        table.add_column(col, justify="right", no_wrap=True)
    for (name, limits), run in result.runs.items():
        stuck = run.outcome == "stuck"
        table.add_row(
            name,
            limits,
            *(str(int((run.outcome == o).sum())) for o in obstacle_study.OUTCOMES),
            f"{float(run.h.min()):.3f}",
            f"{int((~run.end_verdict[stuck]).sum())}/{int(stuck.sum())}",
            f"{result.doa[name]:.3g}",
        )
    console.print(table)
    cov = result.coverage
    console.print(
        f"GP held-out coverage at beta = {sc.gp_beta}: per component "
        f"{[round(float(c), 3) for c in cov['per_component']]}, joint {cov['joint']:.3f}; "
        f"stated probability (1 - delta)^2 = {cov['stated_probability']:.4f}"
    )
    console.print(f"wrote {', '.join(str(p) for p in written)}", markup=False, soft_wrap=True)


def _overrides(seed, n_samples, t_final) -> dict:
    return {
        k: v
        for k, v in {"seed": seed, "n_samples": n_samples, "t_final": t_final}.items()
        if v is not None
    }


@app.command()
def acc(
    scenario: str = typer.Option("paper", help="A preset ('paper', 'stress') or a TOML file."),
    out: Path = typer.Option(Path("results"), help="Output folder (created if needed)."),
    seed: int | None = typer.Option(None, help="Seed for data collection and GP fitting."),
    n_samples: int | None = typer.Option(None, help="Override the number of GP samples Q."),
    t_final: float | None = typer.Option(None, help="Override the simulated horizon, s."),
    debug: bool = typer.Option(False, "--debug", help="Show the traceback of an error."),
) -> None:
    """Run the ACC study: collect data, fit the GP, simulate three controllers, write outputs.

    Writes OUT/acc_<name>.png, .pdf and _metrics.json, all or none.
    """
    import matplotlib

    matplotlib.use("Agg")
    from ._io import ensure_writable_dir
    from .scenarios import load_scenario

    # -- checks, before any work ----------------------------------------------------------
    def check_inputs():
        sc = load_scenario(scenario).replace(**_overrides(seed, n_samples, t_final))
        return sc, ensure_writable_dir(out, name="--out")

    sc, out_dir = _guard(check_inputs, debug=debug, code=EXIT_BAD_INPUT)
    _acc_outputs(sc, out_dir, debug)


@app.command()
def run(
    scenario: str = typer.Option(
        ..., help="A preset ('paper', 'stress', 'obstacle') or a TOML file (its kind key)."
    ),
    out: Path = typer.Option(Path("results"), help="Output folder (created if needed)."),
    seed: int | None = typer.Option(None, help="Seed for data collection and GP fitting."),
    n_samples: int | None = typer.Option(None, help="Override the number of GP samples Q."),
    t_final: float | None = typer.Option(None, help="Override the simulated horizon, s."),
    set_: list[str] = typer.Option(
        [],
        "--set",
        help="Override a scenario key, TABLE.KEY=VALUE (a TOML value), checked like the "
        "file; repeatable, e.g. --set starts.n_x1=3.",
    ),
    debug: bool = typer.Option(False, "--debug", help="Show the traceback of an error."),
) -> None:
    """Run any scenario's study, dispatching on its kind (ACC or obstacle).

    ACC writes OUT/acc_<name>.png, .pdf, _metrics.json; obstacle writes
    OUT/obstacle_<name>.png, .pdf (trajectories), OUT/obstacle_<name>_maps.png, .pdf
    (compatibility maps) and OUT/obstacle_<name>_metrics.json; all or none.
    """
    import matplotlib

    matplotlib.use("Agg")
    from ._io import ensure_writable_dir
    from .scenarios import ACCScenario, load, parse_override

    def check_inputs():
        overrides = dict(parse_override(text) for text in set_)
        sc = load(scenario, overrides=overrides).replace(**_overrides(seed, n_samples, t_final))
        return sc, ensure_writable_dir(out, name="--out")

    sc, out_dir = _guard(check_inputs, debug=debug, code=EXIT_BAD_INPUT)
    if isinstance(sc, ACCScenario):
        _acc_outputs(sc, out_dir, debug)
    else:
        _obstacle_outputs(sc, out_dir, debug)


if __name__ == "__main__":
    app()
