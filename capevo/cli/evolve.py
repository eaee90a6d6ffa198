"""``capevo evolve``: the closed loop on one task, with a progress display and a report at the end.

Embedded by default: a local registry directory (``--root``, default ``./capevo-data``), the
runtime and the learner in this process; nothing to start first. ``--connect ENDPOINT`` uses
a running registry server and runtime workers instead (see :mod:`capevo.evolve.run`).

Invariants:
1. A :class:`CapevoError` ends the command with one ``error [code]: message`` line on stderr
   and the exit code of :data:`capevo.cli.EXIT_CODES` (14 for an identity violation).
2. Ctrl-C or SIGTERM exits 130 after closing the registry, the runtime and the learner;
   finished iterations are on disk and the same command resumes after them.
3. With ``--json`` stdout holds exactly one JSON document (the run's summary); progress and
   messages go to stderr.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
from pathlib import Path
from types import FrameType
from typing import Any

import click

from capevo.cli import (
    DEFAULT_ROOT,
    EXIT_INTERRUPTED,
    LOG_FORMAT,
    identity_option,
    log_level_option,
    login_options,
    make_table,
    phi_option,
    remember_password,
    report_error,
    resolve_target,
    stdout_console,
)
from capevo.errors import CapevoError

# Spelled out here so that `capevo --help` does not import scipy through capevo.evolve.config;
# tests/cli/test_cli_choices.py holds them equal to config_names() and config.MODALITIES.
PRESETS = ("tiny", "cpu-small", "paper")
MODALITIES = ("code", "rl", "il", "hybrid", "il+rl", "hybrid+rl", "hybrid+il", "hybrid+il+rl")


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


@click.command("evolve", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--task", required=True, help="Task: T1..T6 or its name (pick, place, stack, ...).")
@click.option("--iterations", type=click.IntRange(min=0), default=None, help="Iterations. [default: the preset's]")
@click.option("--preset", type=click.Choice(PRESETS), default="cpu-small", show_default=True, help="Budget preset.")
@click.option(
    "--live-episodes",
    type=click.IntRange(min=1),
    default=None,
    help="Live episodes per iteration; iteration 0's seeds are also the final evaluation's. [default: the preset's]",
)
@click.option(
    "--gate-extension",
    type=click.IntRange(min=0),
    default=None,
    help="Paired seeds of the gate's second look: a candidate ahead but not significantly so on the first N "
    "seeds is judged again on N + this many; each look then tests at alpha/2. 0: one look. [default: the preset's]",
)
@click.option(
    "--updates-per-iteration",
    type=click.IntRange(min=0),
    default=None,
    help="ECMs one iteration may learn in sequence, each behind the previous ones' candidates (code and hybrid); "
    "0: one per step of the task. [default: the preset's]",
)
@click.option(
    "--modality",
    type=click.Choice(MODALITIES),
    default="code",
    show_default=True,
    help="How candidates are learned: code (CEM over a skill's parameters), rl (SAC), il (behaviour cloning), "
    "hybrid (LLM edit + CEM; CEM alone without CAPEVO_LLM_BASE_URL). rl/il seed neural v0 ECMs. "
    "A combination (il+rl, hybrid+rl, hybrid+il, hybrid+il+rl) takes turns, one modality per iteration "
    "and one ECM each; with hybrid in it, v0 is the code skill and il clones the set's successes into a "
    "neural version that the gate weighs against it.",
)
@click.option(
    "--root",
    type=click.Path(file_okay=False, path_type=str),
    envvar="CAPEVO_ROOT",
    default=DEFAULT_ROOT,
    show_default=True,
    help="Local registry directory (embedded mode; env CAPEVO_ROOT).",
)
@click.option(
    "--connect",
    multiple=True,
    metavar="ENDPOINT",
    envvar="CAPEVO_CONNECT",
    help="Use the registry server at ENDPOINT (e.g. tcp/127.0.0.1:7447) and its runtime workers instead of the "
    "embedded registry and runtime; repeatable (env CAPEVO_CONNECT).",
)
@login_options
@click.option(
    "--timeout",
    type=click.FloatRange(min=0.01),
    default=10.0,
    show_default=True,
    help="Seconds to wait for each registry reply (with --connect).",
)
@click.option(
    "--report-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Report, metrics, traces and resume state. [default: ./capevo-reports/<task>]",
)
@click.option(
    "--learner",
    type=click.Choice(["local", "remote"]),
    default="local",
    show_default=True,
    help="local: learn in this process; remote (needs --connect): gate candidates that learner workers "
    "(capevo learner serve) publish.",
)
@click.option(
    "--learner-timeout",
    type=click.FloatRange(min=0.0),
    default=600.0,
    show_default=True,
    help="With --learner remote: seconds one iteration waits for a candidate.",
)
@click.option(
    "--worker-wait",
    type=click.FloatRange(min=0.0),
    default=120.0,
    show_default=True,
    help="With --connect: seconds to wait for a runtime worker of the task to serve.",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Seed plan: disjoint training, gate and live seeds; learners' samplers.",
)
@click.option(
    "--perturbations/--no-perturbations",
    default=True,
    show_default=True,
    help="Object jitter, observation noise and dropped actions (the benchmark setting).",
)
@phi_option
@identity_option
@click.option(
    "--tie-siblings",
    is_flag=True,
    help="Search one parameter set for an ECM and its siblings, the same skill for another object "
    "(T5: milk, bread and can share each step's parameters); --modality code only.",
)
@click.option("--report-only", is_flag=True, help="Only rewrite the report of the run in --report-dir.")
@click.option("--json", "as_json", is_flag=True, help="Print the run's summary as JSON on stdout.")
@log_level_option()
def evolve(
    task: str,
    iterations: int | None,
    preset: str,
    live_episodes: int | None,
    gate_extension: int | None,
    updates_per_iteration: int | None,
    modality: str,
    root: str,
    connect: tuple[str, ...],
    namespace: str,
    user: str | None,
    password: str | None,
    timeout: float,
    report_dir: Path | None,
    learner: str,
    learner_timeout: float,
    worker_wait: float,
    seed: int,
    perturbations: bool,
    phi: str,
    identity_path: Path | None,
    tie_siblings: bool,
    report_only: bool,
    as_json: bool,
    log_level: str,
) -> None:
    """Evolve the ECMs of --task: execute, collect experience, learn, gate, promote or roll back.

    \b
    Each iteration runs live episodes under governance (MCAP traces, episodic memory), picks
    the ECM where failed episodes ended, learns a candidate on training seeds, gates it against
    the active version on paired held-out seeds, and promotes or rejects it; a degradation
    monitor rolls back versions whose live success drops. The agent's identity hash is checked
    every iteration (exit 14 if it changed). Metrics are fsynced per iteration: rerun the same
    command after a crash or Ctrl-C to continue. At the end, --report-dir holds report.md,
    metrics.csv and PNG plots.

    \b
    --connect ENDPOINT: the registry is the server at ENDPOINT and episodes run on runtime
    workers (capevo runtime serve --connect ENDPOINT --task T --idle); the learner runs here,
    or, with --learner remote, learner workers publish candidates and this command gates them.
    """
    ctx = click.get_current_context()
    remember_password(password)
    # Our own loggers only: robosuite has its own console handler (a root handler doubles its lines).
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    capevo_log = logging.getLogger("capevo")
    capevo_log.addHandler(handler)
    capevo_log.setLevel(log_level.upper())
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        code = _run(
            ctx,
            task=task,
            iterations=iterations,
            preset=preset,
            live_episodes=live_episodes,
            gate_extension=gate_extension,
            updates_per_iteration=updates_per_iteration,
            modality=modality,
            root=root,
            connect=connect,
            namespace=namespace,
            user=user,
            password=password,
            timeout=timeout,
            report_dir=report_dir,
            learner=learner,
            learner_timeout=learner_timeout,
            worker_wait=worker_wait,
            seed=seed,
            perturbations=perturbations,
            phi=phi,
            identity_path=identity_path,
            tie_siblings=tie_siblings,
            report_only=report_only,
            as_json=as_json,
        )
    finally:
        signal.signal(signal.SIGTERM, previous)
    ctx.exit(code)


def _quiet_robosuite() -> None:
    # robosuite's import sets its logger's level, so import it before quieting it; otherwise its
    # controller-config warnings repeat on every environment reset.
    import robosuite  # noqa: F401

    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)


def _run(ctx: click.Context, **kw: Any) -> int:
    from capevo.evolve.progress import RichProgress
    from capevo.evolve.run import EvolveOptions, run_evolution, write_report_for

    try:
        root_path, endpoints = resolve_target(
            root=kw["root"],
            root_source=ctx.get_parameter_source("root"),
            connect=kw["connect"],
            connect_source=ctx.get_parameter_source("connect"),
        )
        options = EvolveOptions(
            task=kw["task"],
            preset=kw["preset"],
            iterations=kw["iterations"],
            live_episodes=kw["live_episodes"],
            gate_extension=kw["gate_extension"],
            updates_per_iteration=kw["updates_per_iteration"],
            tie_siblings=kw["tie_siblings"],
            root=root_path if root_path is not None else Path(DEFAULT_ROOT),
            connect=endpoints,
            namespace=kw["namespace"],
            user=kw["user"] or None,
            password=kw["password"] or None,
            timeout=kw["timeout"],
            report_dir=kw["report_dir"],
            modality=kw["modality"],
            seed=kw["seed"],
            perturbations=kw["perturbations"],
            phi=kw["phi"],
            learner=kw["learner"],
            learner_timeout_s=kw["learner_timeout"],
            wait_for_worker_s=kw["worker_wait"],
            identity_path=kw["identity_path"],
        )
        if kw["report_only"]:
            files = write_report_for(options)
            _print_files(files, kw["as_json"])
            return 0
        if logging.getLogger("capevo").level > logging.DEBUG:
            _quiet_robosuite()
        result = run_evolution(options, progress=RichProgress())
    except CapevoError as err:
        return report_error(err)
    except KeyboardInterrupt:
        click.echo(
            "error [interrupted]: interrupted; finished iterations are saved, run the same command again to resume",
            err=True,
        )
        return EXIT_INTERRUPTED
    _print_result(result, kw["as_json"])
    return 0


def _print_files(files: list[Path], as_json: bool) -> None:
    if as_json:
        click.echo(json.dumps({"files": [str(f) for f in files]}, indent=2))
    else:
        for f in files:
            click.echo(str(f))


def summary_dict(result: Any) -> dict[str, Any]:
    """The JSON summary ``--json`` prints for a finished run."""
    rows = result.rows
    start = rows[0].live if rows else None
    final = result.final
    from capevo.evolve.metrics import outcome_stats, split_monitor_actions

    fstats = outcome_stats(list(final.final)) if final is not None else None
    actions = split_monitor_actions([rb for r in rows for rb in r.rollbacks])
    return {
        "task": result.task,
        "report_dir": str(result.report_dir),
        "iterations": len(rows),
        "resumed_from": result.resumed_from,
        "identity_hash": result.identity_hash,
        "delta_pi": result.delta_pi,
        "created_v0": [f"{r.name}@{r.version}" for r in result.created],
        "start": start.to_dict() if start else None,
        "start_versions": dict(rows[0].active_versions) if rows else None,
        "final": fstats.to_dict() if fstats else None,
        "final_versions": dict(final.final_versions) if final is not None else None,
        "gate": [{"iteration": r.iteration, **g.to_dict()} for r in rows for g in r.gates],
        # not confirmed: the monitor's screen fired but the replaced version did no better on the same seeds
        "rollbacks": actions[0],
        "monitor_not_confirmed": actions[1],
        "wall_s": result.wall_s,
        "files": [str(f) for f in result.report_files],
    }


def _print_result(result: Any, as_json: bool) -> None:
    data = summary_dict(result)
    if as_json:
        click.echo(json.dumps(data, indent=2, default=str))
        return
    console = stdout_console()
    table = make_table("", "value")
    table.add_row("task", data["task"])
    table.add_row("iterations", f"{data['iterations']} (resumed after {data['resumed_from']})")
    if data["start"]:
        s = data["start"]
        table.add_row("start success", f"{s['successes']}/{s['episodes']} (iteration 0 live seeds)")
    if data["final"]:
        f = data["final"]
        table.add_row("final success", f"{f['successes']}/{f['episodes']} (same seeds)")
    decisions = [f"it{g['iteration']}: {g['decision']} {g['ecm']} v{g['candidate_version']}" for g in data["gate"]]
    table.add_row("gate", "; ".join(decisions) or "-")
    kept = len(data["monitor_not_confirmed"])
    table.add_row("rollbacks", str(len(data["rollbacks"])) + (f" ({kept} drops not confirmed)" if kept else ""))
    table.add_row("identity hash", data["identity_hash"])
    table.add_row("Δπ", f"{data['delta_pi']:g}")
    table.add_row("wall time", f"{data['wall_s']:.0f} s")
    table.add_row("report", str(Path(data["report_dir"]) / "report.md"))
    console.print(table)


if __name__ == "__main__":
    evolve(prog_name="capevo evolve")
