"""The learner worker: pull the active version and the experience, learn, push a candidate.

One worker improves one ECM with one modality:

* ``rl``     SAC warm-started from the active version (:class:`~capevo.learner.rl.SacLearner`);
* ``il``     behaviour cloning from successful traces or the scripted reference
  (:class:`~capevo.learner.bc.BcLearner`);
* ``code``   CEM over a code ECM's parameters (:class:`~capevo.learner.search.CemSearch`);
* ``hybrid`` LLM structural edit + CEM (:class:`~capevo.learner.hybrid.HybridLearner`; plain
  CEM when no ``CAPEVO_LLM_*`` endpoint is configured).

Each update reads the ECM's active version from the registry (any
:class:`~capevo.registry.api.Registry`: a Zenoh :class:`~capevo.registry.client.Client` or a
local directory), runs the learner with the preset's budget, and publishes the result as a
*candidate* with origin, parent and provenance (learner id, config hash, traces used). It never
promotes: the gate decides.

With ``once`` the worker does one update and returns. Otherwise it watches: new
``/episode/summary`` records in the trace files or directories it was given (episodes that ran
the ECM's active version) feed an :class:`~capevo.learner.trigger.UpdateTrigger`; a change of
the ECM's active version (a promotion, a rollback) resets it, since that evidence was about
another version. The active pointer is read on every pass; registry events of the ECM only wake
the loop early. It updates whenever the trigger fires, until ``stop`` is set (SIGTERM/SIGINT with
``handle_signals``). A stop during SAC training ends training early and nothing is published.
Several workers may run at once (also on the same ECM): learner ids are unique and each publish
is one registry transaction, so versions never collide.

Events (``emit``), each a dict with ``event`` and ``learner_id``: ``ready``, ``waiting``,
``trigger``, ``training``, ``published``, ``unchanged`` (a code search kept the parent's
source: nothing published), ``abandoned``, ``error``, ``stopped``.

Invariants:
1. A worker publishes only candidates, each with ``parent`` = the active version it learned
   from and provenance naming its ``learner_id`` and a ``config_hash``.
2. ``run(once=True)`` publishes exactly one version or raises, unless the learner returned the
   parent's own code (``unchanged``) or ``stop`` was set.
3. In watch mode an update happens only when the trigger fires, and at most one update per
   firing; episodes are counted once each.
4. After ``stop`` is set nothing more is published.
5. Every training episode (code learners' seeds and neural learners' task seeds) lies in the
   training block of the worker's seed plan, never in its gate or live blocks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capevo.errors import CapevoError, Invalid, NotFound, Timeout, Unavailable
from capevo.learner.base import Candidate, LearnRequest
from capevo.learner.bc import default_learner_id
from capevo.learner.presets import Preset, make_preset
from capevo.learner.trigger import TriggerConfig, UpdateTrigger
from capevo.records import AuditEvent, EcmVersion, Kind
from capevo.registry.api import Registry
from capevo.runtime.envelope import DEFAULT_PHI, check_phi_choice
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate import SeedPlan
from capevo.runtime.tasks import Perturbations, task_of, task_spec
from capevo.shutdown import stop_on_signals

log = logging.getLogger(__name__)

Emit = Callable[[dict[str, Any]], Any]
MAX_OUTCOMES = 200
"""Recent episodes handed to a learner (the newest)."""
TRAIN_SEEDS = 16
"""Training seeds offered to code learners."""
WORKER_TRAIN_OFFSET = 50_000
"""Learner workers train in the second half of their seed plan's training block (``capevo
evolve``'s in-process learners start at its beginning); never in its gate or live blocks."""


def worker_training_seeds(plan: SeedPlan, seed: int) -> tuple[int, ...]:
    """The code learners' training seeds of a worker seeded ``seed``: inside ``plan``'s training block.

    Workers with different seeds get different slices (cycling within the block's second half),
    and no slice ever reaches the plan's held-out gate seeds.
    """
    half = plan.block - WORKER_TRAIN_OFFSET
    offset = WORKER_TRAIN_OFFSET + (seed * TRAIN_SEEDS) % max(half - TRAIN_SEEDS, 1)
    return tuple(plan.train(TRAIN_SEEDS, offset=offset))


# --- configuration -----------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class LearnerConfig:
    """Settings of one learner worker.

    Args:
        ecm: The ECM to improve.
        modality: One of :func:`modalities`.
        task: Task id or name; default the ECM name's prefix.
        preset: Budget name (:mod:`capevo.learner.presets`).
        learner_id: Default ``<modality>-<host>-<pid>-<random>``.
        traces: Trace files or directories of ``*.mcap`` (experience and trigger input).
        work_dir: Scratch space (code learners' evaluation traces); default a temporary directory.
        once: One update, then return.
        trigger: When to update in watch mode.
        poll_interval_s: How often trace files are re-read in watch mode.
        perturbations: Task perturbations for training; default all on.
        phi: The envelope training episodes run under: ``"task"`` (default), ``"paper"`` or a Φ
            YAML path (:mod:`capevo.runtime.envelope`); use the runtime's, so candidates learn
            inside the envelope they will be gated and run under.
        seed: Seeds the learners (and offsets training episodes).
        seed_plan: Which :class:`~capevo.runtime.gate.SeedPlan` the run uses (``capevo evolve
            --seed``): training episodes come from its training block only, so they never
            replay the gate's held-out seeds.
        progress_bar: Show training progress bars (stderr).
        torch_threads: CPU threads for torch (None: torch's default).

    Raises:
        Invalid: unknown modality, preset or task; a bad value.
    """

    ecm: str
    modality: str
    task: str | None = None
    preset: str = "cpu-small"
    learner_id: str | None = None
    traces: tuple[Path, ...] = ()
    work_dir: Path | None = None
    once: bool = False
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    poll_interval_s: float = 5.0
    perturbations: Perturbations = field(default_factory=Perturbations)
    phi: str = DEFAULT_PHI
    seed: int = 0
    seed_plan: int = 0
    progress_bar: bool = False
    torch_threads: int | None = 1

    def __post_init__(self) -> None:
        if self.modality not in _MODALITIES:
            raise Invalid(
                f"unknown modality {self.modality!r}; valid: {', '.join(modalities())}", details={"field": "modality"}
            )
        make_preset(self.preset)
        check_phi_choice(self.phi)
        if self.task is not None:
            spec = task_spec(self.task)
            if self.ecm not in spec.ecm_names:
                raise Invalid(
                    f"task {spec.name!r} has no ECM {self.ecm!r}; valid: {', '.join(spec.ecm_names)}",
                    details={"field": "ecm"},
                )
        else:
            task_of(self.ecm)
        p = self.poll_interval_s
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not p > 0:
            raise Invalid(f"poll_interval_s must be positive, got {p!r}", details={"field": "poll_interval_s"})
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise Invalid(f"seed must be a non-negative integer, got {self.seed!r}", details={"field": "seed"})
        try:
            SeedPlan(base_seed=self.seed_plan)
        except Invalid as exc:
            raise Invalid(f"seed_plan: {exc.message}", details={"field": "seed_plan"}) from None

    @property
    def task_name(self) -> str:
        return task_spec(self.task).name if self.task is not None else task_of(self.ecm)


# --- modalities ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class LearnerContext:
    """What a modality factory may use to build its learner."""

    registry: Registry
    task: str
    ecm: str
    preset: Preset
    learner_id: str
    traces: tuple[str, ...]
    work_dir: Path
    should_stop: Callable[[], bool]
    progress_bar: bool
    torch_threads: int | None
    open_candidate_evaluator: Callable[[Path], Any] | None = None
    """Builds the evaluator that runs code learners' candidate samples, given the directory their
    traces go to (a :class:`~capevo.runtime.remote_evaluator.RemoteEvaluator`: the samples run on the
    runtime workers, sent inline, and their traces come back to that directory); None runs them
    in this process over a scratch mirror of the registry."""


Factory = Callable[[LearnerContext], contextlib.AbstractContextManager[Any]]
_MODALITIES: dict[str, Factory] = {}


def register_modality(name: str) -> Callable[[Factory], Factory]:
    """Decorator: ``fn(context)`` returns a context manager yielding a learner for ``name``."""

    def deco(fn: Factory) -> Factory:
        _MODALITIES[name] = fn
        return fn

    return deco


def modalities() -> tuple[str, ...]:
    return tuple(_MODALITIES)


def make_learner(modality: str, context: LearnerContext) -> contextlib.AbstractContextManager[Any]:
    """A context manager yielding the learner of ``modality``.

    Raises:
        Invalid: unknown modality; the message lists the valid ones.
    """
    factory = _MODALITIES.get(modality)
    if factory is None:
        raise Invalid(f"unknown modality {modality!r}; valid: {', '.join(modalities())}", details={"field": "modality"})
    return factory(context)


@register_modality("rl")
@contextlib.contextmanager
def _rl(ctx: LearnerContext) -> Iterator[Any]:
    from capevo.learner.rl import SacLearner

    p = ctx.preset
    yield SacLearner(
        config=p.sac,
        env_config=p.env,
        shaping=p.shaping,
        registry=ctx.registry,
        distill=p.bc,
        distill_episodes=p.distill_episodes,
        traces=ctx.traces,
        learner_id=ctx.learner_id,
        progress_bar=ctx.progress_bar,
        should_stop=ctx.should_stop,
        torch_threads=ctx.torch_threads,
    )


@contextlib.contextmanager
def _progress_bar(enabled: bool, description: str, total: int) -> Iterator[Callable[[int], None] | None]:
    """A rich progress bar on stderr; yields ``advance_to(done)`` (None when disabled)."""
    if not enabled:
        yield None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True), transient=False) as bar:
        task = bar.add_task(description, total=total)
        yield lambda done: bar.update(task, completed=done)


@register_modality("il")
@contextlib.contextmanager
def _il(ctx: LearnerContext) -> Iterator[Any]:
    from capevo.learner.bc import BcLearner

    p = ctx.preset
    with _progress_bar(ctx.progress_bar, f"cloning {ctx.ecm}", p.bc.epochs * (1 + p.bc.dagger_rounds)) as advance:
        yield BcLearner(
            config=p.bc,
            env_config=p.env,
            registry=ctx.registry,
            traces=ctx.traces,
            scripted_episodes=p.scripted_episodes,
            learner_id=ctx.learner_id,
            progress=(lambda epoch, _epochs, _loss: advance(epoch)) if advance is not None else None,
            torch_threads=ctx.torch_threads,
            should_stop=ctx.should_stop,
        )


@contextlib.contextmanager
def _scratch_evaluator(ctx: LearnerContext) -> Iterator[Any]:
    """Runs unpublished code candidates on the runtime workers (``ctx.open_candidate_evaluator``) or
    on a private mirror of the registry in this process."""
    from capevo.agent.identity import IdentityMemory
    from capevo.agent.policy import DecompositionPolicy
    from capevo.learner.scratch import ScratchRegistryEvaluator
    from capevo.runtime.evaluator import LocalEvaluator

    trace_dir = ctx.work_dir / "candidate-traces"
    if ctx.open_candidate_evaluator is not None:
        remote = ctx.open_candidate_evaluator(trace_dir)
        try:
            yield remote
        finally:
            remote.close()
        return

    def make(reg: Registry) -> LocalEvaluator:
        return LocalEvaluator(
            reg,
            policy=DecompositionPolicy(identity=IdentityMemory.default()),
            trace_dir=trace_dir,
            perturbations=ctx.preset.env.perturbations,
            phi=ctx.preset.env.phi,
        )

    with ScratchRegistryEvaluator(ctx.registry, make, root=ctx.work_dir / "scratch") as evaluator:
        yield evaluator


def _cem(ctx: LearnerContext, evaluator: Any, learner_id: str, advance: Callable[[int], None] | None) -> Any:
    from capevo.learner.search import CemSearch

    p = ctx.preset
    seen = [0]

    def progress(_event: Any) -> None:
        seen[0] += 1
        if advance is not None:
            advance(seen[0])

    return CemSearch(
        evaluator,
        population=p.cem_population,
        iterations=p.cem_iterations,
        episodes_per_candidate=p.cem_episodes,
        seed=p.sac.seed,
        learner_id=learner_id,
        progress=progress,
    )


@register_modality("code")
@contextlib.contextmanager
def _code(ctx: LearnerContext) -> Iterator[Any]:
    total = ctx.preset.cem_population * ctx.preset.cem_iterations
    with _scratch_evaluator(ctx) as evaluator, _progress_bar(ctx.progress_bar, f"CEM {ctx.ecm}", total) as advance:
        yield _cem(ctx, evaluator, ctx.learner_id, advance)


@register_modality("hybrid")
@contextlib.contextmanager
def _hybrid(ctx: LearnerContext) -> Iterator[Any]:
    from capevo.learner.chat import Chat, ChatConfig
    from capevo.learner.hybrid import HybridLearner
    from capevo.learner.synthesis import LlmSynthesis

    chat_config = ChatConfig.from_env()
    chat = Chat(chat_config) if chat_config is not None else None
    total = ctx.preset.cem_population * ctx.preset.cem_iterations
    with _scratch_evaluator(ctx) as evaluator, _progress_bar(ctx.progress_bar, f"CEM {ctx.ecm}", total) as advance:
        synthesis = LlmSynthesis(chat, evaluator=evaluator, learner_id=f"{ctx.learner_id}:llm")
        yield HybridLearner(synthesis, _cem(ctx, evaluator, f"{ctx.learner_id}:cem", advance))


# --- experience ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class SeenEpisode:
    """One finished episode read from a trace."""

    path: str
    summary: Any
    """The :class:`~capevo.runtime.traces.EpisodeSummary`."""

    def outcome(self) -> EpisodeOutcome | None:
        """As an evaluation outcome (None when the episode had no seed)."""
        s = self.summary
        if s.seed is None:
            return None
        return EpisodeOutcome(
            seed=int(s.seed),
            success=bool(s.success),
            reward=float(s.total_reward),
            steps=int(s.steps),
            duration_s=float(s.duration_s),
            interventions=int(s.interventions),
            unsafe_steps=int(s.unsafe_steps),
            ecm_failures=0,
            capability_set=dict(s.capability_set),
            trace_path=self.path,
        )


class EpisodeFeed:
    """New ``/episode/summary`` records in trace files and directories, each returned once.

    Args:
        paths: Files or directories (their ``*.mcap`` files, not recursive; files created later
            are picked up).
        task: Only traces of this task are read.
    """

    def __init__(self, paths: Sequence[str | Path], *, task: str) -> None:
        self.paths = tuple(Path(p) for p in paths)
        self.task = task_spec(task).name
        self._seen: dict[Path, int] = {}
        self._other_task: set[Path] = set()

    def files(self) -> list[Path]:
        from capevo.runtime.traces.files import trace_files

        return trace_files(self.paths, missing_ok=True)

    def poll(self) -> list[SeenEpisode]:
        """Episodes finished since the last poll, in file order (files in name order)."""
        from capevo.runtime.traces import EpisodeSummary, TraceReader

        new: list[SeenEpisode] = []
        for f in self.files():
            if f in self._other_task:
                continue
            try:
                with TraceReader(f, allow_incomplete=True) as reader:
                    if reader.metadata().task != self.task:
                        self._other_task.add(f)
                        continue
                    summaries = [r for r in reader.records([EpisodeSummary.TOPIC]) if isinstance(r, EpisodeSummary)]
            except Exception as exc:  # a trace another process is writing right now, or a damaged one
                log.debug("cannot read %s yet: %s", f, exc)
                continue
            done = self._seen.get(f, 0)
            new.extend(SeenEpisode(path=str(f), summary=s) for s in summaries[done:])
            self._seen[f] = max(done, len(summaries))
        return new


# --- the worker ----------------------------------------------------------------------------


class LearnerWorker:
    """Runs one learner against a registry (see the module docstring).

    Args:
        config: What to learn and how.
        open_registry: Returns the registry to use (called once per run; the worker closes it).
        emit: Receives every event dict.
        open_candidate_evaluator: Given a trace directory, returns the evaluator code learners'
            candidate samples run on (a :class:`~capevo.runtime.remote_evaluator.RemoteEvaluator`: on the
            runtime workers); None runs them in this process. Called once per update; the worker
            closes what it returns.
    """

    def __init__(
        self,
        config: LearnerConfig,
        open_registry: Callable[[], Registry],
        *,
        emit: Emit | None = None,
        open_candidate_evaluator: Callable[[Path], Any] | None = None,
    ):
        self.config = config
        self.task = config.task_name
        self.learner_id = config.learner_id or default_learner_id(config.modality)
        self.seed_plan = SeedPlan(base_seed=config.seed_plan)
        preset = make_preset(config.preset).with_perturbations(config.perturbations).with_seed(config.seed)
        # Neural training episodes run task seeds seed_base + seed + k: keep them in the plan's training block.
        train = self.seed_plan.range("train")
        env = dataclasses.replace(
            preset.env, seed_base=train.start + WORKER_TRAIN_OFFSET, seed=config.seed % (WORKER_TRAIN_OFFSET // 2)
        )
        self.preset = dataclasses.replace(preset, env=dataclasses.replace(env, phi=config.phi))
        self._open_registry = open_registry
        self._open_candidate_evaluator = open_candidate_evaluator
        self._emit_fn = emit
        self._wake = threading.Event()
        self.published: list[EcmVersion] = []

    # --- plumbing ---------------------------------------------------------------------------

    def _emit(self, event: str, **fields: Any) -> None:
        record = {"event": event, "learner_id": self.learner_id, **fields}
        if self._emit_fn is not None:
            self._emit_fn(record)

    def _on_registry_event(self, event: AuditEvent, record: EcmVersion) -> None:
        if event.name == self.config.ecm:
            self._wake.set()

    def _connect(self, stop: threading.Event) -> Registry | None:
        delay = 1.0
        announced = False
        while True:
            try:
                return self._open_registry()
            except (Unavailable, Timeout) as exc:
                if self.config.once:
                    raise
                if not announced:
                    self._emit("waiting", reason=str(exc))
                    announced = True
                if stop.wait(delay):
                    return None
                delay = min(delay * 2, 30.0)

    def _subscribe(self, registry: Registry, stack: contextlib.ExitStack) -> None:
        subscribe = getattr(registry, "subscribe_events", None)
        if callable(subscribe):
            stack.enter_context(subscribe(self.config.ecm, self._on_registry_event))
            return
        add = getattr(registry, "add_listener", None)
        if callable(add):
            listener = _Listener(self._on_registry_event)
            add(listener)
            stack.callback(registry.remove_listener, listener)  # type: ignore[attr-defined]

    # --- one update -------------------------------------------------------------------------

    def request(self, registry: Registry, outcomes: Sequence[EpisodeOutcome] = ()) -> LearnRequest:
        """The learn request for the ECM's active version.

        Raises:
            NotFound: the ECM has no active version.
        """
        try:
            parent = registry.get_version(self.config.ecm)
        except NotFound as exc:
            raise NotFound(
                f"{self.config.ecm} has no active version to learn from; publish and promote a v0 first "
                f"(e.g. capevo ecm seed): {exc.message}",
                details={"ecm": self.config.ecm},
            ) from None
        source = ""
        if parent.kind is Kind.CODE:
            source = registry.get_artifact(self.config.ecm, parent.version).decode("utf-8")
        elif self.config.modality in ("code", "hybrid"):
            raise Invalid(
                f"{self.config.ecm}@{parent.version} is a {parent.kind.value} ECM; modality "
                f"{self.config.modality!r} improves code ECMs (use rl or il)",
                details={"field": "modality"},
            )
        seeds = worker_training_seeds(self.seed_plan, self.config.seed)
        return LearnRequest(
            task=self.task,
            ecm=self.config.ecm,
            parent=parent,
            source=source,
            train_seeds=seeds,
            outcomes=tuple(outcomes[-MAX_OUTCOMES:]),
        )

    def update(
        self, registry: Registry, stop: threading.Event, *, reason: str, outcomes: Sequence[EpisodeOutcome] = ()
    ) -> EcmVersion | None:
        """Learn once from the active version and publish the candidate.

        Returns:
            The published version; None when ``stop`` was set meanwhile or the result is the
            parent's own code (nothing published).

        Raises:
            CapevoError: the request or the learner failed.
        """
        request = self.request(registry, outcomes)
        self._emit(
            "training",
            ecm=request.ecm,
            parent=request.parent.version,
            parent_kind=request.parent.kind.value,
            modality=self.config.modality,
            preset=self.preset.name,
            reason=reason,
            episodes=len(request.outcomes),
        )
        work = self.config.work_dir
        with contextlib.ExitStack() as stack:
            if work is None:
                work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="capevo-learner-")))
            context = LearnerContext(
                registry=registry,
                task=self.task,
                ecm=self.config.ecm,
                preset=self.preset,
                learner_id=self.learner_id,
                traces=tuple(str(t) for t in self.config.traces),
                work_dir=Path(work),
                should_stop=stop.is_set,
                progress_bar=self.config.progress_bar,
                torch_threads=self.config.torch_threads,
                open_candidate_evaluator=self._open_candidate_evaluator,
            )
            started = time.perf_counter()
            try:
                with make_learner(self.config.modality, context) as learner:
                    candidate: Candidate = learner.learn(request)
            except CapevoError:
                if not stop.is_set():
                    raise
                # cut short by the stop (e.g. too few demonstrations collected): not a failure
                self._emit("abandoned", ecm=request.ecm, reason="stopped during training; nothing published")
                return None
            seconds = time.perf_counter() - started
        if stop.is_set():
            self._emit("abandoned", ecm=request.ecm, reason="stopped during training; nothing published")
            return None
        if request.parent.kind is Kind.CODE and candidate.artifact == request.source.encode():
            # A search whose best sample was the parent itself: a copy would only burden the gate.
            self._emit("unchanged", ecm=request.ecm, parent=request.parent.version, notes=_jsonable(candidate.notes))
            return None
        record = registry.publish(candidate.ecm, candidate.artifact, candidate.spec)
        self.published.append(record)
        self._emit(
            "published",
            ecm=record.name,
            version=record.version,
            parent=record.parent,
            kind=record.kind.value,
            origin=record.origin.value,
            state=record.state.value,
            provenance=record.provenance.to_dict(),
            seconds=seconds,
            notes=_jsonable(candidate.notes),
        )
        return record

    # --- the loop ---------------------------------------------------------------------------

    def run(self, stop: threading.Event | None = None, *, handle_signals: bool = True) -> int:
        """Update once (``config.once``) or watch and update until ``stop``.

        Returns:
            The number of versions published.

        Raises:
            CapevoError: with ``once``, whatever kept the update from publishing; in watch mode
                only failures to start (a bad configuration).
        """
        stop = stop if stop is not None else threading.Event()
        with contextlib.ExitStack() as stack:
            stack.enter_context(stop_on_signals(stop, self._wake, enabled=handle_signals, what="learner"))
            stack.callback(lambda: self._emit("stopped", published=len(self.published)))
            registry = self._connect(stop)
            if registry is None:
                return 0
            stack.callback(registry.close)
            self._emit(
                "ready",
                ecm=self.config.ecm,
                task=self.task,
                modality=self.config.modality,
                preset=self.preset.name,
                once=self.config.once,
            )
            if self.config.once:
                self.update(registry, stop, reason="once")
                return len(self.published)
            self._subscribe(registry, stack)
            self._watch(registry, stop)
        return len(self.published)

    def _active(self, registry: Registry) -> int | None:
        try:
            return registry.capability_set().active.get(self.config.ecm)
        except (Unavailable, Timeout) as exc:
            log.warning("registry unreachable: %s", exc)
            return None

    def _watch(self, registry: Registry, stop: threading.Event) -> None:
        feed = EpisodeFeed(self.config.traces, task=self.task)
        trigger = UpdateTrigger(self.config.trigger)
        active = self._active(registry)
        outcomes: list[EpisodeOutcome] = []
        while not stop.is_set():
            # Events only wake the loop early: a registry opened elsewhere (another process, or
            # another LocalRegistry object) tells no listener here, so the pointer is read every pass.
            now = self._active(registry)
            if now is not None and now != active:
                log.info("%s active version %s -> %s; trigger reset", self.config.ecm, active, now)
                trigger.reset()
                outcomes.clear()
                active = now
            for seen in feed.poll():
                if active is None or seen.summary.capability_set.get(self.config.ecm) != active:
                    continue
                trigger.observe(bool(seen.summary.success))
                outcome = seen.outcome()
                if outcome is not None:
                    outcomes.append(outcome)
            del outcomes[:-MAX_OUTCOMES]
            decision = trigger.check()
            if decision.fire and active is not None:
                self._emit("trigger", ecm=self.config.ecm, active=active, **decision.to_dict())
                try:
                    self.update(registry, stop, reason=decision.reason, outcomes=outcomes)
                except CapevoError as exc:
                    log.error("update of %s failed: %s", self.config.ecm, exc)
                    self._emit("error", ecm=self.config.ecm, code=exc.code.value, message=exc.message)
                except Exception as exc:  # a learner bug must not end a long-running worker
                    log.exception("update of %s crashed", self.config.ecm)
                    self._emit("error", ecm=self.config.ecm, code="internal", message=f"{type(exc).__name__}: {exc}")
                trigger.mark_updated()
            self._wake.wait(self.config.poll_interval_s)
            self._wake.clear()


class _Listener:
    """Adapts a callback to :class:`~capevo.registry.local.EventListener`."""

    def __init__(self, callback: Callable[[AuditEvent, EcmVersion], Any]) -> None:
        self._callback = callback

    def on_event(self, event: AuditEvent, record: EcmVersion) -> None:
        self._callback(event, record)


def _jsonable(value: Any) -> Any:
    """``value`` with anything JSON cannot hold turned into strings."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)
