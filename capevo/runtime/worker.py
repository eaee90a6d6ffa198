"""The runtime worker: a process that runs a task's episodes with the registry's active ECMs.

``capevo runtime serve --connect EP --task T1`` (see :mod:`capevo.cli.runtime`) runs a
:class:`RuntimeWorker`:

* resolves the task's capability set from the registry and fetches each artifact once
  (cached on disk by sha256, see :mod:`capevo.runtime.artifact_cache`);
* subscribes to the registry's events and, on a ``promote`` or ``rollback`` of an ECM it
  runs, hot-swaps that ECM at the next episode boundary (never inside an ECM execution);
* announces itself and what it runs on Zenoh (:mod:`capevo.runtime.worker_protocol`);
* keeps running episodes on its last good versions while the registry is away; when the
  registry's liveliness token returns it re-reads the capability set and catches up;
* serves evaluation requests (``evaluate(task, versions, seeds)``, optionally with inline
  candidate artifacts in place of some ECMs' registry artifacts) between its own episodes, on
  its own environment; :class:`~capevo.runtime.remote_evaluator.RemoteEvaluator` is the client
  side, and splits one call's seeds across every live worker of the task
  (:mod:`capevo.runtime.fanout`);
* shuts down cleanly on SIGTERM/SIGINT (ends the running episode, replies to queued
  requests with ``unavailable``, closes traces and sessions). It never forks.

Keys, requests and replies: :mod:`capevo.runtime.worker_protocol`. Inline code never runs in the
worker's process: an override whose origin the trust policy would run in-process is refused
(:class:`Forbidden`). A call's trace file (``"traces": true``) is written to a temporary
directory and removed when the worker keeps no traces of its own (the outcomes' ``trace_path``
is then None).

Invariants:
1. The loaded versions change only between episodes (``LoadedCapabilitySet.begin_episode``).
2. Every evaluate query gets exactly one reply (outcomes or error), also when the worker
   shuts down with it queued.
3. The adoption reply always names the versions the next episode will start with, unless a
   swap is pending (then listed under ``pending``).
4. Losing the registry never stops the episode loop; nothing blocks on the registry for
   longer than the client's timeout.
5. A trace file holds only episodes of one capability set: a swap starts a new file.
6. Overrides change only the request they come with: the worker's own episodes and later
   requests load the registry's artifacts, and an override's bytes never enter the on-disk
   artifact cache.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import queue
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from capevo.errors import (
    CapevoError,
    Forbidden,
    Invalid,
    NotFound,
    Timeout,
    Unavailable,
)
from capevo.records import Action, ArtifactRef, AuditEvent, CapabilitySet, EcmVersion, Origin, State
from capevo.registry.keys import DEFAULT_NAMESPACE, Keys, validate_namespace
from capevo.runtime.artifact_cache import ArtifactCache, ArtifactStore, MemoryArtifactCache, check_sha256
from capevo.runtime.capabilities import DEFAULT_RECOVERY, LoadedCapabilitySet, check_recovery_mode
from capevo.runtime.ecm import LoadOptions, TrustPolicy
from capevo.runtime.envelope import PhiChoice, resolve_phi
from capevo.runtime.episode import (
    DEFAULT_STEP_BUDGET,
    DEFAULT_TIMEOUT_S,
    make_governor,
    run_episode_detailed,
)
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.evaluator import LocalEvaluator
from capevo.runtime.governance import Phi
from capevo.runtime.policy import DecisionPolicy
from capevo.runtime.safety_monitor import SafetyLimits
from capevo.runtime.tasks import Perturbations, TaskEnv, make_task, task_spec
from capevo.runtime.traces import (
    DEFAULT_COMPRESSION,
    TraceMetadata,
    TraceWriter,
    check_compression,
)
from capevo.runtime.worker_protocol import (
    JSON_ENCODING,
    MAX_QUEUED_EVALUATIONS,
    MAX_TRACE_REPLY_BYTES,
    Adoption,
    EvaluateRequest,
    RuntimeKeys,
    default_worker_id,
    encode_outcomes,
    first_line,
    validate_worker_id,
    zenoh_client_config,
)
from capevo.shutdown import stop_on_signals

log = logging.getLogger("capevo.runtime.worker")


@dataclass(frozen=True, slots=True, kw_only=True)
class WorkerConfig:
    """Settings of one runtime worker.

    Args:
        connect: Zenoh endpoint(s) of the registry (or a router that reaches it).
        task: Task id or name.
        namespace: Registry namespace; the worker's keys live under it too.
        user, password: Zenoh credentials (both or neither).
        worker_id: Key chunk naming this worker; default ``<host>-<pid>``.
        trace_dir: Where episode traces go (one file per capability set); None writes none.
        trace_compression: Their chunk compression: ``"lz4"`` (default), ``"zstd"`` or ``"none"``.
        cache_dir: On-disk artifact cache; None keeps artifacts in memory only.
        episodes: Episodes to run before exiting; None runs until stopped.
        idle: Run no episodes of its own; only serve evaluation requests.
        horizon: Episode length; default the task's.
        perturbations: Task perturbations; default all on.
        governance: False runs the evaluation-only counting mode.
        phi: Safety envelope: ``"task"`` (default: the task's scene-aware Φ), ``"paper"``, a Φ
            YAML path or a :class:`Phi` (see :mod:`capevo.runtime.envelope`).
        safety_limits: The hard limits the safety monitor grades ``unsafe`` against, in the
            worker's own episodes and in the evaluations it serves; default the paper's.
        seed: Seed of the first episode; episode i uses ``seed + i``.
        step_budget_per_ecm, timeout_s: Per-ECM step budget and per-call compute limit.
        recovery: ECM recovery mode.
        registry_timeout: Seconds to wait for each registry reply.
        retry_interval_s: Pause between attempts to reach the registry at start-up.
    """

    connect: tuple[str, ...]
    task: str
    namespace: str = DEFAULT_NAMESPACE
    user: str | None = None
    password: str | None = field(default=None, repr=False)
    worker_id: str | None = None
    trace_dir: Path | None = None
    trace_compression: str = DEFAULT_COMPRESSION
    cache_dir: Path | None = None
    episodes: int | None = None
    idle: bool = False
    horizon: int | None = None
    perturbations: Perturbations = field(default_factory=Perturbations)
    governance: bool = True
    phi: PhiChoice = None
    safety_limits: SafetyLimits | None = None
    seed: int = 0
    step_budget_per_ecm: int | None = DEFAULT_STEP_BUDGET
    timeout_s: float = DEFAULT_TIMEOUT_S
    recovery: str = DEFAULT_RECOVERY
    registry_timeout: float = 10.0
    retry_interval_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.connect:
            raise Invalid("a runtime worker needs the registry's endpoint (--connect)", details={"field": "connect"})
        validate_namespace(self.namespace)
        task_spec(self.task)
        check_compression(self.trace_compression)
        if self.worker_id is not None:
            validate_worker_id(self.worker_id)
        if self.episodes is not None and (isinstance(self.episodes, bool) or self.episodes < 1):
            raise Invalid(f"episodes must be >= 1, got {self.episodes!r}", details={"field": "episodes"})
        if self.idle and self.episodes is not None:
            raise Invalid("give either --idle or --episodes, not both", details={"field": "idle"})
        if isinstance(self.seed, bool) or self.seed < 0:
            raise Invalid(f"seed must be >= 0, got {self.seed!r}", details={"field": "seed"})
        check_recovery_mode(self.recovery)


EventSink = Callable[[dict[str, Any]], Any]


class _Request:
    __slots__ = ("query", "request")

    def __init__(self, query: zenoh.Query, request: EvaluateRequest) -> None:
        self.query = query
        self.request = request


def _reply(query: zenoh.Query, result: bytes | CapevoError, *, attachment: bytes | None = None) -> None:
    """Send the one reply of ``query`` and finalise it."""
    try:
        with query:
            if isinstance(result, CapevoError):
                query.reply_err(result.to_payload(), encoding=JSON_ENCODING)
            else:
                query.reply(query.key_expr, result, encoding=JSON_ENCODING, attachment=attachment)
    except zenoh.ZError as exc:
        log.warning("could not reply to %s: %s", query.selector, exc)


class _OverrideRegistry:
    """A read-only view of ``registry`` in which some ECMs' artifacts are inline bytes.

    The overridden version keeps its record (descriptor, interface, version number, so the
    outcomes name it) except the artifact reference, which names the inline bytes, and the
    origin, which is ``origin`` when given.

    Raises (from :meth:`get_version`):
        Forbidden: the trust policy would run the inline code in the worker's process.
    """

    def __init__(
        self, registry: Any, overrides: Mapping[str, bytes], origin: Origin | None, trust: TrustPolicy
    ) -> None:
        self._registry = registry
        self._bytes = dict(overrides)
        self._sha = {k: hashlib.sha256(v).hexdigest() for k, v in self._bytes.items()}
        self._origin = origin
        self._trust = trust

    def capability_set(self, revision: int | None = None) -> CapabilitySet:
        return self._registry.capability_set(revision)

    def get_ecm(self, name: str) -> Any:
        return self._registry.get_ecm(name)

    def get_version(self, name: str, version: int | None = None) -> EcmVersion:
        record = self._registry.get_version(name, version)
        data = self._bytes.get(name)
        if data is None:
            return record
        origin = self._origin or record.origin
        if self._trust.runs_in_process(record.kind, origin):
            raise Forbidden(
                f"inline artifact for {name} would run in the worker's process (origin {origin.value!r}); "
                "inline code runs only in the sandbox: give an override_origin the trust policy sandboxes",
                details={"field": "override_origin", "ecm": name},
            )
        artifact = ArtifactRef(sha256=self._sha[name], size=len(data), media_type=record.artifact.media_type)
        return dataclasses.replace(record, artifact=artifact, origin=origin)

    def get_artifact(self, name: str, version: int | None = None) -> bytes:
        data = self._bytes.get(name)
        return data if data is not None else self._registry.get_artifact(name, version)


class _OverrideCache:
    """The worker's artifact cache, except that inline bytes are served from memory and never stored."""

    def __init__(self, base: ArtifactStore, overrides: Mapping[str, bytes]) -> None:
        self._base = base
        self._inline = {hashlib.sha256(v).hexdigest(): bytes(v) for v in overrides.values()}

    def get(self, sha256: str) -> bytes | None:
        inline = self._inline.get(check_sha256(sha256))
        return inline if inline is not None else self._base.get(sha256)

    def put(self, sha256: str, data: bytes) -> None:
        if check_sha256(sha256) not in self._inline:
            self._base.put(sha256, data)

    def fetch(self, sha256: str, load: Callable[[], bytes]) -> bytes:
        inline = self._inline.get(check_sha256(sha256))
        return inline if inline is not None else self._base.fetch(sha256, load)


@contextlib.contextmanager
def _overridden(evaluator: LocalEvaluator, request: EvaluateRequest) -> Any:
    """``evaluator`` reading ``request``'s inline artifacts for the duration (invariant 6).

    The worker serves requests one at a time on its main thread, so swapping the evaluator's
    registry and cache for the call and back is safe; a copy of the evaluator would have to
    repeat its dozen settings.
    """
    if not request.overrides:
        yield evaluator
        return
    registry, cache = evaluator.registry, evaluator.cache
    trust = (evaluator.load_options or LoadOptions()).trust
    evaluator.registry = _OverrideRegistry(registry, request.overrides, request.override_origin, trust)
    evaluator.cache = _OverrideCache(cache, request.overrides)
    try:
        yield evaluator
    finally:
        evaluator.registry, evaluator.cache = registry, cache


@contextlib.contextmanager
def _trace_scratch(evaluator: LocalEvaluator, request: EvaluateRequest) -> Any:
    """A temporary trace directory for a call that asks for its trace from a worker that keeps none.

    Yields:
        True when the directory is temporary (removed on exit), False otherwise.
    """
    if not request.traces or evaluator.trace_dir is not None:
        yield False
        return
    with tempfile.TemporaryDirectory(prefix="capevo-eval-trace-") as tmp:
        evaluator.trace_dir = Path(tmp)
        try:
            yield True
        finally:
            evaluator.trace_dir = None


def _trace_bytes(outcomes: Sequence[EpisodeOutcome]) -> bytes | None:
    """The bytes of a call's one trace file (evaluator invariant 1), or None when too large or unreadable."""
    paths = {o.trace_path for o in outcomes if o.trace_path}
    if len(paths) != 1:
        return None
    path = Path(next(iter(paths)))
    try:
        size = path.stat().st_size
        if size > MAX_TRACE_REPLY_BYTES:
            log.warning("not sending trace %s back: %d bytes, over %d", path, size, MAX_TRACE_REPLY_BYTES)
            return None
        return path.read_bytes()
    except OSError as exc:
        log.warning("cannot read trace %s to send back: %s", path, exc)
        return None


class RuntimeWorker:
    """One runtime worker (see the module docstring).

    Args:
        config: Its settings.
        policy: π_A, the persistent agent's decision policy (built by the caller, which lies
            above the runtime: ``capevo runtime serve`` builds it from ``--identity``).
        agent_identity_hash: The agent's identity hash, recorded in every trace.
        emit: Called (on the main thread or a Zenoh thread) with each event as a JSON-able
            dict: ``ready``, ``waiting``, ``registry``, ``swap_queued``, ``swap``, ``episode``,
            ``evaluated``, ``stopped``.
    """

    def __init__(
        self,
        config: WorkerConfig,
        *,
        policy: DecisionPolicy,
        agent_identity_hash: str,
        emit: EventSink | None = None,
    ) -> None:
        self.config = config
        self.policy = policy
        self.agent_identity_hash = agent_identity_hash
        self.worker_id = config.worker_id or default_worker_id()
        self.spec = task_spec(config.task)
        self.keys = RuntimeKeys(config.namespace)
        self.registry_keys = Keys(config.namespace)
        self._emit_cb = emit
        self._requests: queue.Queue[_Request] = queue.Queue(maxsize=MAX_QUEUED_EVALUATIONS)
        self._requests_lock = threading.Lock()
        self._wake = threading.Event()
        self._resync = threading.Event()
        self._registry_up = True
        self._seen_registry = False
        self._episodes = 0
        self._started_at = time.time()
        self._caps: LoadedCapabilitySet | None = None
        self._stopping = False
        self._cache: ArtifactStore = (
            ArtifactCache(config.cache_dir) if config.cache_dir is not None else MemoryArtifactCache()
        )
        self.phi: Phi = resolve_phi(config.phi, task_spec(config.task))
        self.safety_limits = config.safety_limits if config.safety_limits is not None else SafetyLimits()

    # --- events ---------------------------------------------------------------------------

    def _emit(self, event: str, **fields: Any) -> None:
        if self._emit_cb is None:
            return
        try:
            self._emit_cb({"event": event, "worker_id": self.worker_id, **fields})
        except Exception:  # a broken printer must not stop the worker
            log.exception("event sink failed on %s", event)

    # --- public state -----------------------------------------------------------------------

    def adoption(self) -> Adoption:
        """What this worker runs now."""
        caps = self._caps
        return Adoption(
            worker_id=self.worker_id,
            task=self.spec.name,
            revision=caps.revision if caps is not None else 0,
            versions=caps.versions if caps is not None else {},
            pending=caps.pending() if caps is not None else {},
            episodes=self._episodes,
            registry_connected=self._registry_up,
            pid=os.getpid(),
            started_at=self._started_at,
        )

    # --- Zenoh callbacks (Zenoh threads) ----------------------------------------------------

    def _on_adopted(self, query: zenoh.Query) -> None:
        _reply(query, json.dumps(self.adoption().to_dict()).encode())

    def _on_evaluate(self, query: zenoh.Query) -> None:
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            request = EvaluateRequest.from_json(payload)
            if request.task != self.spec.name:
                raise Invalid(
                    f"runtime worker {self.worker_id} runs task {self.spec.name!r}, not {request.task!r}",
                    details={"field": "task"},
                )
        except CapevoError as exc:
            _reply(query, exc)
            return
        refusal: CapevoError | None = None
        with self._requests_lock:
            if self._stopping:
                refusal = Unavailable(f"runtime worker {self.worker_id} is shutting down")
            else:
                try:
                    self._requests.put_nowait(_Request(query, request))
                except queue.Full:
                    refusal = Unavailable(f"runtime worker {self.worker_id} is busy: {MAX_QUEUED_EVALUATIONS} queued")
        if refusal is not None:
            _reply(query, refusal)
            return
        self._wake.set()

    def _on_registry_event(self, event: AuditEvent, record: EcmVersion) -> None:
        caps = self._caps
        if caps is None or event.name not in caps.names or event.action not in (Action.PROMOTE, Action.ROLLBACK):
            return
        if record.state is not State.ACTIVE:
            return
        if event.name in caps.pinned:
            return
        caps.queue_swap(event.name, record.version, record=record, revision=event.revision)
        self._emit(
            "swap_queued", name=event.name, version=record.version, action=event.action.value, revision=event.revision
        )
        self._wake.set()

    def _on_registry_liveliness(self, sample: zenoh.Sample) -> None:
        up = sample.kind == zenoh.SampleKind.PUT
        was_up, seen = self._registry_up, self._seen_registry
        self._registry_up = up
        self._seen_registry = True
        if up and seen and not was_up:
            # Events committed while we were away are lost; re-read the set.
            self._resync.set()
            self._wake.set()
        if not seen and up:
            return
        if up != was_up:
            log.warning("registry %s", "is back" if up else "went away; running on the last good versions")
            self._emit("registry", connected=up)

    # --- main loop ----------------------------------------------------------------------------

    def run(self, stop: threading.Event | None = None, *, handle_signals: bool = True) -> int:
        """Serve until ``stop`` is set, SIGTERM/SIGINT arrives or the episode count is reached.

        Returns:
            Episodes run.

        Raises:
            Invalid, Corrupt: a capability set that cannot be loaded (bad artifacts, plans that
                do not compose).
        """
        stop = stop if stop is not None else threading.Event()
        with contextlib.ExitStack() as stack:
            stack.enter_context(stop_on_signals(stop, enabled=handle_signals, what="runtime worker"))
            client = self._open_client(stop)
            if client is None:
                return 0
            stack.callback(client.close)
            env = make_task(self.spec.name, perturbations=self.config.perturbations, horizon=self.config.horizon)
            stack.callback(env.close)
            env.reset(seed=self.config.seed)
            shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
            caps = self._load(client, shapes, stop)
            if caps is None:
                return 0
            stack.callback(caps.close)
            self._caps = caps
            evaluator = LocalEvaluator(
                client,
                policy=self.policy,
                phi=self.phi,
                safety_limits=self.safety_limits,
                trace_dir=self.config.trace_dir / "evaluations" if self.config.trace_dir is not None else None,
                trace_compression=self.config.trace_compression,
                perturbations=self.config.perturbations,
                horizon=self.config.horizon,
                step_budget_per_ecm=self.config.step_budget_per_ecm,
                timeout_s=self.config.timeout_s,
                governance=self.config.governance,
                agent_identity_hash=self.agent_identity_hash,
                cache=self._cache,
                recovery=self.config.recovery,
                worker_id=self.worker_id,
                env=env,
                should_stop=stop.is_set,
            )
            session = self._open_session(stack)
            subscription = client.subscribe_events("*", self._on_registry_event)
            stack.callback(subscription.close)
            liveliness = session.liveliness().declare_subscriber(
                self.registry_keys.alive(), self._on_registry_liveliness, history=True
            )
            stack.callback(liveliness.undeclare)
            # Events that landed between loading and subscribing are caught by one re-read.
            self._resync.set()
            self._emit(
                "ready",
                task=self.spec.name,
                namespace=self.config.namespace,
                revision=caps.revision,
                versions=caps.versions,
                pid=os.getpid(),
                keys={
                    "alive": self.keys.alive(self.worker_id),
                    "adopted": self.keys.adopted(self.worker_id),
                    "evaluate": self.keys.evaluate(self.worker_id),
                    "evaluate_task": self.keys.evaluate_task(self.spec.name),
                },
            )
            self._loop(env, caps, self.policy, self.agent_identity_hash, evaluator, stop)
        self._emit("stopped", episodes=self._episodes)
        return self._episodes

    def _open_client(self, stop: threading.Event) -> Any:
        from capevo.registry.client import Client

        announced = False
        while not stop.is_set():
            try:
                return Client(
                    self.config.connect,
                    namespace=self.config.namespace,
                    user=self.config.user,
                    password=self.config.password,
                    timeout=self.config.registry_timeout,
                    actor=f"runtime:{self.worker_id}",
                )
            except Unavailable as exc:
                if not announced:
                    self._emit("waiting", reason=str(exc))
                    announced = True
                stop.wait(self.config.retry_interval_s)
        return None

    def _load(self, client: Any, shapes: Mapping[str, Sequence[int]], stop: threading.Event) -> Any:
        announced = False
        while not stop.is_set():
            try:
                return LoadedCapabilitySet(
                    client,
                    self.spec.name,
                    cache=self._cache,
                    recovery=self.config.recovery,
                    observation_shapes=shapes,
                )
            except (Unavailable, Timeout, NotFound) as exc:
                if not announced:
                    self._emit("waiting", reason=str(exc))
                    announced = True
                log.warning("cannot load the capability set yet: %s", exc)
                stop.wait(self.config.retry_interval_s)
        return None

    def _open_session(self, stack: contextlib.ExitStack) -> zenoh.Session:
        try:
            session = zenoh.open(zenoh_client_config(self.config.connect, self.config.user, self.config.password))
        except zenoh.ZError as exc:
            raise Unavailable(f"cannot open the worker's Zenoh session: {first_line(exc)}") from None
        stack.callback(session.close)
        for key, handler, complete in (
            (self.keys.adopted(self.worker_id), self._on_adopted, False),
            (self.keys.evaluate(self.worker_id), self._on_evaluate, False),
            # complete=True: a query on the shared key goes to one worker of the task, not all.
            (self.keys.evaluate_task(self.spec.name), self._on_evaluate, True),
        ):
            queryable = session.declare_queryable(key, handler, complete=complete)
            stack.callback(queryable.undeclare)
        for key in (self.keys.alive(self.worker_id), self.keys.serves(self.worker_id, self.spec.name)):
            token = session.liveliness().declare_token(key)
            # Undeclared before the queryables (the stack unwinds in reverse): alive implies served.
            stack.callback(token.undeclare)
        # Runs first on the way out, while the session can still carry the error replies.
        stack.callback(self._drain, f"runtime worker {self.worker_id} is shutting down")
        return session

    def _loop(
        self,
        env: TaskEnv,
        caps: LoadedCapabilitySet,
        policy: Any,
        identity_hash: str,
        evaluator: LocalEvaluator,
        stop: threading.Event,
    ) -> None:
        governor = make_governor(env, self.phi, enforce=self.config.governance)
        writer: TraceWriter | None = None
        files = 0
        try:
            while not stop.is_set():
                self._serve_requests(evaluator, stop)
                if self._resync.is_set() and self._registry_up:
                    try:
                        queued = caps.refresh()
                        self._resync.clear()
                        if queued:
                            self._emit("swap_queued", versions=queued, action="resync", revision=caps.revision)
                    except (Unavailable, Timeout) as exc:
                        log.info("re-reading the capability set failed: %s", exc)
                if self.config.idle:
                    self._wake.wait(0.2)
                    self._wake.clear()
                    continue
                if self.config.episodes is not None and self._episodes >= self.config.episodes:
                    break
                swaps = caps.begin_episode()
                for s in swaps:
                    self._emit("swap", revision=caps.revision, **s.to_dict())
                if self.config.trace_dir is not None and (writer is None or any(s.applied for s in swaps)):
                    if writer is not None:
                        writer.close()
                    files += 1
                    writer = self._open_trace(caps, identity_hash, files)
                seed = self.config.seed + self._episodes
                run = run_episode_detailed(
                    env,
                    caps,
                    policy,
                    governor,
                    writer,
                    seed=seed,
                    episode=self._episodes,
                    step_budget_per_ecm=self.config.step_budget_per_ecm,
                    timeout_s=self.config.timeout_s,
                    trace_path=str(writer.path) if writer is not None else None,
                    should_stop=stop.is_set,
                    apply_swaps=False,
                    safety_limits=self.safety_limits,
                )
                self._episodes += 1
                o = run.outcome
                self._emit(
                    "episode",
                    episode=self._episodes - 1,
                    seed=seed,
                    success=o.success,
                    steps=o.steps,
                    reward=o.reward,
                    interventions=o.interventions,
                    unsafe_steps=o.unsafe_steps,
                    ecm_failures=o.ecm_failures,
                    versions=dict(o.capability_set),
                    revision=caps.revision,
                    end_reason=run.end_reason,
                    duration_s=o.duration_s,
                    registry_connected=self._registry_up,
                    trace_path=o.trace_path,
                )
        finally:
            if writer is not None:
                writer.close()

    def _open_trace(self, caps: LoadedCapabilitySet, identity_hash: str, index: int) -> TraceWriter:
        assert self.config.trace_dir is not None
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(self._started_at))
        run_id = f"{self.worker_id}-{stamp}-{index:04d}"
        metadata = TraceMetadata.collect(
            run_id=run_id,
            task=self.spec.name,
            capability_set=caps.capability_set,
            phi_hash=self.phi.hash,
            agent_identity_hash=identity_hash,
            seeds=(self.config.seed + self._episodes,),
            worker_id=self.worker_id,
        )
        return TraceWriter(
            self.config.trace_dir / f"{run_id}.mcap",
            metadata,
            compression=self.config.trace_compression,
        )

    def _serve_requests(self, evaluator: LocalEvaluator, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                item = self._requests.get_nowait()
            except queue.Empty:
                return
            req = item.request
            started = time.monotonic()
            trace: bytes | None = None
            try:
                with _overridden(evaluator, req), _trace_scratch(evaluator, req) as scratch:
                    outcomes = evaluator.evaluate(req.task, req.versions, req.seeds)
                    if req.traces:
                        trace = _trace_bytes(outcomes)
                if scratch:  # the trace lived only to be sent: the outcomes must not name it
                    outcomes = [dataclasses.replace(o, trace_path=None) for o in outcomes]
                result: bytes | CapevoError = encode_outcomes(self.worker_id, outcomes)
                self._emit(
                    "evaluated",
                    task=req.task,
                    versions=dict(req.versions),
                    seeds=len(req.seeds),
                    overrides=sorted(req.overrides),
                    successes=sum(o.success for o in outcomes),
                    duration_s=time.monotonic() - started,
                )
            except CapevoError as exc:
                result = exc
            except Exception as exc:  # an evaluation bug must cost the request, never the worker
                log.exception("evaluate request failed")
                result = CapevoError(f"evaluation failed in runtime worker {self.worker_id}: {type(exc).__name__}")
            _reply(item.query, result, attachment=trace if not isinstance(result, CapevoError) else None)

    def _drain(self, why: str) -> None:
        """Refuse every queued request and every later one (invariant 2)."""
        with self._requests_lock:
            self._stopping = True
            items = []
            while True:
                try:
                    items.append(self._requests.get_nowait())
                except queue.Empty:
                    break
        for item in items:
            _reply(item.query, Unavailable(why))
