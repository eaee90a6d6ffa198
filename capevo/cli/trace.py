"""``capevo trace ...``: summarize run traces, export experience for learners, salvage crashes.

Commands::

    capevo trace summary FILE [--json]
    capevo trace export FILE... [--episodes [SPEC]] [-o OUT] [--format npz|jsonl] [--ecm NAME]...
                                [--allow-incomplete] [--force] [--json]
    capevo trace recover FILE [-o OUT] [--force] [--json]
    capevo trace blame PATH... [--json]

Invariants:
1. Errors (missing file, not an MCAP file, unfinished file, bad episode selection) print
   one ``error [code]: message`` line on stderr and exit non-zero (the codes of
   :mod:`capevo.cli`), never a traceback; this holds when the group runs on its own too.
2. ``--json`` prints exactly one JSON document on stdout.
3. ``export`` and ``recover`` never replace an existing output without ``--force``.
4. ``blame`` reads only the files it is given (a directory: its ``*.mcap`` files, recursively)
   and judges their failed episodes as ``capevo evolve`` does when it picks the ECM to update
   (:func:`capevo.learner.experience.failure_weights`).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import click
from rich.console import Console

from capevo.cli import CapevoGroup, emit, fmt_opt, json_option, make_table
from capevo.errors import Conflict, Invalid
from capevo.learner.experience import EpisodeEnd, failed_activations, failure_weights, read_episode_ends
from capevo.runtime.tasks import task_spec
from capevo.runtime.traces import TraceReader
from capevo.runtime.traces.export import EXPORT_FORMATS, Transitions, export_transitions, parse_episodes
from capevo.runtime.traces.files import trace_files
from capevo.runtime.traces.recover import RecoverReport, default_output, recover
from capevo.runtime.traces.summary import TraceSummary, summarize

_FILE = click.Path(path_type=Path, dir_okay=True, file_okay=True)


@click.group(cls=CapevoGroup, context_settings={"help_option_names": ["-h", "--help"]})
def trace() -> None:
    """MCAP run traces: per-episode summary, experience export, crash salvage."""


# ---------------------------------------------------------------------------------------
# summary
# ---------------------------------------------------------------------------------------


@trace.command("summary")
@click.argument("file", type=_FILE)
@json_option
def summary_cmd(file: Path, as_json: bool) -> None:
    """Per-episode success, reward and interventions of trace FILE.

    An unfinished file (crashed worker) is summarized from what it holds; episodes without
    a summary record show success '?'.
    """
    summary = summarize(file, allow_incomplete=True)
    emit(as_json, summary.to_dict(), lambda console: _render_summary(console, summary))


def _render_summary(console: Console, s: TraceSummary) -> None:
    m = s.metadata
    state = "complete" if s.complete else "UNFINISHED (run `capevo trace recover` to salvage it)"
    console.print(f"run {m.run_id}  task {m.task}  registry revision {m.registry_revision}  file {state}")
    if not s.episodes:
        console.print("no episodes")
        return
    table = make_table("EPISODE", "SEED", "SUCCESS", "REWARD", "STEPS", "INTERVENTIONS", "UNSAFE", "DURATION_S")
    for e in s.episodes:
        success = "?" if e.success is None else ("yes" if e.success else "no")
        duration = "-" if e.duration_s is None else f"{e.duration_s:.2f}"
        table.add_row(
            str(e.episode),
            fmt_opt(e.seed),
            success,
            f"{e.total_reward:.3f}",
            str(e.steps),
            str(e.interventions),
            fmt_opt(e.unsafe_steps),
            duration,
        )
    console.print(table)
    rate = s.success_rate
    finished = sum(e.finished for e in s.episodes)
    console.print(
        f"{len(s.episodes)} episodes ({finished} finished), success rate "
        + ("-" if rate is None else f"{100 * rate:.1f}%")
        + f", {sum(e.interventions for e in s.episodes)} interventions"
    )


# ---------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------


@trace.command("export")
@click.argument("files", nargs=-1, required=True, type=_FILE)
@click.option(
    "--episodes",
    "episodes",
    is_flag=False,
    flag_value="all",
    default="all",
    show_default=True,
    metavar="[SPEC]",
    help="Episodes to export: 'all', or indices and ranges like 0,3,5-9.",
)
@click.option("-o", "--output", type=click.Path(path_type=Path), default=None, help="Output file.")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(EXPORT_FORMATS),
    default=None,
    help="npz (default, or from the output suffix) or jsonl.",
)
@click.option("--ecm", "ecms", multiple=True, metavar="NAME", help="Only steps of this ECM; repeatable.")
@click.option("--allow-incomplete", is_flag=True, help="Read unfinished (crashed) files up to the damage.")
@click.option("--force", is_flag=True, help="Replace the output if it exists.")
@json_option
def export_cmd(
    files: tuple[Path, ...],
    episodes: str,
    output: Path | None,
    fmt: str | None,
    ecms: tuple[str, ...],
    allow_incomplete: bool,
    force: bool,
    as_json: bool,
) -> None:
    """Export the transitions of trace FILE(s) for learners.

    Arrays (npz) / keys (jsonl): obs (N,D) float32, action (N,A) float32, reward (N,)
    float32, next_obs (N,D) float32, done, terminated, truncated, is_success (N,) bool,
    ecm (N,) str, version, episode, step (N,) int64, run_id (N,) str.
    """
    selection = parse_episodes(episodes)
    if fmt is None:
        fmt = "jsonl" if output is not None and output.suffix.lower() == ".jsonl" else "npz"
    if output is None:
        first = files[0]
        output = first.with_name(f"{first.stem}.transitions.{fmt}")
    if output.exists() and not force:
        raise Conflict(f"output already exists: {output} (pass --force to replace it)", details={"path": str(output)})
    if output.is_dir():
        raise Invalid(f"output is a directory: {output}", details={"field": "output"})
    transitions = export_transitions(
        files, episodes=selection, ecms=set(ecms) if ecms else None, allow_incomplete=allow_incomplete
    )
    if fmt == "npz":
        transitions.save_npz(output)
    else:
        transitions.save_jsonl(output)
    result = {
        "output": str(output),
        "format": fmt,
        "transitions": len(transitions),
        "episodes": str(selection),
        "arrays": {name: [list(a.shape), a.dtype.str] for name, a in transitions.arrays().items()},
    }
    emit(as_json, result, lambda console: _render_export(console, output, fmt, transitions))


def _render_export(console: Console, output: Path, fmt: str, t: Transitions) -> None:
    n_episodes = len({(r, e) for r, e in zip(t.run_id.tolist(), t.episode.tolist(), strict=True)})
    console.print(
        f"wrote {len(t)} transitions from {n_episodes} episodes to {output} ({fmt}; "
        f"obs dim {t.obs.shape[1]}, action dim {t.action.shape[1]})"
    )


# ---------------------------------------------------------------------------------------
# recover
# ---------------------------------------------------------------------------------------


@trace.command("recover")
@click.argument("file", type=_FILE)
@click.option(
    "-o", "--output", type=click.Path(path_type=Path), default=None, help="Output file (default FILE.recovered.mcap)."
)
@click.option("--force", is_flag=True, help="Replace the output if it exists.")
@json_option
def recover_cmd(file: Path, output: Path | None, force: bool, as_json: bool) -> None:
    """Salvage a crashed worker's trace FILE into a finished MCAP file.

    Copies every record up to the first truncated or corrupt one; the copy opens in
    Foxglove and in every `capevo trace` command.
    """
    report = recover(file, output or default_output(file), overwrite=force)
    emit(as_json, report.to_dict(), lambda console: _render_recover(console, report))


def _render_recover(console: Console, r: RecoverReport) -> None:
    topics = ", ".join(f"{topic} {n}" for topic, n in sorted(r.messages_by_topic.items())) or "none"
    console.print(f"recovered {r.messages} messages into {r.output} ({topics})")
    if r.complete:
        console.print("the source was already a finished file")
    else:
        console.print(f"the source stopped at byte {r.good_bytes} of {r.source_bytes}: {r.reason}")
    if r.dropped_messages:
        console.print(f"dropped {r.dropped_messages} messages whose channel record was lost")


# ---------------------------------------------------------------------------------------
# blame
# ---------------------------------------------------------------------------------------


@trace.command("blame")
@click.argument("paths", nargs=-1, required=True, type=_FILE)
@json_option
def blame_cmd(paths: tuple[Path, ...], as_json: bool) -> None:
    """Where the failed episodes of trace PATH(s) stopped, and which ECM they blame.

    A PATH that is a directory stands for its *.mcap files (recursively). Each failed episode
    carries a blame of 1, shared by the steps that did not hand over to a later one (the
    one running at the end; a step that hogged a timed-out episode instead), which is how
    `capevo evolve` picks the ECM to learn next. The traces must all be of one task, whose
    decomposition judges the steps. For `capevo runtime evaluate --trace-dir`.
    """
    files = trace_files(paths, recursive=True)
    spec = task_spec(_traces_task(files))
    decomposition = spec.ecm_names
    ends = [end for f in files for end in read_episode_ends(f)]
    failed = [e for e in ends if not e.success]
    weights = failure_weights(ends, decomposition)
    ranked = dict(sorted(weights.items(), key=lambda kv: (-kv[1], decomposition.index(kv[0]))))
    result = {
        "task": spec.name,
        "files": [str(f) for f in files],
        "episodes": len(ends),
        "successes": len(ends) - len(failed),
        "blame": ranked,
        "failed": [_failed_row(e, decomposition) for e in failed],
    }
    emit(as_json, result, lambda console: _render_blame(console, result))


def _traces_task(files: list[Path]) -> str:
    tasks: set[str] = set()
    for f in files:
        with TraceReader(f, allow_incomplete=True) as reader:
            tasks.add(reader.metadata().task)
    if len(tasks) != 1:
        listed = ", ".join(sorted(tasks))
        raise Invalid(f"the traces hold several tasks ({listed}): blame one at a time", details={"field": "paths"})
    return tasks.pop()


def _failed_row(end: EpisodeEnd, decomposition: tuple[str, ...]) -> dict[str, Any]:
    return {
        "trace": end.trace_path,
        "seed": end.seed,
        "steps": end.steps,
        "ended": end.end_reason,
        "last_ecm": end.last_ecm,
        "blamed": failed_activations(end, decomposition),
        "ecm_steps": dict(sorted(end.ecm_steps.items(), key=lambda kv: -kv[1])),
        "budget_exhausted": list(end.budget_exhausted),
        "unsafe_steps": {k: v for k, v in end.ecm_unsafe.items() if v},
    }


def _render_blame(console: Console, r: dict[str, Any]) -> None:
    prefix = f"{r['task']}."

    def short(ecm: str | None) -> str:
        return "-" if ecm is None else ecm.removeprefix(prefix)

    console.print(
        f"task {r['task']}: {r['episodes']} episodes in {len(r['files'])} file(s), {r['successes']} succeeded, "
        f"{len(r['failed'])} failed"
    )
    if not r["failed"]:
        return
    table = make_table("SEED", "STEPS", "LAST ECM", "BLAMED (ACTIVATIONS)", "MOST STEPS", "ENDED")
    for row in r["failed"]:
        blamed = ", ".join(f"{short(k)} x{n}" if n > 1 else short(k) for k, n in Counter(row["blamed"]).items())
        spent = ", ".join(f"{short(k)} {v}" for k, v in list(row["ecm_steps"].items())[:2])
        table.add_row(fmt_opt(row["seed"]), str(row["steps"]), short(row["last_ecm"]), blamed, spent, row["ended"])
    console.print(table)
    console.print("blame (1 per failed episode): " + ", ".join(f"{short(k)} {v:.3g}" for k, v in r["blame"].items()))


if __name__ == "__main__":
    trace(prog_name="capevo trace")
