"""``capevo experiment run|report|verify``: grids of tasks × methods × seeds on Ray, their report, and
the check that every number of the report recomputes from the raw metrics (issue 20).

``run CONFIG`` takes a YAML path, a packaged config (``h1``, ``h2``, ``h3``, ``ablation-t3``) or a
preset (``smoke``, ``cpu-small``, ``paper``); it starts a local Ray instance with ``--workers``
CPUs (``--address`` joins a cluster instead), resumes a run directory that has finished cells,
and writes the report at the end (:mod:`capevo.experiment.runner`).

Invariants:
1. A :class:`CapevoError` ends the command with one ``error [code]: message`` line on stderr and
   the exit code of :data:`capevo.cli.EXIT_CODES`.
2. ``verify`` exits 0 only when every number recomputes; otherwise it prints each mismatch and
   exits 1. ``run`` exits 1 when a cell failed (the others are on disk).
3. Ctrl-C or SIGTERM exits 130; finished cells are on disk and the same command resumes.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
from pathlib import Path
from types import FrameType

import click

from capevo.cli import EXIT_INTERRUPTED, report_error
from capevo.errors import CapevoError


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


@click.group("experiment", context_settings={"help_option_names": ["-h", "--help"]})
def experiment() -> None:
    """Run experiment grids (tasks × methods × seeds) on Ray, report them, verify the report."""


@experiment.command("run")
@click.argument("config")
@click.option(
    "--out",
    "run_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Run directory (resumed when it holds finished cells). [default: ./capevo-experiments/<name>]",
)
@click.option("--workers", type=click.IntRange(min=1), default=2, show_default=True, help="CPUs of the local Ray.")
@click.option("--address", default=None, help="Join a Ray cluster (ray://HOST:10001 or auto) instead.")
@click.option(
    "--retries", type=click.IntRange(min=0), default=1, show_default=True, help="Further attempts of a failing cell."
)
@click.option(
    "--work-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Where cells work on their host, kept so an interrupted cell resumes. [default: <tmp>/capevo-work/<key>]",
)
@click.option("--no-report", is_flag=True, help="Do not write the report at the end.")
@click.option("--json", "as_json", is_flag=True, help="Print the run's summary as JSON on stdout.")
def run(
    config: str,
    run_dir: Path | None,
    workers: int,
    address: str | None,
    retries: int,
    work_dir: Path | None,
    no_report: bool,
    as_json: bool,
) -> None:
    """Run (or resume) the grid CONFIG: a YAML file, a packaged config or a preset."""
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        code = _run(config, run_dir, workers, address, retries, work_dir, no_report, as_json)
    finally:
        signal.signal(signal.SIGTERM, previous)
    sys.exit(code)


def _run(
    source: str,
    run_dir: Path | None,
    workers: int,
    address: str | None,
    retries: int,
    work_dir: Path | None,
    no_report: bool,
    as_json: bool,
) -> int:
    from capevo.experiment.config import load_config
    from capevo.experiment.progress import RichGridProgress
    from capevo.experiment.runner import run_experiment

    logging.getLogger("capevo").setLevel(logging.WARNING)
    try:
        config = load_config(source)
        out = run_dir if run_dir is not None else Path("capevo-experiments") / config.name
        summary = run_experiment(
            config,
            out,
            workers=workers,
            address=address,
            retries=retries,
            work_dir=work_dir,
            progress=RichGridProgress(),
            command=["capevo", "experiment", "run", *sys.argv[sys.argv.index("run") + 1 :]]
            if "run" in sys.argv
            else None,
        )
        files: list[Path] = []
        if not no_report:
            from capevo.experiment.report import write_report

            files = write_report(out)
    except CapevoError as err:
        return report_error(err)
    except KeyboardInterrupt:
        click.echo(
            "error [interrupted]: interrupted; finished cells and iterations are kept, run the same command to resume",
            err=True,
        )
        return EXIT_INTERRUPTED
    data = {
        "run_dir": str(summary.run_dir),
        "done": list(summary.done),
        "skipped": list(summary.skipped),
        "failed": list(summary.failed),
        "wall_s": round(summary.wall_s, 1),
        "report": [str(f) for f in files],
    }
    if as_json:
        click.echo(json.dumps(data, indent=2))
    else:
        click.echo(
            f"{summary.run_dir}: {len(summary.done)} cells run, {len(summary.skipped)} already done, "
            f"{len(summary.failed)} failed, {summary.wall_s:.0f} s"
        )
        for f in files[:1]:
            click.echo(f"report: {f}")
    return 1 if summary.failed else 0


@experiment.command("report")
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
def report(run_dir: Path) -> None:
    """Write RUN_DIR/report/ (Markdown, figures, numbers.json) from the run's files."""
    from capevo.experiment.report import write_report

    try:
        files = write_report(run_dir)
    except CapevoError as err:
        sys.exit(report_error(err))
    for f in files:
        click.echo(str(f))


@experiment.command("verify")
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
def verify(run_dir: Path) -> None:
    """Recompute every number of RUN_DIR's report from the raw metrics; exit 1 on a mismatch."""
    from capevo.experiment.verify import verify_run

    try:
        mismatches = verify_run(run_dir)
    except CapevoError as err:
        sys.exit(report_error(err))
    for m in mismatches:
        click.echo(m, err=True)
    if mismatches:
        click.echo(f"{len(mismatches)} mismatch(es)", err=True)
        sys.exit(1)
    click.echo("ok: every number recomputes from the raw metrics")


if __name__ == "__main__":
    experiment(prog_name="capevo experiment")
