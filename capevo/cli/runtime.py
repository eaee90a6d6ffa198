"""``capevo runtime ...``: run a runtime worker, list the running ones, ask one to evaluate, gate a candidate.

Invariants:
1. ``serve`` exits 0 after SIGTERM or SIGINT once the worker has closed its traces and
   Zenoh sessions, and 0 after ``--episodes N`` episodes.
2. With ``--json``, every line ``serve`` prints on stdout is one JSON object with an
   ``event`` field (``ready``, ``waiting``, ``registry``, ``swap_queued``, ``swap``,
   ``episode``, ``evaluated``, ``stopped``); logs go to stderr.
3. Errors follow the ``capevo`` convention: one ``error [code]: message`` line on stderr and
   the code's exit status.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
from pathlib import Path
from typing import Any

import click
from rich.console import Console

from capevo.cli import (
    LOGIN_OPTIONS,
    CapevoGroup,
    emit,
    fmt_time,
    identity_option,
    json_option,
    log_level_option,
    log_to_stderr,
    make_table,
    phi_option,
    registry_timeout_option,
    remember_password,
    resolve_target,
)
from capevo.cli.evolve import PRESETS
from capevo.errors import Invalid


@click.group(cls=CapevoGroup, context_settings={"help_option_names": ["-h", "--help"]})
def runtime() -> None:
    """Run tasks with the registry's ECMs (runtime workers)."""


def _connection_options(func: Any) -> Any:
    decorators = [
        click.option(
            "--connect",
            multiple=True,
            required=True,
            metavar="ENDPOINT",
            envvar="CAPEVO_CONNECT",
            help="Zenoh endpoint of the registry, e.g. tcp/127.0.0.1:7447; repeatable (env CAPEVO_CONNECT).",
        ),
        *LOGIN_OPTIONS,
    ]
    for deco in reversed(decorators):
        func = deco(func)
    return func


@runtime.command("serve")
@_connection_options
@click.option("--task", required=True, help="Task to run: T1..T6 or its name (pick, place, ...).")
@click.option("--worker-id", default=None, help="Key chunk naming this worker. [default: <host>-<pid>]")
@click.option(
    "--trace-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Write MCAP traces here (one file per capability set; evaluations under evaluations/).",
)
@click.option(
    "--trace-compression",
    type=click.Choice(["lz4", "zstd", "none"]),
    default="lz4",
    show_default=True,
    help="Chunk compression of the traces: none costs less CPU per step for files about 3x larger.",
)
@click.option(
    "--cache-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="On-disk artifact cache (by sha256). [default: in memory]",
)
@click.option("--episodes", type=click.IntRange(min=1), default=None, help="Run N episodes, then exit.")
@click.option("--idle", is_flag=True, help="Run no episodes; only serve evaluation requests.")
@click.option("--horizon", type=click.IntRange(min=1), default=None, help="Episode length. [default: the task's]")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the first episode.")
@click.option("--no-perturbations", is_flag=True, help="Run the clean task (no jitter, noise or dropped actions).")
@click.option(
    "--governance/--no-governance",
    default=True,
    show_default=True,
    help="Enforce the safety envelope Φ; --no-governance only counts what it would do (evaluation only).",
)
@phi_option
@identity_option
@click.option("--step-budget", type=click.IntRange(min=1), default=200, show_default=True, help="Steps per ECM run.")
@click.option(
    "--ecm-timeout", type=click.FloatRange(min=0.001), default=0.5, show_default=True, help="Seconds per ECM call."
)
@click.option(
    "--recovery",
    type=click.Choice(["abort", "retry", "fallback", "retry-fallback"]),
    default="retry",
    show_default=True,
    help="What to do when an ECM call fails.",
)
@registry_timeout_option
@log_level_option()
@json_option
def serve_cmd(
    connect: tuple[str, ...],
    namespace: str,
    user: str | None,
    password: str | None,
    task: str,
    worker_id: str | None,
    trace_dir: Path | None,
    trace_compression: str,
    cache_dir: Path | None,
    episodes: int | None,
    idle: bool,
    horizon: int | None,
    seed: int,
    no_perturbations: bool,
    governance: bool,
    phi: str,
    identity_path: Path | None,
    step_budget: int,
    ecm_timeout: float,
    recovery: str,
    timeout: float,
    log_level: str,
    as_json: bool,
) -> None:
    """Run episodes of --task with the registry's active ECMs until SIGTERM (or --episodes N).

    Hot-swaps an ECM between episodes when the registry promotes or rolls it back, keeps
    running on its last versions while the registry is away, and serves evaluation requests
    on <ns>/runtime/<worker_id>/evaluate and <ns>/runtime/evaluate/<task>.
    """
    from capevo.agent import DecompositionPolicy, IdentityMemory, identity_hash, load_identity
    from capevo.registry.zconfig import split_endpoints
    from capevo.runtime.tasks import Perturbations
    from capevo.runtime.worker import RuntimeWorker, WorkerConfig

    log_to_stderr(log_level)
    if log_level.upper() != "DEBUG":
        # robosuite repeats its controller-config warnings on every reset.
        logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    config = WorkerConfig(
        connect=split_endpoints(connect),
        task=task,
        namespace=namespace,
        user=user or None,
        password=remember_password(password),
        worker_id=worker_id,
        trace_dir=trace_dir,
        trace_compression=trace_compression,
        cache_dir=cache_dir,
        episodes=episodes,
        idle=idle,
        horizon=horizon,
        perturbations=Perturbations.none() if no_perturbations else Perturbations(),
        governance=governance,
        phi=phi,
        seed=seed,
        step_budget_per_ecm=step_budget,
        timeout_s=ecm_timeout,
        recovery=recovery,
        registry_timeout=timeout,
    )

    def show(event: dict[str, Any]) -> None:
        if as_json:
            click.echo(json.dumps(event, default=str))
        else:
            click.echo(_human(event))
        sys.stdout.flush()

    identity = load_identity(identity_path) if identity_path is not None else IdentityMemory.default()
    policy = DecompositionPolicy(identity=identity)
    worker = RuntimeWorker(config, policy=policy, agent_identity_hash=identity_hash(policy, identity), emit=show)
    worker.run(handle_signals=True)


def _human(event: dict[str, Any]) -> str:
    kind = event.get("event")
    wid = event.get("worker_id", "")
    if kind == "ready":
        versions = ", ".join(f"{k}@{v}" for k, v in sorted(event.get("versions", {}).items()))
        return f"[{wid}] ready: task {event.get('task')} at revision {event.get('revision')}: {versions}"
    if kind == "episode":
        status = "success" if event.get("success") else event.get("end_reason", "")
        return (
            f"[{wid}] episode {event.get('episode')} (seed {event.get('seed')}): {status}, {event.get('steps')} steps, "
            f"reward {event.get('reward', 0.0):.3f}, {event.get('interventions')} interventions, "
            f"{event.get('unsafe_steps')} unsafe, {event.get('ecm_failures')} ECM failures"
        )
    if kind == "swap":
        if event.get("applied"):
            return f"[{wid}] swapped {event.get('name')} {event.get('from_version')} -> {event.get('to_version')}"
        state = "deferred" if event.get("pending") else "refused"
        return f"[{wid}] swap of {event.get('name')} to {event.get('to_version')} {state}: {event.get('error')}"
    if kind == "registry":
        return f"[{wid}] registry {'is back' if event.get('connected') else 'went away; running on the last versions'}"
    rest = {k: v for k, v in event.items() if k not in ("event", "worker_id")}
    return f"[{wid}] {kind}: {json.dumps(rest, default=str)}"


@runtime.command("list")
@_connection_options
@click.option("--timeout", type=click.FloatRange(min=0.01), default=3.0, show_default=True, help="Seconds to wait.")
@json_option
def list_cmd(
    connect: tuple[str, ...], namespace: str, user: str | None, password: str | None, timeout: float, as_json: bool
) -> None:
    """List the runtime workers that answer on <ns>/runtime/*/adopted, with the versions they run."""
    from capevo.runtime.remote_evaluator import list_workers

    workers = list_workers(
        list(connect), namespace=namespace, user=user or None, password=remember_password(password), timeout=timeout
    )
    emit(as_json, [w.to_dict() for w in workers], lambda c: _render_workers(c, workers))


def _render_workers(console: Console, workers: list[Any]) -> None:
    if not workers:
        console.print("no runtime workers answered")
        return
    table = make_table("WORKER", "TASK", "REVISION", "VERSIONS", "PENDING", "EPISODES", "REGISTRY", "STARTED")
    for w in workers:
        table.add_row(
            w.worker_id,
            w.task,
            str(w.revision),
            ", ".join(f"{k}@{v}" for k, v in sorted(w.versions.items())),
            ", ".join(f"{k}@{v}" for k, v in sorted(w.pending.items())) or "-",
            str(w.episodes),
            "up" if w.registry_connected else "away",
            fmt_time(w.started_at),
        )
    console.print(table)


def _parse_versions(values: tuple[str, ...], option: str = "version") -> dict[str, int]:
    out: dict[str, int] = {}
    for value in values:
        name, sep, version = value.partition("=")
        if not sep or not version.isdigit():
            raise Invalid(f"--{option} takes NAME=VERSION, got {value!r}", details={"field": option})
        out[name] = int(version)
    return out


def parse_seeds(text: str) -> list[int]:
    """Seeds written as numbers and ranges, ``0-9,20`` (inclusive).

    Raises:
        Invalid: naming ``seeds``, on anything else or on no seed at all.
    """
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise Invalid(f"--seeds takes numbers and ranges like 0-9,20, got {text!r}", details={"field": "seeds"})
        seeds.extend(range(int(lo), int(hi) + 1) if sep else [int(lo)])
    if not seeds:
        raise Invalid("--seeds: give at least one seed", details={"field": "seeds"})
    return seeds


def where_episodes_run(root: str | None, connect: tuple[str, ...]) -> tuple[Path | None, tuple[str, ...]]:
    """``(root, ())`` to run episodes in this process, or ``(None, endpoints)`` for runtime workers."""
    ctx = click.get_current_context()
    return resolve_target(
        root=root,
        root_source=ctx.get_parameter_source("root"),
        connect=connect,
        connect_source=ctx.get_parameter_source("connect"),
    )


def episode_target_options(func: Any) -> Any:
    """``--connect``/``--root`` (where the episodes run) and the login options of ``evaluate``,
    ``gate`` and ``capevo learner distil``."""
    decorators = [
        click.option(
            "--connect",
            multiple=True,
            metavar="ENDPOINT",
            envvar="CAPEVO_CONNECT",
            help="Zenoh endpoint of the registry: the episodes run on its runtime workers; repeatable.",
        ),
        click.option(
            "--root",
            envvar="CAPEVO_ROOT",
            default=None,
            help="Local registry directory: the episodes run in this process instead (env CAPEVO_ROOT).",
        ),
        click.option(
            "--namespace", default="capevo", show_default=True, envvar="CAPEVO_NAMESPACE", help="Zenoh key prefix."
        ),
        click.option("--user", default=None, envvar="CAPEVO_USER", help="Registry user (env CAPEVO_USER)."),
        click.option(
            "--password", default=None, envvar="CAPEVO_PASSWORD", help="Registry password (env CAPEVO_PASSWORD)."
        ),
    ]
    for deco in reversed(decorators):
        func = deco(func)
    return func


@runtime.command("evaluate")
@episode_target_options
@click.option("--task", required=True, help="Task: T1..T6 or its name.")
@click.option("--seeds", default="0-4", show_default=True, help="Seeds, e.g. 0-9 or 1,5,7.")
@click.option("--version", "versions", multiple=True, metavar="NAME=VERSION", help="Run NAME at VERSION; repeatable.")
@click.option("--worker-id", default=None, help="Ask this worker. [default: any worker of the task]")
@click.option("--timeout", type=click.FloatRange(min=0.01), default=600.0, show_default=True, help="Seconds to wait.")
@phi_option
@click.option("--horizon", type=click.IntRange(min=1), default=None, help="With --root: episode length.")
@click.option(
    "--trace-dir",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Write the episodes' MCAP traces here (with --connect, each worker's part comes back as a file); "
    "read them with `capevo trace blame`.",
)
@json_option
def evaluate_cmd(
    connect: tuple[str, ...],
    root: str | None,
    namespace: str,
    user: str | None,
    password: str | None,
    task: str,
    seeds: str,
    versions: tuple[str, ...],
    worker_id: str | None,
    timeout: float,
    phi: str,
    horizon: int | None,
    trace_dir: Path | None,
    as_json: bool,
) -> None:
    """Run evaluation episodes and print their outcomes, with 95 % Wilson intervals.

    \b
    --connect EP: on a runtime worker of the task (its own Φ, horizon and perturbations apply).
    --root DIR: in this process, on the local registry, under --phi, perturbations on.
    With --trace-dir, each outcome's trace_path names its episode's trace there.
    """
    from capevo.runtime.gate_stats import wilson_interval

    root_path, endpoints = where_episodes_run(root, connect)
    pinned = _parse_versions(versions)
    seed_list = parse_seeds(seeds)
    if root_path is not None:
        outcomes = _evaluate_locally(
            root_path, task, pinned, seed_list, phi=phi, horizon=horizon, actor=user, trace_dir=trace_dir
        )
    else:
        from capevo.runtime.remote_evaluator import RemoteEvaluator

        with RemoteEvaluator(
            list(endpoints),
            namespace=namespace,
            user=user or None,
            password=remember_password(password),
            worker_id=worker_id,
            timeout=timeout,
            trace_dir=trace_dir,
        ) as evaluator:
            outcomes = evaluator.evaluate(task, pinned, seed_list)
    n = len(outcomes)
    successes = sum(o.success for o in outcomes)
    unsafe = sum(o.unsafe_steps > 0 for o in outcomes)

    def render(console: Console) -> None:
        table = make_table("SEED", "SUCCESS", "REWARD", "STEPS", "INTERVENTIONS", "UNSAFE", "ECM FAILURES")
        for o in outcomes:
            table.add_row(
                str(o.seed),
                "yes" if o.success else "no",
                f"{o.reward:.3f}",
                str(o.steps),
                str(o.interventions),
                str(o.unsafe_steps),
                str(o.ecm_failures),
            )
        console.print(table)
        ok, bad = wilson_interval(successes, n, alpha=0.025), wilson_interval(unsafe, n, alpha=0.025)
        console.print(
            f"success {successes}/{n} = {successes / n:.1%} [95% Wilson {ok.low:.1%}, {ok.high:.1%}]; "
            f"unsafe episodes {unsafe}/{n} [{bad.low:.1%}, {bad.high:.1%}]"
        )

    emit(as_json, [o.to_dict() for o in outcomes], render)


def gate_options(func: Any) -> Any:
    """The gate's ``--preset``, ``--extension``, ``--seed-plan`` and ``--round``, as ``gate`` and
    ``capevo learner distil`` take them."""
    decorators = [
        click.option(
            "--preset",
            type=click.Choice(PRESETS),
            default="cpu-small",
            show_default=True,
            help="Budget preset: the gate's thresholds and paired seeds N (distil: the learners' budget too), "
            "as capevo evolve uses them.",
        ),
        click.option(
            "--extension",
            type=click.IntRange(min=0),
            default=None,
            help="Paired seeds of the gate's second look (0: one look). [default: the preset's]",
        ),
        click.option(
            "--seed-plan",
            type=click.IntRange(min=0),
            default=0,
            show_default=True,
            help="The run's seed plan (evolve --seed).",
        ),
        click.option(
            "--round",
            "round_",
            type=click.IntRange(min=0),
            required=True,
            help="Which disjoint batch of the plan's gate seeds to use. capevo evolve uses batch i in iteration i: "
            "pick one no earlier decision has used, or the gate sees seeds it was already judged on.",
        ),
    ]
    for decorate in reversed(decorators):
        func = decorate(func)
    return func


@runtime.command("gate")
@click.argument("name")
@click.argument("version", type=click.IntRange(min=0))
@episode_target_options
@click.option("--task", default=None, help="Task: T1..T6 or its name. [default: the ECM name's prefix]")
@gate_options
@click.option(
    "--with",
    "with_",
    multiple=True,
    metavar="NAME=VERSION",
    help="Another candidate decided together with this one (a set learned together); repeatable.",
)
@click.option("--worker-id", default=None, help="With --connect: ask this worker. [default: any worker of the task]")
@click.option("--timeout", type=click.FloatRange(min=0.01), default=600.0, show_default=True, help="Seconds to wait.")
@phi_option
@json_option
def gate_cmd(
    name: str,
    version: int,
    connect: tuple[str, ...],
    root: str | None,
    namespace: str,
    user: str | None,
    password: str | None,
    task: str | None,
    preset: str,
    extension: int | None,
    seed_plan: int,
    round_: int,
    with_: tuple[str, ...],
    worker_id: str | None,
    timeout: float,
    phi: str,
    as_json: bool,
) -> None:
    """Gate candidate VERSION of NAME against the active version: promote or reject it.

    The same decision as an iteration of capevo evolve: both versions run on the seed plan's
    held-out gate seeds (batch --round), paired, with the preset's thresholds; the evidence is
    recorded in the registry. For candidates published outside a run (capevo learner serve
    --once, capevo ecm publish).

    \b
    --connect EP: episodes on the task's runtime workers (their Φ, horizon and perturbations).
    --root DIR: in this process, on the local registry, under --phi, perturbations on.
    --with NAME=VERSION: the active set against the set with every candidate named, one
    decision for all (as capevo evolve gates a chain).
    """
    import dataclasses

    from capevo.evolve.config import make_config
    from capevo.records.names import validate_name
    from capevo.runtime.gate import Gate, SeedPlan
    from capevo.runtime.tasks import task_of

    validate_name(name)
    companions = _parse_versions(with_, "with")
    for other in companions:
        validate_name(other)
    root_path, endpoints = where_episodes_run(root, connect)
    config = make_config(preset)
    gate_config = config.gate if extension is None else dataclasses.replace(config.gate, extend_n=extension)
    plan = SeedPlan(base_seed=seed_plan)
    seeds = plan.gate(config.gate_episodes, round=round_)
    more = plan.gate_extension(gate_config.extend_n, round=round_) if gate_config.extend_n else []
    task_name = task or task_of(name)
    strangers = sorted(o for o in companions if task_of(o) != task_of(name))
    if strangers:
        raise Invalid(
            f"--with names ECMs of another task than {name}'s: {', '.join(strangers)}", details={"field": "with"}
        )
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
            actor="gate",
        )
        gate = Gate(registry, evaluator, gate_config, actor=user or "gate", seed_plan=plan)  # type: ignore[arg-type]
        decision = gate.run(
            name, version, task=task_name, seeds=seeds, extension_seeds=more, with_candidates=companions
        )

    def render(console: Console) -> None:
        console.print(decision.reason)

    emit(as_json, decision.to_dict(), render)


def open_gate_side(
    stack: contextlib.ExitStack,
    root: Path | None,
    endpoints: tuple[str, ...],
    *,
    namespace: str,
    user: str | None,
    password: str | None,
    worker_id: str | None,
    timeout: float,
    phi: str,
    actor: str,
) -> tuple[Any, Any]:
    """The registry and the evaluator a gate decision uses, both closed with ``stack``: a local
    registry and episodes in this process (``root``), or the registry server and its runtime
    workers (``endpoints``)."""
    if root is not None:
        return _local_registry_and_evaluator(stack, root, phi=phi, actor=user or actor)
    from capevo.registry.open import open_registry
    from capevo.runtime.remote_evaluator import RemoteEvaluator

    password = remember_password(password)
    registry = open_registry(connect=list(endpoints), namespace=namespace, user=user or None, password=password)
    stack.callback(registry.close)
    evaluator = stack.enter_context(
        RemoteEvaluator(
            list(endpoints),
            namespace=namespace,
            user=user or None,
            password=password,
            worker_id=worker_id,
            timeout=timeout,
        )
    )
    return registry, evaluator


def _local_registry_and_evaluator(
    stack: contextlib.ExitStack,
    root: Path,
    *,
    phi: str,
    actor: str,
    horizon: int | None = None,
    trace_dir: Path | None = None,
) -> tuple[Any, Any]:
    """A local registry and an in-process evaluator on it, both closed with ``stack``."""
    from capevo.agent import DecompositionPolicy, IdentityMemory, identity_hash
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.evaluator import LocalEvaluator

    if not (root / "registry.sqlite3").is_file():
        raise Invalid(f"no registry at {str(root)!r} (no registry.sqlite3 there)", details={"field": "root"})
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    registry = stack.enter_context(LocalRegistry(root, actor=actor))
    evaluator = stack.enter_context(
        LocalEvaluator(
            registry,
            policy=policy,
            phi=phi,
            horizon=horizon,
            trace_dir=trace_dir,
            agent_identity_hash=identity_hash(policy, policy.identity),
            worker_id="capevo-runtime-evaluate",
        )
    )
    return registry, evaluator


def _evaluate_locally(
    root: Path,
    task: str,
    pinned: dict[str, int],
    seeds: list[int],
    *,
    phi: str,
    horizon: int | None,
    actor: str | None,
    trace_dir: Path | None,
) -> list[Any]:
    with contextlib.ExitStack() as stack:
        _, evaluator = _local_registry_and_evaluator(
            stack, root, phi=phi, actor=actor or "evaluate", horizon=horizon, trace_dir=trace_dir
        )
        return evaluator.evaluate(task, pinned, seeds)


if __name__ == "__main__":
    runtime(prog_name="capevo runtime")
