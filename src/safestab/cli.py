"""Command line: a thin front end over the public functions.

Every command checks its inputs before any work: the scenario (every key, when the file is
loaded), the command-line overrides (checked like the file) and the output folder (created if
missing, and proved writable by creating and removing a probe file). Outputs are written all
or none, each atomically (``safestab._io.write_all``): a failed run leaves the output folder
as it was. An error prints one line, ``error: <class>: <message>``, to stderr and exits
non-zero (2 for bad input, 1 for a failure during the run); ``--debug`` adds the traceback.
"""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import typer

from .controller_names import CONTROLLERS, EXPORT_CHOICES

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
def _main(
    no_compilation_cache: bool = typer.Option(
        False,
        "--no-compilation-cache",
        help="Do not read or write JAX's persistent compilation cache (on by default in "
        "~/.cache/safestab/jax, or $SAFESTAB_COMPILATION_CACHE; safe to delete).",
    ),
    no_fit_cache: bool = typer.Option(
        False,
        "--no-fit-cache",
        help="Fit every GP afresh: do not read or write the GP fit cache (on by default in "
        "~/.cache/safestab/fits, or $SAFESTAB_FIT_CACHE; safe to delete).",
    ),
) -> None:
    """Safe stabilization with closed-form CLF-CBF formulas and GP learning."""
    import warnings

    warnings.formatwarning = _format_warning  # one line, no path into the installed package
    # an old controller name in a file or an option: shown at the command line, which
    # Python's default filters would hide (a DeprecationWarning outside __main__)
    warnings.filterwarnings("default", ".*the controller name", DeprecationWarning)
    if no_compilation_cache:
        from ._cache import disable_compilation_cache

        disable_compilation_cache()
    if no_fit_cache:
        import os

        from .learning._fit_cache import disable_fit_cache

        disable_fit_cache()
        os.environ["SAFESTAB_FIT_CACHE"] = "off"  # worker processes (Ray) read it at import


def _format_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    line: str | None = None,
) -> str:
    """A warning at the command line: ``warning: <Category>: <message>`` on one line.

    The default format leads with the file and line inside safestab that raised it, which
    tells a user of the command nothing (and shows an internal path).
    """
    return f"warning: {category.__name__}: {' '.join(str(message).split())}\n"


def _one_line(exc: BaseException) -> str:
    """``<class>: <message>`` on one line (whitespace collapsed, long messages cut).

    The exception's notes (``add_note``: another error met on the way, say) follow the
    message in brackets.
    """
    notes = [str(n) for n in getattr(exc, "__notes__", ()) or ()]
    message = " ".join(" ".join([str(exc), *(f"[{n}]" for n in notes)]).split())
    if len(message) > _MAX_MESSAGE:
        message = message[: _MAX_MESSAGE - 40] + " ... (cut; --debug shows all)"
    return f"error: {type(exc).__name__}: {message}" if message else f"error: {type(exc).__name__}"


def _guard(
    step: Callable[[], T], *, debug: bool, code: int, input_errors: tuple[type, ...] = ()
) -> T:
    """Run one step of a command; on an exception print one line (or the traceback) and exit.

    Exceptions of the types ``input_errors`` exit with :data:`EXIT_BAD_INPUT` instead of
    ``code`` (an argument found bad only once the step has started, say against a cluster).
    """
    try:
        return step()
    except Exception as exc:
        if debug:
            typer.echo(traceback.format_exc().rstrip(), err=True)
        typer.echo(_one_line(exc), err=True)
        bad_input = isinstance(exc, input_errors)
        raise typer.Exit(code=EXIT_BAD_INPUT if bad_input else code) from None


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


def _study_outputs(sc, out_dir: Path, debug: bool) -> None:
    """Run a scenario's study through the pipeline, write its outputs, print its summary."""
    from rich.table import Table
    from rich.text import Text

    from .scenarios import kinds

    study = kinds.study_of(sc)
    console = _console(width=study.table_width)
    done = _guard(
        lambda: _with_progress(console, lambda r: kinds.run(sc, out_dir, progress=r)),
        debug=debug,
        code=EXIT_RUN_FAILED,
    )
    summary = _guard(done.summary, debug=debug, code=EXIT_RUN_FAILED)
    # plain text, not markup: the units in the headers ("min h [m]") are not style tags
    table = Table(title=Text(summary.title))
    for i, col in enumerate(summary.columns):
        # the last column (statuses, c*) may wrap in a narrow terminal
        table.add_column(Text(col), justify="right", no_wrap=i < len(summary.columns) - 1)
    for row in summary.rows:
        table.add_row(*map(Text, row))
    console.print(table)
    for line in summary.lines:
        console.print(line, markup=False, soft_wrap=True)
    _print_written(console, done.written)


def _print_written(console: Any, written: list[Path]) -> None:
    """Name the files written (the run record last) and the folder's other runs, if any."""
    from .scenarios import pipeline

    console.print(f"wrote {', '.join(str(p) for p in written)}", markup=False, soft_wrap=True)
    note = pipeline.other_runs(written[-1].parent, written[-1])
    if note:
        console.print(f"note: {note}", markup=False, soft_wrap=True)


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
    from .scenarios import kinds, load_scenario

    # -- checks, before any work ----------------------------------------------------------
    def check_inputs():
        sc = kinds.with_overrides(
            load_scenario(scenario), seed=seed, n_samples=n_samples, t_final=t_final
        )
        return sc, ensure_writable_dir(out, name="--out")

    sc, out_dir = _guard(check_inputs, debug=debug, code=EXIT_BAD_INPUT)
    _study_outputs(sc, out_dir, debug)


@app.command()
def run(
    scenario: list[str] = typer.Option(
        ...,
        help="A preset ('paper', 'stress', 'stress-ood', 'paper-limited', 'stress-limited', "
        "'obstacle', 'swarm') or a TOML file "
        "(its kind key); repeatable: the studies of one kind run one after another in one "
        "process, which compiles the programs they share once (other kinds: --jobs).",
    ),
    out: Path = typer.Option(Path("results"), help="Output folder (created if needed)."),
    seed: int | None = typer.Option(
        None, help="Seed for data collection and GP fitting (the swarm: its start jitter)."
    ),
    n_samples: int | None = typer.Option(None, help="Override the number of GP samples Q."),
    t_final: float | None = typer.Option(None, help="Override the simulated horizon, s."),
    set_: list[str] = typer.Option(
        [],
        "--set",
        help="Override a scenario key, TABLE.KEY=VALUE (a TOML value), checked like the "
        "file; repeatable, e.g. --set starts.n_x1=3.",
    ),
    jobs: int | None = typer.Option(
        None,
        "--jobs",
        min=1,
        help="Processes that run studies at once (default: one per CPU, at most one per "
        "kind). The studies of one kind always share a process and run in the order given; "
        "1 runs every study in this process, one after another.",
    ),
    debug: bool = typer.Option(False, "--debug", help="Show the traceback of an error."),
) -> None:
    """Run any scenario's study through the study pipeline, by its kind (ACC, obstacle, swarm).

    Writes OUT/<kind>_<name>.png, .pdf (the obstacle also _maps.png, .pdf), _metrics.json and
    _run.json (the record of the run), all or none per scenario. The swarm learns nothing:
    --n-samples is refused for it, and --seed seeds its start jitter. With several
    --scenario, every scenario and override is checked before any work and the options apply
    to each. The studies of one kind run in one process, in the order given (they share
    compiled programs). Studies of different kinds run in up to --jobs processes at once:
    this one shows its progress, the others' output is printed after this one's studies, in
    order. In each process a failed study stops those after it there (their outputs are not
    written; those before it are kept); the command exits non-zero if any study failed,
    after every process has finished. Ctrl-C or SIGTERM stops every process (each finishes
    its writes, all or none, or is killed after 10 s). The results do not depend on --jobs
    (each study computes alone, whichever process runs it).
    """
    import matplotlib

    matplotlib.use("Agg")
    from ._io import ensure_writable_dir
    from .scenarios import kinds, load, parse_override

    def check_inputs():
        overrides = dict(parse_override(text) for text in set_)
        scenarios = [
            kinds.with_overrides(
                load(name, overrides=overrides), seed=seed, n_samples=n_samples, t_final=t_final
            )
            for name in scenario
        ]
        return scenarios, ensure_writable_dir(out, name="--out")

    scenarios, out_dir = _guard(check_inputs, debug=debug, code=EXIT_BAD_INPUT)
    lanes = plan_lanes(scenario, [kinds.study_of(sc).kind for sc in scenarios], jobs)
    options = lane_options(out_dir, seed, n_samples, t_final, set_, debug)
    children: list[Lane] = []
    first_failure = None
    # with other processes, SIGTERM too stops them before this one exits
    with terminate_as_exit() if len(lanes) > 1 else contextlib.nullcontext():
        try:
            for names in lanes[1:]:  # one by one: a failed start still stops those started
                children.append(start_lane(names, options))
            try:
                for name, sc in zip(scenario, scenarios, strict=True):
                    if name in lanes[0]:
                        _study_outputs(sc, out_dir, debug)
            except typer.Exit as exc:  # the other processes still finish their studies
                first_failure = exc.exit_code
            codes = [finish_lane(child) for child in children]
        except BaseException:  # interrupted, or a process could not start: stop the others
            for child in children:
                child.stop()
            raise
    failed = [code for code in [first_failure, *codes] if code]
    if failed:
        raise typer.Exit(code=failed[0])


@contextlib.contextmanager
def terminate_as_exit():
    """While inside, SIGTERM raises ``SystemExit(143)`` in the main thread, as Ctrl-C does.

    Python's default for SIGTERM ends the process at once, with no ``except`` or ``finally``
    run: ``safestab run`` would leave its other processes running (and writing outputs)
    after it was stopped by a job scheduler or ``kill``. Raised as an exception, it stops
    them first. Outside the main thread (where no handler can be set), nothing changes.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        # once: a second SIGTERM while the other processes are being stopped (up to 10 s
        # each) must not interrupt that and leave the rest running
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        # None: a handler set from C, which Python cannot put back (then the default)
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def plan_lanes(
    names: list[str], kinds: list[str], jobs: int | None, cpus: int | None = None
) -> list[list[str]]:
    """The scenarios of each process of ``safestab run``, this one's first, each in order.

    The kinds, in order of first appearance, are dealt round-robin to ``min(kinds, jobs)``
    processes (``jobs`` default: ``cpus``, default the CPUs this process may use).
    """
    if jobs is None:
        from ._batching import cpu_count

        jobs = cpus if cpus is not None else cpu_count()
    order = list(dict.fromkeys(kinds))
    n = max(1, min(len(order), jobs))
    lane_of = {kind: i % n for i, kind in enumerate(order)}
    return [
        [name for name, kind in zip(names, kinds, strict=True) if lane_of[kind] == i]
        for i in range(n)
    ]


def lane_options(out_dir, seed, n_samples, t_final, set_, debug) -> list[str]:
    """The options of ``safestab run`` that a process running some of its scenarios takes."""
    options = ["--out", str(out_dir), "--jobs", "1"]
    for flag, value in (("--seed", seed), ("--n-samples", n_samples), ("--t-final", t_final)):
        if value is not None:
            options += [flag, repr(value)]
    for text in set_:
        options += ["--set", text]
    return options + (["--debug"] if debug else [])


class Lane:
    """A process running some scenarios (``safestab run ... --jobs 1``), its output in files."""

    #: Seconds a stopped process has to finish writing (its outputs all or none) before it
    #: is killed.
    STOP_SECONDS = 10.0

    def __init__(self, names: list[str], process: Any, stdout: Any, stderr: Any) -> None:
        self.names, self.process, self.stdout, self.stderr = names, process, stdout, stderr

    def stop(self) -> None:
        """Interrupt the process (as Ctrl-C would), kill it if it lingers; close its files."""
        import signal
        import subprocess

        try:
            if self.process.poll() is None:
                self.process.send_signal(signal.SIGINT)
                try:
                    self.process.wait(timeout=self.STOP_SECONDS)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
        finally:
            self.stdout.close()
            self.stderr.close()


def lane_command(names: list[str], options: list[str]) -> list[str]:
    """The command line of a process that runs ``names`` (a separate function: tests swap it)."""
    import sys

    scenarios = [arg for name in names for arg in ("--scenario", name)]
    return [sys.executable, "-m", "safestab.cli", "run", *scenarios, *options]


def lane_environment(
    environ: Mapping[str, str], compilation_cache: Path | None, fit_cache: Path | None
) -> dict[str, str]:
    """``environ`` with the cache variables set to the folders this process uses (None: off).

    A process started by ``safestab run`` then uses this one's caches whatever set them
    (``--no-compilation-cache``, ``--no-fit-cache``, the environment, or Python).
    """
    from ._cache import child_cache_environment

    return {**environ, **child_cache_environment(compilation_cache, fit_cache)}


def start_lane(names: list[str], options: list[str]) -> Lane:
    """Start a process for ``names``, with this process's caches (or none) and environment."""
    import os
    import subprocess
    import tempfile

    from ._cache import compilation_cache_dir
    from .learning._fit_cache import fit_cache_dir

    env = lane_environment(os.environ, compilation_cache_dir(), fit_cache_dir())
    stdout, stderr = tempfile.TemporaryFile(), tempfile.TemporaryFile()
    try:
        process = subprocess.Popen(
            lane_command(names, options), stdout=stdout, stderr=stderr, env=env
        )
    except BaseException:
        stdout.close()
        stderr.close()
        raise
    typer.echo(
        f"running {', '.join(names)} in another process: its output follows this one's studies"
    )
    return Lane(names, process, stdout, stderr)


def finish_lane(lane: Lane) -> int:
    """Wait for a lane's process, print its output; its exit code."""
    code = lane.process.wait()
    for fh, err in ((lane.stdout, False), (lane.stderr, True)):
        fh.seek(0)
        text = fh.read().decode(errors="replace")
        fh.close()  # stop() closes it again: a no-op
        if text:
            typer.echo(text, nl=not text.endswith("\n"), err=err)
    if code < 0:  # ended by a signal: no line of its own says so
        typer.echo(
            f"error: the process running {', '.join(lane.names)} ended by signal {-code}", err=True
        )
        return EXIT_RUN_FAILED
    return code


@app.command("export")
def export_cmd(
    scenario: str = typer.Option(
        "stress", help="A preset ('paper', 'stress', 'obstacle') or a TOML file."
    ),
    out: Path = typer.Option(Path("build"), help="Output folder (created if needed)."),
    controller: str = typer.Option(
        "gp",
        help=", ".join(f"'{short}' ('{name}')" for short, name in EXPORT_CHOICES.items())
        + ", by either name; 'gp' through the fast GP cache.",
    ),
    name: str | None = typer.Option(
        None, help="Prefix of the C names and files (default 'acc' or 'obstacle')."
    ),
    precision: str | None = typer.Option(
        None, help="'double' or 'float' (default: the target's, else 'double')."
    ),
    cases: int = typer.Option(256, help="Recorded states in the C test harness."),
    n_samples: int | None = typer.Option(None, help="Override the number of GP samples Q."),
    n_inducing: int = typer.Option(32, help="Inducing points of the fast GP cache."),
    seed: int | None = typer.Option(None, help="Seed for data, GP fit and recorded states."),
    check: bool = typer.Option(True, help="Compile and run the harness (needs a C compiler)."),
    target: str | None = typer.Option(
        None,
        help="Also build for 'cortex-m4' (float) or 'cortex-m7' (double), run the harness "
        "under QEMU and measure size, stack and instructions per step (docs/export.md).",
    ),
) -> None:
    """Export an ACC or obstacle controller step as C99 (name.c, name.h) with a C harness."""
    from rich.console import Console

    from .errors import SafeStabError
    from .scenarios.export_study import export_scenario

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
            check=check or target is not None,
            target=target,
            progress=lambda msg: console.print(msg),
        )
    except SafeStabError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=2) from None
    for note in report.notes:
        console.print(f"[yellow]note:[/yellow] {note}")
    for path in report.files:
        console.print(f"wrote {path}")
    console.print(f"build the harness: {report.build_command}")
    if report.harness_output is not None:
        console.print(report.harness_output.rstrip())
        if not report.passed:
            console.print("[red]the harness found mismatches[/red]")
            raise typer.Exit(code=1)
    if report.embedded is not None:
        _print_embedded(console, report.embedded)
        if report.embedded.harness_mismatches:
            console.print("[red]the harness found mismatches on the target[/red]")
            raise typer.Exit(code=1)


def _print_embedded(console: Any, rep: Any) -> None:
    """The embedded build's measurements as a table (safestab export --target)."""
    from rich.table import Table

    budget = 168_000  # instructions in 1 ms at 168 MHz
    table = Table(title=f"{rep.target} ({rep.precision}) under QEMU", show_header=False)
    rows = [
        ("harness on the target vs JAX", f"{rep.harness_mismatches} mismatches / {rep.states}"),
        ("outputs bit-identical to the host build", f"{rep.bit_identical_to_host} / {rep.states}"),
        ("step object: code + constants (flash)", f"{rep.step_text:,} B"),
        ("minimal firmware image: flash / static RAM", f"{rep.firmware_flash:,} B / "
         f"{rep.firmware_ram:,} B"),
        ("stack: static call graph / measured", f"{rep.stack_static:,} B / "
         f"{rep.stack_measured:,} B"),
        ("instructions per step: max / median", f"{rep.instructions_max:,} / "
         f"{rep.instructions_median:,}"),
        ("headroom at 168 MHz, 1 kHz (168,000 / max)", f"{budget / rep.instructions_max:.1f}x"),
        ("library calls", ", ".join(rep.library_calls) or "none"),
    ]  # fmt: skip
    for key, value in rows:
        table.add_row(key, value)
    console.print(table)


@app.command("mc")
def mc(
    scenario: str = typer.Option(
        "stress",
        help="A preset ('paper', 'stress', 'stress-ood', 'paper-limited', 'stress-limited', "
        "'obstacle', 'swarm') or a TOML file "
        "(an ACC or obstacle file's \\[montecarlo] table, if any, sets the trials).",
    ),
    trials: int | None = typer.Option(
        None, help="Number of trials N (default: the file's; the swarm: 32)."
    ),
    datasets: int | None = typer.Option(
        None, help="Independent data sets K (default: file's); not for the swarm."
    ),
    backend: str = typer.Option("local", help="'local' or 'ray' (the swarm: 'local')."),
    address: str | None = typer.Option(None, help="Ray cluster address (else RAY_ADDRESS)."),
    chunk_size: int | None = typer.Option(None, help="Trials per compiled batch."),
    controllers: str | None = typer.Option(
        None,
        help="Comma-separated controllers to compare (default: the file's), from: "
        + ", ".join(CONTROLLERS)
        + "; for the swarm, its modes: centralized, decentralized, unfiltered (default: all).",
    ),
    workers: int | None = typer.Option(
        None,
        help="Chunks (and data sets) run at once in threads of a process: local (default 2 "
        "on 2+ CPUs), or of each Ray task, which asks for as many CPUs (default: the "
        "smallest node's CPUs).",
    ),
    out: Path = typer.Option(Path("results"), help="Output folder (created if needed)."),
    seed: int = typer.Option(0, help="Seed: trial i depends on (seed, i) only."),
    debug: bool = typer.Option(False, "--debug", help="Show the traceback of an error."),
) -> None:
    """Monte Carlo of any scenario's study, by its kind: safety rates with 95 % intervals.

    Writes OUT/mc_<name>.png, _metrics.json, _trials.npz and _run.json, all or none.
    """
    import matplotlib

    matplotlib.use("Agg")
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from ._io import ensure_writable_dir
    from .errors import ParameterError
    from .scenarios import kinds, load
    from .scenarios.pipeline import MonteCarloOptions

    def check_inputs():
        sc = load(scenario)
        names = None if controllers is None else tuple(n.strip() for n in controllers.split(","))
        options = MonteCarloOptions(
            trials=trials, datasets=datasets, backend=backend, address=address,
            chunk_size=chunk_size, controllers=names, workers=workers, seed=seed,
        )  # fmt: skip
        # every option is checked here, before any work (kinds.check_mc_options and the
        # kind's plan)
        plan = kinds.plan_mc(sc, options, name="--scenario")
        return plan, ensure_writable_dir(out, name="--out")

    plan, out_dir = _guard(check_inputs, debug=debug, code=EXIT_BAD_INPUT)
    console = Console(width=max(100, Console().width))

    def run():
        with Progress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), TimeRemainingColumn(), console=console,
        ) as progress:  # fmt: skip
            tasks = plan.study.montecarlo.tasks
            bars = {name: progress.add_task(name, total=None) for name in tasks}

            def report(task: str, done: int, total: int) -> None:
                progress.update(bars[task], completed=done, total=total)

            return kinds.run_mc(plan, out_dir, progress=report)

    # a --workers beyond the Ray cluster's largest node is found once Ray is connected
    done = _guard(run, debug=debug, code=EXIT_RUN_FAILED, input_errors=(ParameterError,))
    Console().print(done.montecarlo_table())  # the terminal's own width
    _print_written(console, done.written)


if __name__ == "__main__":
    app()
