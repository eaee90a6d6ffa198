"""Assemble and run one evolution: registry, persistent agent, runtime, learner, loop.

Two ways to run, as ``capevo evolve`` offers them:

* **embedded** (default): a :class:`~capevo.registry.local.LocalRegistry` directory (``root``),
  the runtime in this process (:class:`~capevo.runtime.evaluator.LocalEvaluator`) and the
  learner in this process. Nothing to start first.
* **connect**: a running registry server over Zenoh (:class:`~capevo.registry.client.Client`)
  and the episodes (live, gate, final) on runtime workers of the task
  (:class:`~capevo.runtime.remote_evaluator.RemoteEvaluator`; start them with
  ``capevo runtime serve --connect EP --task T --idle``), each call split across all of them.
  The learner still runs here (``learner="local"``: a neural learner's training episodes run
  in this process; CEM's candidate samples go inline to the same runtime workers), or learner workers
  publish the candidates (``learner="remote"``: ``capevo learner serve --connect EP --ecm NAME``)
  and this process only gates them.

Invariants:
1. Every resource opened here (registry, evaluator, learner, episodic memory) is closed before
   :func:`run_evolution` returns or raises.
2. Version 0 is created only after the report directory's manifest accepted the run (a run
   that cannot be resumed changes nothing in the registry).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capevo.errors import Invalid
from capevo.evolve.config import MODALITIES, NEURAL_MODALITIES, EvolveConfig, make_config
from capevo.evolve.loop import EvolutionLoop, EvolveResult, ensure_v0
from capevo.evolve.progress import ProgressSink, RecordingProgress
from capevo.evolve.state import RunManifest, load_manifest
from capevo.runtime.envelope import resolve_phi
from capevo.runtime.gate import SeedPlan
from capevo.runtime.tasks import Perturbations, task_spec

log = logging.getLogger(__name__)

DEFAULT_ROOT = Path("./capevo-data")
DEFAULT_REPORTS = Path("./capevo-reports")
LEARNER_MODES: tuple[str, ...] = ("local", "remote")


@dataclass(frozen=True, slots=True, kw_only=True)
class EvolveOptions:
    """What ``capevo evolve`` was asked to do.

    Args:
        task: Task id or name (``T1``, ``pick``, ...).
        preset: Budget preset (:func:`capevo.evolve.config.make_config`).
        iterations: Overrides the preset's number of iterations.
        live_episodes: Overrides the preset's live episodes per iteration (iteration 0's are
            also the final evaluation's seeds).
        gate_extension: Overrides the gate's second look (``GateConfig.extend_n``, paired seeds).
        updates_per_iteration: Overrides how many ECMs one iteration may learn in sequence
            (0: one per decomposition step).
        tie_siblings: Search one parameter set for an ECM and its siblings
            (``CemSettings.tie_siblings``; T5's same step for its three objects). ``code`` only.
        root: Local registry directory (embedded mode).
        connect: Zenoh endpoints of a registry server (connect mode); overrides ``root``.
        namespace, user, password, timeout: Zenoh registry client settings.
        report_dir: Report and resume state; default ``./capevo-reports/<task>``.
        modality: ``code``, ``rl``, ``il`` or ``hybrid``.
        seed: Seed plan (disjoint train/gate/live seeds) and learners' seeds.
        perturbations: Task perturbations on (the benchmark setting) or off.
        phi: Overrides the preset's envelope (``"task"``, ``"paper"`` or a Φ YAML path).
        learner: ``local`` (in this process) or ``remote`` (learner workers publish candidates).
        learner_timeout_s: With remote learners, how long one iteration waits for a candidate.
        wait_for_worker_s: With remote runtime workers, how long to wait for one to serve.
        evaluate_timeout_s: Seconds one remote evaluation may take.
        identity_path: M_id YAML; default the packaged identity.
        config: A full config instead of ``preset`` (+ ``iterations``).
    """

    task: str
    preset: str = "cpu-small"
    iterations: int | None = None
    live_episodes: int | None = None
    gate_extension: int | None = None
    updates_per_iteration: int | None = None
    tie_siblings: bool = False
    root: Path = DEFAULT_ROOT
    connect: tuple[str, ...] = ()
    namespace: str = "capevo"
    user: str | None = None
    password: str | None = field(default=None, repr=False)
    timeout: float = 10.0
    report_dir: Path | None = None
    modality: str = "code"
    seed: int = 0
    perturbations: bool = True
    phi: str | None = None
    learner: str = "local"
    learner_timeout_s: float | None = 600.0
    wait_for_worker_s: float = 120.0
    evaluate_timeout_s: float = 1800.0
    identity_path: Path | None = None
    config: EvolveConfig | None = None

    def __post_init__(self) -> None:
        task_spec(self.task)
        if self.modality not in MODALITIES:
            raise Invalid(
                f"unknown modality {self.modality!r}; valid: {', '.join(MODALITIES)}", details={"field": "modality"}
            )
        if self.learner not in LEARNER_MODES:
            raise Invalid(
                f"unknown learner mode {self.learner!r}; valid: {', '.join(LEARNER_MODES)}",
                details={"field": "learner"},
            )
        if self.learner == "remote" and not self.connect:
            raise Invalid(
                "remote learners publish to a registry server: give --connect ENDPOINT with --learner remote",
                details={"field": "learner"},
            )
        if self.tie_siblings and self.modality != "code":
            raise Invalid(
                f"--tie-siblings ties the parameters of code skills searched by CEM: it needs --modality code, "
                f"not {self.modality!r}",
                details={"field": "tie_siblings"},
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise Invalid(f"seed must be a non-negative integer, got {self.seed!r}", details={"field": "seed"})

    @property
    def mode(self) -> str:
        return "connect" if self.connect else "embedded"

    def resolved_report_dir(self) -> Path:
        return self.report_dir if self.report_dir is not None else DEFAULT_REPORTS / task_spec(self.task).name

    def resolved_config(self) -> EvolveConfig:
        changes = {
            "iterations": self.iterations,
            "live_episodes": self.live_episodes,
            "updates_per_iteration": self.updates_per_iteration,
            "phi": self.phi,
        }
        changes = {k: v for k, v in changes.items() if v is not None}
        config = self.config if self.config is not None else make_config(self.preset)
        if self.gate_extension is not None:
            changes["gate"] = dataclasses.replace(config.gate, extend_n=self.gate_extension)
        if self.tie_siblings:
            changes["cem"] = dataclasses.replace(config.cem, tie_siblings=True)
        return config.replace(**changes) if changes else config

    def registry_where(self) -> str:
        return ",".join(self.connect) if self.connect else str(Path(self.root).resolve())


def open_registry_for(options: EvolveOptions, *, actor: str = "evolve") -> Any:
    """The run's registry: a LocalRegistry at ``root`` or a Zenoh client of ``connect``."""
    from capevo.registry.open import open_registry

    if options.connect:
        return open_registry(
            connect=options.connect,
            namespace=options.namespace,
            user=options.user,
            password=options.password,
            timeout=options.timeout,
            actor=actor,
        )
    # Login settings (say CAPEVO_USER from the environment) mean nothing to a local registry.
    return open_registry(root=options.root, actor=actor)


def run_evolution(
    options: EvolveOptions,
    *,
    progress: ProgressSink | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> EvolveResult:
    """Run (or resume) the evolution ``options`` describe and write its report.

    Returns:
        The loop's result (rows, final evaluation, identity hash, report files).

    Raises:
        IdentityViolation: the agent changed (against the run's manifest or during the run).
        Invalid: bad options, or a report directory holding a run with other settings.
        Unavailable, Timeout: the registry or the runtime workers cannot be reached.
    """
    from capevo.agent import DecompositionPolicy, EpisodicMemory, IdentityMemory, PersistentAgent, load_identity
    from capevo.learner.presets import make_preset

    spec = task_spec(options.task)
    config = options.resolved_config()
    config.check_budget(spec.name, modality=options.modality)
    report_dir = options.resolved_report_dir()
    report_dir.mkdir(parents=True, exist_ok=True)
    sink: ProgressSink = progress if progress is not None else RecordingProgress()
    perturbations = Perturbations() if options.perturbations else Perturbations.none()
    with contextlib.ExitStack() as stack:
        stack.callback(sink.close)
        identity = load_identity(options.identity_path) if options.identity_path else IdentityMemory.default()
        policy = DecompositionPolicy(identity=identity)
        memory = EpisodicMemory(report_dir / "agent" / "episodic.jsonl")
        stack.callback(memory.close)
        agent = PersistentAgent(policy, identity, memory)
        manifest = RunManifest(
            task=spec.name,
            modality=options.modality,
            seed=options.seed,
            perturbations=options.perturbations,
            config=config,
            identity_hash=agent.identity_hash,
            mode=options.mode,
            registry=options.registry_where(),
            learner=options.learner,
            created_at=time.time(),
        )
        on_disk = load_manifest(report_dir)
        if on_disk is not None:
            on_disk.check_resume(manifest)
        registry = open_registry_for(options)
        stack.callback(registry.close)
        learner_preset = make_preset(config.learner_preset)
        created = ensure_v0(
            registry,
            spec.name,
            modality=options.modality,
            net_arch=learner_preset.sac.net_arch,
            seed=options.seed,
        )
        if created:
            sink.message(
                "created version 0 (manual creation): "
                + ", ".join(f"{r.name}@{r.version} ({r.kind.value}, origin {r.origin.value})" for r in created)
            )
        sink.message(f"safety envelope Φ: {config.phi} (hash {resolve_phi(config.phi, spec).hash[:12]})")
        evaluator = _evaluator(options, registry, agent, config, perturbations, report_dir)
        stack.callback(_close, evaluator)
        updater = _updater(options, registry, agent, config, perturbations, report_dir, should_stop)
        stack.callback(updater.close)
        loop = EvolutionLoop(
            task=spec.name,
            config=config,
            registry=registry,
            evaluator=evaluator,
            updater=updater,
            agent=agent,
            report_dir=report_dir,
            manifest=manifest,
            plan=SeedPlan(base_seed=options.seed),
            modality=options.modality,
            progress=sink,
            wait_for_worker_s=options.wait_for_worker_s if options.connect else 0.0,
            created=created,
        )
        return loop.run(should_stop=should_stop)
    raise AssertionError("unreachable")  # pragma: no cover - the with block returns or raises


def _close(obj: Any) -> None:
    close = getattr(obj, "close", None)
    if callable(close):
        close()


def _evaluator(
    options: EvolveOptions,
    registry: Any,
    agent: Any,
    config: EvolveConfig,
    perturbations: Perturbations,
    report_dir: Path,
) -> Any:
    if options.connect:
        from capevo.runtime.remote_evaluator import RemoteEvaluator

        # the workers' traces come back into the report (the loop reads the live ones to pick
        # the ECM to update), also from workers on other hosts
        return RemoteEvaluator(
            list(options.connect),
            namespace=options.namespace,
            user=options.user,
            password=options.password,
            timeout=options.evaluate_timeout_s,
            trace_dir=report_dir / "traces" / "live",
        )
    from capevo.runtime.evaluator import LocalEvaluator

    traces = report_dir / "traces" / "live"
    traces.mkdir(parents=True, exist_ok=True)
    return LocalEvaluator(
        registry,
        policy=agent,
        trace_dir=traces,
        perturbations=perturbations,
        phi=config.phi,
        horizon=config.horizon,
        step_budget_per_ecm=config.step_budget_per_ecm,
        agent_identity_hash=agent.identity_hash,
        worker_id="evolve",
    )


def _updater(
    options: EvolveOptions,
    registry: Any,
    agent: Any,
    config: EvolveConfig,
    perturbations: Perturbations,
    report_dir: Path,
    should_stop: Callable[[], bool] | None,
) -> Any:
    from capevo.evolve.learners import RemoteCandidates, UpdaterContext, make_updater

    if options.learner == "remote":
        return RemoteCandidates(registry, timeout_s=options.learner_timeout_s, should_stop=should_stop)
    candidates = None
    if options.connect and options.modality not in NEURAL_MODALITIES:
        from capevo.runtime.remote_evaluator import RemoteEvaluator

        # CEM's samples run on the runtime workers too, sent inline; their traces come back
        # here, where CEM reads them (issue 19: one path for live, gate and candidate episodes).
        candidates = RemoteEvaluator(
            list(options.connect),
            namespace=options.namespace,
            user=options.user,
            password=options.password,
            timeout=options.evaluate_timeout_s,
            trace_dir=report_dir / "traces" / "learner",
        )
    context = UpdaterContext(
        registry=registry,
        task=task_spec(options.task).name,
        config=config,
        policy=agent,
        agent_identity_hash=agent.identity_hash,
        perturbations=perturbations,
        trace_dir=report_dir / "traces" / "learner",
        state_dir=report_dir / "learner-state",
        candidate_evaluator=candidates,
    )
    return make_updater(options.modality, context)


def write_report_for(options: EvolveOptions) -> list[Path]:
    """Rewrite the report of the run in ``options``' report directory from disk and the registry.

    Raises:
        NotFound: no run there.
    """
    from capevo.errors import NotFound
    from capevo.evolve.report import write_report

    directory = options.resolved_report_dir()
    manifest = load_manifest(directory)
    if manifest is None:
        raise NotFound(f"{directory} holds no evolve run (no run.json)", details={"path": str(directory)})
    if not options.connect and not Path(options.root).is_dir():
        raise NotFound(f"registry root {str(options.root)!r} does not exist", details={"field": "root"})
    registry = open_registry_for(options)
    try:
        return write_report(directory, registry=registry, manifest=manifest)
    finally:
        registry.close()


__all__ = [
    "DEFAULT_REPORTS",
    "DEFAULT_ROOT",
    "LEARNER_MODES",
    "EvolveOptions",
    "open_registry_for",
    "run_evolution",
    "write_report_for",
]
