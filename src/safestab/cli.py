"""Command line: a thin front end over the public functions."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="safestab: safe stabilization with GP learning.",
)


@app.callback()
def _main() -> None:
    """Safe stabilization with closed-form CLF-CBF formulas and GP learning."""


@app.command()
def acc(
    scenario: str = typer.Option("paper", help="A preset ('paper', 'stress') or a TOML file."),
    out: Path = typer.Option(Path("results"), help="Output folder (created if needed)."),
    seed: int | None = typer.Option(None, help="Seed for data collection and GP fitting."),
    n_samples: int | None = typer.Option(None, help="Override the number of GP samples Q."),
    t_final: float | None = typer.Option(None, help="Override the simulated horizon, s."),
) -> None:
    """Run the ACC study: collect data, fit the GP, simulate three controllers, write outputs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from .errors import ScenarioError
    from .plotting import plot_acc_study
    from .scenarios import load_scenario
    from .scenarios.acc_study import run_study

    console = Console(width=max(100, Console().width))
    try:
        sc = load_scenario(scenario)
    except ScenarioError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=2) from None
    out.mkdir(parents=True, exist_ok=True)
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

        result = run_study(sc, seed=seed, progress=report, n_samples=n_samples, t_final=t_final)
    fig = plot_acc_study(result)
    for ext in ("png", "pdf"):
        fig.savefig(out / f"acc_{sc.name}.{ext}", dpi=200)
    plt.close(fig)
    result.write_metrics(out / f"acc_{sc.name}_metrics.json")

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
    console.print(f"wrote {out}/acc_{sc.name}.png, .pdf and _metrics.json")


@app.command("export")
def export_cmd(
    scenario: str = typer.Option("stress", help="A preset ('paper', 'stress') or a TOML file."),
    out: Path = typer.Option(Path("build"), help="Output folder (created if needed)."),
    controller: str = typer.Option(
        "gp", help="'gp' (GP-corrected, fast cache), 'nominal' or 'true' model."
    ),
    name: str = typer.Option("acc", help="Prefix of the C names and files."),
    precision: str = typer.Option("double", help="'double' or 'float'."),
    cases: int = typer.Option(256, help="Recorded states in the C test harness."),
    n_samples: int | None = typer.Option(None, help="Override the number of GP samples Q."),
    n_inducing: int = typer.Option(32, help="Inducing points of the fast GP cache."),
    seed: int | None = typer.Option(None, help="Seed for data, GP fit and recorded states."),
    check: bool = typer.Option(True, help="Compile and run the harness (needs a C compiler)."),
) -> None:
    """Export an ACC controller step as C99 (name.c, name.h) with a C test harness."""
    from rich.console import Console

    from .errors import SafeStabError
    from .export.scenario_export import export_scenario

    console = Console()
    try:
        report = export_scenario(
            scenario,
            out,
            controller=controller,
            name=name,
            precision=precision,
            cases=cases,
            n_samples=n_samples,
            n_inducing=n_inducing,
            seed=seed,
            check=check,
            progress=lambda msg: console.print(msg),
        )
    except SafeStabError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=2) from None
    for path in report.files:
        console.print(f"wrote {path}")
    console.print(f"build the harness: {report.build_command}")
    if report.harness_output is not None:
        console.print(report.harness_output.rstrip())
        if not report.passed:
            console.print("[red]the harness found mismatches[/red]")
            raise typer.Exit(code=1)


if __name__ == "__main__":
    app()
