"""``capevo learner ...``: run a learner worker that improves one ECM and pushes candidates.

Usage::

    capevo learner serve --connect tcp/127.0.0.1:7447 --ecm pick.reach --modality rl \\
        [--task T1] [--preset tiny|cpu-small|paper] [--traces DIR]... [--once] [--json]
    capevo learner distil --root DIR --task T6 --traces DIR --round 10 [--extension 20] [--json]

Invariants:
1. ``serve --once`` exits 0 after publishing one candidate; without ``--once`` it exits 0 after
   SIGTERM or SIGINT once the registry session is closed.
2. With ``--json`` every line ``serve`` prints on stdout is one JSON object with an ``event``
   field (``ready``, ``waiting``, ``trigger``, ``training``, ``published``, ``unchanged``,
   ``abandoned``, ``error``, ``stopped``); logs and progress bars go to stderr.
3. ``distil --json`` prints one JSON document on stdout (the candidates, the ECMs skipped and
   the gate's decision); the learners' events go to stderr.
4. Errors follow the ``capevo`` convention: one ``error [code]: message`` line on stderr and the
   code's exit status; the password is never printed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import click

from capevo.cli import (
    CapevoGroup,
    log_level_option,
    log_to_stderr,
    login_options,
    phi_option,
    registry_timeout_option,
    remember_password,
)
from capevo.cli.runtime import episode_target_options, gate_options, open_gate_side, where_episodes_run
from capevo.errors import Invalid


@click.group(cls=CapevoGroup, context_settings={"help_option_names": ["-h", "--help"]})
def learner() -> None:
    """Learner workers: improve an ECM (rl, il, code, hybrid) and publish candidates."""


@learner.command("serve")
@click.option(
    "--connect",
    multiple=True,
    metavar="ENDPOINT",
    envvar="CAPEVO_CONNECT",
    help="Zenoh endpoint of the registry, e.g. tcp/127.0.0.1:7447; repeatable (env CAPEVO_CONNECT).",
)
@click.option(
    "--root",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Use the registry directory ROOT in-process instead of --connect.",
)
@login_options
@click.option("--ecm", required=True, help="The ECM to improve, e.g. pick.reach.")
@click.option(
    "--modality",
    type=click.Choice(["rl", "il", "code", "hybrid"]),
    required=True,
    help="rl: SAC; il: behaviour cloning; code: CEM over PARAMS; hybrid: LLM edit + CEM.",
)
@click.option("--task", default=None, help="Task (T1..T6 or its name). [default: the ECM name's prefix]")
@click.option(
    "--preset",
    type=click.Choice(["tiny", "cpu-small", "paper"]),
    default="cpu-small",
    show_default=True,
    help="Training budget.",
)
@click.option(
    "--traces",
    "traces",
    multiple=True,
    type=click.Path(path_type=Path),
    help="Trace file or directory of *.mcap to learn from and to watch; repeatable.",
)
@click.option(
    "--work-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Scratch directory (code learners' evaluation traces). [default: a temporary one]",
)
@click.option("--learner-id", default=None, help="Recorded in provenance. [default: <modality>-<host>-<pid>-<rand>]")
@click.option("--once", is_flag=True, help="Do one update now, publish it and exit.")
@click.option(
    "--min-episodes",
    type=click.IntRange(min=0),
    default=20,
    show_default=True,
    help="Update after this many new episodes of the active version (0: off).",
)
@click.option(
    "--window", type=click.IntRange(min=1), default=20, show_default=True, help="Episodes per success-rate window."
)
@click.option(
    "--margin",
    type=click.FloatRange(min=0.0, max=1.0),
    default=0.2,
    show_default=True,
    help="Update when the success rate drops by this much between two windows (0: off).",
)
@click.option(
    "--poll", type=click.FloatRange(min=0.01), default=5.0, show_default=True, help="Seconds between trace scans."
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seeds the learner.")
@click.option(
    "--seed-plan",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="The run's seed plan (capevo evolve --seed): train only on its training seeds, never its gate seeds.",
)
@click.option("--no-perturbations", is_flag=True, help="Train on the clean task (no jitter, noise or dropped actions).")
@phi_option
@click.option(
    "--progress/--no-progress",
    default=None,
    help="Show training progress bars on stderr. [default: when stderr is a terminal]",
)
@click.option(
    "--torch-threads", type=click.IntRange(min=1), default=1, show_default=True, help="CPU threads for torch."
)
@click.option(
    "--evaluate-on-workers",
    is_flag=True,
    help="code/hybrid: run CEM's samples on the runtime workers of the task (via --connect), not in this process.",
)
@click.option(
    "--evaluate-timeout",
    type=click.FloatRange(min=1.0),
    default=600.0,
    show_default=True,
    help="Seconds to wait for all the episodes of one batch of samples on the workers.",
)
@registry_timeout_option
@log_level_option()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON event per line.")
def serve_cmd(
    connect: tuple[str, ...],
    root: Path | None,
    namespace: str,
    user: str | None,
    password: str | None,
    ecm: str,
    modality: str,
    task: str | None,
    preset: str,
    traces: tuple[Path, ...],
    work_dir: Path | None,
    learner_id: str | None,
    once: bool,
    min_episodes: int,
    window: int,
    margin: float,
    poll: float,
    seed: int,
    seed_plan: int,
    no_perturbations: bool,
    phi: str,
    progress: bool | None,
    torch_threads: int,
    evaluate_on_workers: bool,
    evaluate_timeout: float,
    timeout: float,
    log_level: str,
    as_json: bool,
) -> None:
    """Improve --ecm with --modality and publish candidates to the registry for gating.

    With --once: pull the active version and the experience, train, publish one candidate,
    exit. Otherwise watch --traces for new episodes of the active version and registry events,
    and update whenever the trigger fires (--min-episodes new episodes, or a success-rate drop
    of --margin between two --window windows), until SIGTERM. With --evaluate-on-workers a code
    learner's samples run on the task's runtime workers (sent inline, traces returned), the same
    path as the gate's and the live episodes.
    """
    from capevo.learner.bc import default_learner_id
    from capevo.learner.trigger import TriggerConfig
    from capevo.learner.worker import LearnerConfig, LearnerWorker
    from capevo.registry.open import open_registry
    from capevo.registry.zconfig import split_endpoints
    from capevo.runtime.tasks import Perturbations

    log_to_stderr(log_level)
    endpoints = split_endpoints(connect)
    if (root is None) == (not endpoints):
        raise Invalid("give exactly one of --connect ENDPOINT or --root DIR", details={"field": "connect"})
    if evaluate_on_workers and not endpoints:
        raise Invalid(
            "--evaluate-on-workers needs --connect (the runtime workers' Zenoh network)", details={"field": "connect"}
        )
    if evaluate_on_workers and modality not in ("code", "hybrid"):
        raise Invalid(
            f"--evaluate-on-workers runs code learners' samples; modality {modality!r} publishes versions to gate",
            details={"field": "evaluate_on_workers"},
        )
    secret = remember_password(password)
    config = LearnerConfig(
        ecm=ecm,
        modality=modality,
        task=task,
        preset=preset,
        learner_id=learner_id or default_learner_id(modality),
        traces=tuple(traces),
        work_dir=work_dir,
        once=once,
        trigger=TriggerConfig(min_new_episodes=min_episodes or None, window=window, degradation_margin=margin or None),
        poll_interval_s=poll,
        perturbations=Perturbations.none() if no_perturbations else Perturbations(),
        phi=phi,
        seed=seed,
        seed_plan=seed_plan,
        progress_bar=sys.stderr.isatty() if progress is None else progress,
        torch_threads=torch_threads,
    )

    def open_it() -> Any:
        if root is not None:
            return open_registry(root=root, actor=config.learner_id)
        return open_registry(
            connect=endpoints,
            namespace=namespace,
            user=user or None,
            password=secret,
            timeout=timeout,
            actor=config.learner_id,
        )

    def show(event: dict[str, Any]) -> None:
        click.echo(json.dumps(event, default=str) if as_json else _human(event))
        sys.stdout.flush()

    def open_evaluator(trace_dir: Path) -> Any:
        from capevo.runtime.remote_evaluator import RemoteEvaluator

        return RemoteEvaluator(
            list(endpoints),
            namespace=namespace,
            user=user or None,
            password=secret,
            timeout=evaluate_timeout,
            trace_dir=trace_dir,
        )

    worker = LearnerWorker(
        config, open_it, emit=show, open_candidate_evaluator=open_evaluator if evaluate_on_workers else None
    )
    worker.run(handle_signals=True)


@learner.command("distil")
@episode_target_options
@click.option("--task", required=True, help="Task: T1..T6 or its name.")
@click.option(
    "--traces",
    "traces",
    multiple=True,
    required=True,
    type=click.Path(exists=True, path_type=Path),
    help="Trace file or directory of the current set's episodes; its successful ones are cloned. Repeatable.",
)
@gate_options
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seeds the learners.")
@click.option("--worker-id", default=None, help="With --connect: ask this worker. [default: any worker of the task]")
@click.option(
    "--timeout",
    type=click.FloatRange(min=0.01),
    default=600.0,
    show_default=True,
    help="Seconds to wait for the gate's episodes.",
)
@click.option(
    "--torch-threads", type=click.IntRange(min=1), default=1, show_default=True, help="CPU threads for torch."
)
@phi_option
@log_level_option()
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document.")
def distil_cmd(
    connect: tuple[str, ...],
    root: str | None,
    namespace: str,
    user: str | None,
    password: str | None,
    task: str,
    traces: tuple[Path, ...],
    preset: str,
    extension: int | None,
    seed_plan: int,
    round_: int,
    seed: int,
    worker_id: str | None,
    timeout: float,
    torch_threads: int,
    phi: str,
    log_level: str,
    as_json: bool,
) -> None:
    """Clone every ECM of --task from the set's successful traces and gate the clones as one change.

    The hybrid path from code to neural ECMs (issue 19): each ECM whose steps ran to a hand-over
    in a successful episode of --traces gets a behaviour-cloned neural candidate (modality il,
    one update, the --preset's budget); ECMs without such steps keep their active version. The
    gate then judges the active set against the set with all the candidates, one decision for
    all (capevo runtime gate ... --with ...), on batch --round of the seed plan's gate seeds.

    \b
    --root DIR: the registry directory; the gate's episodes run in this process under --phi.
    --connect EP: the registry server; the gate's episodes run on the task's runtime workers.
    """
    import contextlib
    import dataclasses

    from capevo.evolve.config import make_config
    from capevo.evolve.distil import distil_set

    log_to_stderr(log_level)
    root_path, endpoints = where_episodes_run(root, connect)
    config = make_config(preset)
    gate_config = config.gate if extension is None else dataclasses.replace(config.gate, extend_n=extension)

    def show(event: dict[str, Any]) -> None:
        if event.get("event") == "skipped":
            click.echo(f"{event['ecm']}: kept as it is ({event['reason']})", err=True)
        else:
            click.echo(_human(event), err=True)

    with contextlib.ExitStack() as stack:
        registry, evaluator = open_gate_side(
            stack,
            root_path,
            endpoints,
            namespace=namespace,
            user=user,
            password=password,
            worker_id=worker_id,
            timeout=timeout,
            phi=phi,
            actor="distil",
        )
        result = distil_set(
            registry,
            evaluator,
            task=task,
            traces=traces,
            gate_config=gate_config,
            gate_episodes=config.gate_episodes,
            round_=round_,
            preset=preset,
            phi=phi,
            seed=seed,
            seed_plan=seed_plan,
            actor=user or "distil",
            torch_threads=torch_threads,
            emit=show,
        )
    if as_json:
        click.echo(json.dumps(result.to_dict(), default=str))
        return
    names = ", ".join(f"{c.name} v{c.version}" for c in result.candidates)
    click.echo(f"cloned: {names}")
    for skipped in result.skipped:
        click.echo(f"kept as it is: {skipped.ecm} ({skipped.reason})")
    click.echo(f"{'promoted' if result.decision.promoted else 'rejected'} as one change: {result.decision.reason}")


def _human(event: dict[str, Any]) -> str:
    kind = event.get("event")
    lid = event.get("learner_id", "")
    if kind == "ready":
        return (
            f"[{lid}] ready: {event.get('modality')} learner for {event.get('ecm')} ({event.get('task')}), "
            f"preset {event.get('preset')}{', one update' if event.get('once') else ''}"
        )
    if kind == "training":
        return (
            f"[{lid}] training {event.get('ecm')} from v{event.get('parent')} ({event.get('parent_kind')}) "
            f"because {event.get('reason')}"
        )
    if kind == "published":
        prov = event.get("provenance") or {}
        return (
            f"[{lid}] published {event.get('ecm')} v{event.get('version')} ({event.get('origin')}, parent "
            f"v{event.get('parent')}, config {str(prov.get('config_hash', ''))[:12]}) as a candidate"
        )
    if kind == "trigger":
        return f"[{lid}] trigger: {event.get('reason')} after {event.get('new_episodes')} new episodes"
    rest = {k: v for k, v in event.items() if k not in ("event", "learner_id")}
    return f"[{lid}] {kind}: {json.dumps(rest, default=str)}"


if __name__ == "__main__":
    learner(prog_name="capevo learner")
