"""The runtime worker: a process that runs a task's episodes with the registry's active ECMs.

``capevo runtime serve --connect EP --task T1`` (see :mod:`capevo.cli.runtime`) runs a
:class:`RuntimeWorker`:

* resolves the task's capability set from the registry and fetches each artifact once
  (cached on disk by sha256, see :mod:`capevo.runtime.artifact_cache`);
* subscribes to the registry's events and, on a ``promote`` or ``rollback`` of an ECM it
  runs, hot-swaps that ECM at the next episode boundary (never inside an ECM execution);
* announces itself and what it runs on Zenoh (key space below);
* keeps running episodes on its last good versions while the registry is away; when the
  registry's liveliness token returns it re-reads the capability set and catches up;
* serves evaluation requests (``evaluate(task, versions, seeds)``, optionally with inline
  candidate artifacts in place of some ECMs' registry artifacts) between its own episodes, on
  its own environment; :class:`RemoteEvaluator` is the client side, and splits one call's
  seeds across every live worker of the task (:mod:`capevo.runtime.fanout`);
* shuts down cleanly on SIGTERM/SIGINT (ends the running episode, replies to queued
  requests with ``unavailable``, closes traces and sessions). It never forks.

Key space, under the registry's namespace ``<ns>``::

    <ns>/runtime/<worker_id>/alive      liveliness token while the worker serves
    <ns>/runtime/<worker_id>/serves/<task>
                                        liveliness token: the same, naming its task (task
                                        name); get <ns>/runtime/*/serves/<task> finds the
                                        live workers of a task in one round trip
    <ns>/runtime/<worker_id>/adopted    queryable: JSON Adoption {worker_id, task, revision,
                                        versions, pending, episodes, registry_connected, pid,
                                        started_at}; get <ns>/runtime/*/adopted lists all
    <ns>/runtime/<worker_id>/evaluate   queryable: run an EvaluateRequest on this worker
    <ns>/runtime/evaluate/<task>        queryable (complete): the same, served by any one
                                        worker of <task> (task name, e.g. ``pick``)

An evaluate request's payload is JSON ``{"task", "versions", "seeds"}``, plus optionally
``"overrides": {ecm: base64 artifact}`` and ``"override_origin"``: unpublished candidate
artifacts (a learner's CEM samples) that run in place of the named ECMs' artifacts at the
version ``versions`` (or the registry) names, keeping that version's descriptor and interface.
Candidates reach a worker this way, inline, or as registry versions pinned in ``versions``;
never as paths on a shared disk. Inline code never runs in the worker's process: an override
whose origin the trust policy would run in-process is refused (:class:`Forbidden`). The reply
is JSON ``{"worker_id", "outcomes": [EpisodeOutcome.to_dict(), ...]}``, or an error reply
carrying :meth:`CapevoError.to_payload`. With ``"traces": true`` the reply's attachment is the
call's MCAP trace file (written to a temporary directory and removed when the worker keeps no
traces of its own; the outcomes' ``trace_path`` is then None), so the caller can read the
episodes without sharing the worker's disk.

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
7. :meth:`RemoteEvaluator.evaluate` returns one outcome per seed, in seed order, each from
   exactly one episode, whichever workers ran them and however many died on the way (see
   :mod:`capevo.runtime.fanout` for the split and the retry rules).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import queue
import re
import socket
import tempfile
import threading
import time
import uuid
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
    TooLarge,
    Unavailable,
    error_from_payload,
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
from capevo.runtime.evaluator import LocalEvaluator, check_seeds, check_versions
from capevo.runtime.fanout import DEFAULT_MAX_ATTEMPTS, Part, SeedLedger
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
from capevo.shutdown import stop_on_signals

log = logging.getLogger("capevo.runtime.worker")

RUNTIME_SEGMENT = "runtime"
EVALUATE = "evaluate"
WORKER_ID_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")
MAX_EVAL_SEEDS = 1000
MAX_QUEUED_EVALUATIONS = 16
MAX_REQUEST_BYTES = 4 << 20
"""Inline artifacts travel in the request (base64): code skills are a few kB; a large neural
candidate goes through the registry instead (publish it as a candidate, pin its version)."""
DEFAULT_EVALUATE_TIMEOUT_S = 600.0
JSON_ENCODING = "application/json"
SERVES = "serves"
MAX_TRACE_REPLY_BYTES = 256 << 20
"""A call's trace file travels back with its outcomes up to this size (lz4 MCAP)."""
DISCOVERY_TIMEOUT_S = 5.0
"""At most this long to list the live workers of a task (the router answers from its table)."""


def validate_worker_id(worker_id: object) -> str:
    """Return ``worker_id`` if it is a usable key chunk (1-64 of ``[A-Za-z0-9_.-]``, not ``evaluate``).

    Raises:
        Invalid: anything else.
    """
    if not isinstance(worker_id, str) or not WORKER_ID_PATTERN.fullmatch(worker_id) or worker_id == EVALUATE:
        raise Invalid(
            f"worker id {worker_id!r} must be 1-64 letters, digits, '_', '.' or '-' (and not {EVALUATE!r})",
            details={"field": "worker_id"},
        )
    return worker_id


def default_worker_id() -> str:
    """``<host>-<pid>``, reduced to the characters a key chunk allows."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:40] or "host"
    return f"{host}-{os.getpid()}"


@dataclass(frozen=True, slots=True)
class RuntimeKeys:
    """The runtime workers' keys under a namespace (see the module docstring)."""

    namespace: str = DEFAULT_NAMESPACE

    def __post_init__(self) -> None:
        validate_namespace(self.namespace)

    @property
    def root(self) -> str:
        return f"{self.namespace}/{RUNTIME_SEGMENT}"

    def alive(self, worker_id: str) -> str:
        return f"{self.root}/{validate_worker_id(worker_id)}/alive"

    def alive_all(self) -> str:
        return f"{self.root}/*/alive"

    def serves(self, worker_id: str, task: str) -> str:
        return f"{self.root}/{validate_worker_id(worker_id)}/{SERVES}/{task_spec(task).name}"

    def serves_task(self, task: str) -> str:
        return f"{self.root}/*/{SERVES}/{task_spec(task).name}"

    def adopted(self, worker_id: str) -> str:
        return f"{self.root}/{validate_worker_id(worker_id)}/adopted"

    def adopted_all(self) -> str:
        return f"{self.root}/*/adopted"

    def evaluate(self, worker_id: str) -> str:
        return f"{self.root}/{validate_worker_id(worker_id)}/{EVALUATE}"

    def evaluate_task(self, task: str) -> str:
        return f"{self.root}/{EVALUATE}/{task_spec(task).name}"

    def worker_of(self, key: str) -> str | None:
        """The worker id in a ``<ns>/runtime/<id>/...`` key, or None."""
        prefix = self.root + "/"
        if not key.startswith(prefix):
            return None
        part = key[len(prefix) :].split("/", 1)[0]
        return part if part and part != EVALUATE else None


@dataclass(frozen=True, slots=True, kw_only=True)
class Adoption:
    """What a worker runs now: the reply of ``<ns>/runtime/<worker_id>/adopted``."""

    worker_id: str
    task: str
    revision: int
    versions: Mapping[str, int]
    pending: Mapping[str, int] = field(default_factory=dict)
    episodes: int = 0
    registry_connected: bool = True
    pid: int = 0
    started_at: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "worker_id": self.worker_id,
            "task": self.task,
            "revision": self.revision,
            "versions": dict(sorted(self.versions.items())),
            "pending": dict(sorted(self.pending.items())),
            "episodes": self.episodes,
            "registry_connected": self.registry_connected,
            "pid": self.pid,
            "started_at": self.started_at,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Adoption:
        """Inverse of :meth:`to_dict`.

        Raises:
            Invalid: a missing or mistyped field.
        """
        try:
            return cls(
                worker_id=str(d["worker_id"]),
                task=str(d["task"]),
                revision=int(d["revision"]),
                versions={str(k): int(v) for k, v in d["versions"].items()},
                pending={str(k): int(v) for k, v in (d.get("pending") or {}).items()},
                episodes=int(d.get("episodes", 0)),
                registry_connected=bool(d.get("registry_connected", True)),
                pid=int(d.get("pid", 0)),
                started_at=float(d.get("started_at", 0.0)),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise Invalid(f"malformed adoption record: {type(exc).__name__}: {exc}") from None


def check_overrides(overrides: Mapping[str, bytes] | None, task: str) -> dict[str, bytes]:
    """``overrides`` as ``{ecm: bytes}`` for ECMs of ``task``'s plan.

    Raises:
        Invalid: not a mapping of plan ECM names to non-empty bytes; unknown task.
    """
    if overrides is None:
        return {}
    if not isinstance(overrides, Mapping):
        raise Invalid(f"overrides must be a mapping, got {type(overrides).__name__}", details={"field": "overrides"})
    spec = task_spec(task)
    out: dict[str, bytes] = {}
    for name, data in overrides.items():
        if not isinstance(name, str) or name not in spec.ecm_names:
            raise Invalid(
                f"override {name!r} is not an ECM of task {spec.name!r} ({', '.join(spec.ecm_names)})",
                details={"field": "overrides"},
            )
        if not isinstance(data, (bytes, bytearray)) or not data:
            raise Invalid(f"override {name!r} must be non-empty bytes", details={"field": "overrides"})
        out[name] = bytes(data)
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class EvaluateRequest:
    """The payload of an evaluate query.

    ``overrides`` (inline artifacts, base64 on the wire) run in place of the named ECMs'
    registry artifacts; ``override_origin`` is the origin they run under (default the
    overridden version's), which decides where code runs (see the module docstring).
    """

    task: str
    versions: Mapping[str, int]
    seeds: tuple[int, ...]
    overrides: Mapping[str, bytes] = field(default_factory=dict)
    override_origin: Origin | None = None
    traces: bool = False
    """Send the call's trace file back with the outcomes (the reply's attachment)."""

    def to_json(self) -> bytes:
        body: dict[str, Any] = {"task": self.task, "versions": dict(self.versions), "seeds": list(self.seeds)}
        if self.traces:
            body["traces"] = True
        if self.overrides:
            body["overrides"] = {k: base64.b64encode(v).decode("ascii") for k, v in sorted(self.overrides.items())}
        if self.override_origin is not None:
            body["override_origin"] = self.override_origin.value
        return json.dumps(body, separators=(",", ":")).encode()

    @classmethod
    def from_json(cls, payload: bytes, *, max_seeds: int = MAX_EVAL_SEEDS) -> EvaluateRequest:
        """Parse and check a request.

        Raises:
            TooLarge: the payload or the seed list is over the limit.
            Invalid: not JSON, a missing or mistyped field, an unknown task, an override of an
                ECM outside the task's plan, an unknown origin.
        """
        if len(payload) > MAX_REQUEST_BYTES:
            raise TooLarge(f"evaluate request is {len(payload)} bytes; the limit is {MAX_REQUEST_BYTES}")
        try:
            body = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            raise Invalid(f"evaluate request is not JSON: {exc}", details={"field": "payload"}) from None
        if not isinstance(body, dict):
            raise Invalid("evaluate request must be a JSON object", details={"field": "payload"})
        unknown = sorted(set(body) - {"task", "versions", "seeds", "overrides", "override_origin", "traces"})
        if unknown:
            raise Invalid(f"evaluate request: unknown field(s) {', '.join(unknown)}", details={"field": unknown[0]})
        task = body.get("task")
        if not isinstance(task, str):
            raise Invalid("evaluate request: task must be a string", details={"field": "task"})
        spec = task_spec(task)
        seeds = body.get("seeds")
        if not isinstance(seeds, list):
            raise Invalid("evaluate request: seeds must be a list of integers", details={"field": "seeds"})
        if len(seeds) > max_seeds:
            raise TooLarge(f"evaluate request has {len(seeds)} seeds; a worker runs at most {max_seeds} per request")
        raw = body.get("overrides") or {}
        if not isinstance(raw, dict) or not all(isinstance(v, str) for v in raw.values()):
            raise Invalid(
                "evaluate request: overrides must map ECM names to base64 text", details={"field": "overrides"}
            )
        try:
            decoded = {k: base64.b64decode(v, validate=True) for k, v in raw.items()}
        except (binascii.Error, ValueError):
            raise Invalid("evaluate request: an override is not base64", details={"field": "overrides"}) from None
        traces = body.get("traces", False)
        if not isinstance(traces, bool):
            raise Invalid("evaluate request: traces must be true or false", details={"field": "traces"})
        origin = body.get("override_origin")
        if origin is not None:
            try:
                origin = Origin(origin)
            except (ValueError, TypeError):
                valid = ", ".join(o.value for o in Origin)
                raise Invalid(
                    f"evaluate request: unknown override_origin {origin!r}; valid: {valid}",
                    details={"field": "override_origin"},
                ) from None
        return cls(
            task=spec.name,
            versions=check_versions(body.get("versions") or {}),
            seeds=tuple(check_seeds(seeds)),
            overrides=check_overrides(decoded, spec.name),
            override_origin=origin,
            traces=traces,
        )


def encode_outcomes(worker_id: str, outcomes: Sequence[EpisodeOutcome]) -> bytes:
    return json.dumps({"worker_id": worker_id, "outcomes": [o.to_dict() for o in outcomes]}).encode()


def decode_outcomes(payload: bytes) -> tuple[str, list[EpisodeOutcome]]:
    """Inverse of :func:`encode_outcomes`.

    Raises:
        CapevoError: a malformed reply.
    """
    try:
        body = json.loads(payload)
        return str(body.get("worker_id", "")), [EpisodeOutcome.from_dict(o) for o in body["outcomes"]]
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CapevoError(f"malformed evaluate reply from a runtime worker: {type(exc).__name__}: {exc}") from None


def _zenoh_config(connect: Sequence[str], user: str | None, password: str | None) -> zenoh.Config:
    from capevo.registry.zconfig import client_config

    return client_config(connect=list(connect), user=user, password=password)


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /", 1)[0].splitlines()[0][:300] if text else type(exc).__name__


# ---------------------------------------------------------------------------------------
# Worker
# ---------------------------------------------------------------------------------------


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
            session = zenoh.open(_zenoh_config(self.config.connect, self.config.user, self.config.password))
        except zenoh.ZError as exc:
            raise Unavailable(f"cannot open the worker's Zenoh session: {_first_line(exc)}") from None
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


# ---------------------------------------------------------------------------------------
# Clients of workers
# ---------------------------------------------------------------------------------------


class _SessionOwner:
    """A Zenoh session given by the caller, or opened (and later closed) here."""

    def __init__(
        self,
        *,
        session: zenoh.Session | None,
        connect: Sequence[str] | str | None,
        user: str | None,
        password: str | None,
    ) -> None:
        from capevo.registry.zconfig import split_endpoints

        if (session is None) == (not split_endpoints(connect)):
            raise Invalid("give exactly one of session or connect", details={"field": "connect"})
        self._own = session is None
        if session is None:
            endpoints = split_endpoints(connect)
            try:
                session = zenoh.open(_zenoh_config(endpoints, user, password))
            except zenoh.ZError as exc:
                raise Unavailable(
                    f"cannot reach {', '.join(endpoints)}: {_first_line(exc)}", details={"connect": list(endpoints)}
                ) from None
        self.session: zenoh.Session = session
        self._closed = False

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._own:
            with contextlib.suppress(zenoh.ZError):
                self.session.close()


class RemoteEvaluator:
    """:class:`capevo.runtime.evaluation.Evaluator` served by runtime workers over Zenoh.

    One call's seeds are split across every live worker of the task (found by their
    ``<ns>/runtime/*/serves/<task>`` liveliness tokens) and run concurrently, one query per
    worker; the outcomes are merged back in seed order (:mod:`capevo.runtime.fanout`). A worker
    that dies mid-call (its liveliness token goes, or its query ends without outcomes) or
    refuses with ``unavailable`` (shutting down, queue full) has its unfinished seeds re-split
    across the workers still alive, re-listing them first if none is left; every seed is
    counted once (invariant 7). Any other error from a worker (``invalid``, ``not_found``, an
    evaluation failure) ends the call with that error, as a local evaluation would.

    It also implements :class:`capevo.learner.base.CandidateEvaluator`: ``overrides`` travel
    inline in the request, so a learner's unpublished candidates run on the workers too.

    Args:
        connect: Endpoint(s) of the registry router (or any router the workers reach); or
        session: an open Zenoh session to use (not closed here).
        namespace: The registry's namespace.
        user, password: Zenoh credentials when ``connect`` is given.
        worker_id: Ask only this worker (no split); default every live worker of the task.
        timeout: Seconds to wait for all the outcomes of one call.
        max_attempts: Dispatches of one seed before the call gives up with ``unavailable``.
        trace_dir: When given, each worker sends its part's trace file back with the outcomes
            and it is written here (``<worker_id>-<file name>``); the outcomes' ``trace_path``
            names these local copies, so learners read a remote worker's episodes without a
            shared disk. None leaves each ``trace_path`` as the worker's own (None when the
            worker keeps no traces).

    Raises:
        Invalid: neither or both of ``connect``/``session``; bad namespace, worker id, timeout or
            max_attempts.
        Unavailable: the session cannot open.
    """

    def __init__(
        self,
        connect: Sequence[str] | str | None = None,
        *,
        session: zenoh.Session | None = None,
        namespace: str = DEFAULT_NAMESPACE,
        user: str | None = None,
        password: str | None = None,
        worker_id: str | None = None,
        timeout: float = DEFAULT_EVALUATE_TIMEOUT_S,
        max_attempts: int = DEFAULT_MAX_ATTEMPTS,
        trace_dir: str | os.PathLike[str] | None = None,
    ) -> None:
        self.keys = RuntimeKeys(namespace)
        self.trace_dir = Path(trace_dir) if trace_dir is not None else None
        self.worker_id = validate_worker_id(worker_id) if worker_id is not None else None
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
            raise Invalid(
                f"timeout must be a positive number of seconds, got {timeout!r}", details={"field": "timeout"}
            )
        self.timeout = float(timeout)
        SeedLedger((), max_attempts=max_attempts)  # checks max_attempts
        self.max_attempts = max_attempts
        self.last_call: dict[str, Any] = {}
        """How the last call went: ``parts``, ``failed_parts``, ``dropped``, ``workers``."""
        self._owner = _SessionOwner(session=session, connect=connect, user=user, password=password)
        self._listeners: set[queue.Queue[tuple[str, Any, Any]]] = set()
        self._listeners_lock = threading.Lock()
        try:
            # One subscriber for the evaluator's life: a call learns of a death while it waits.
            self._liveliness: Any = self._owner.session.liveliness().declare_subscriber(
                self.keys.alive_all(), zenoh.handlers.Callback(self._on_liveliness)
            )
        except zenoh.ZError as exc:
            self._owner.close()
            raise Unavailable(f"cannot watch the runtime workers: {_first_line(exc)}") from None

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        worker = self.keys.worker_of(str(sample.key_expr))
        if worker is None:
            return
        with self._listeners_lock:
            for q in self._listeners:
                q.put(("gone", worker, None))

    def live_workers(self, task: str, timeout: float = DISCOVERY_TIMEOUT_S) -> list[str]:
        """The ids of the workers whose ``serves/<task>`` token is alive, sorted.

        Raises:
            Invalid: unknown task. Unavailable: the liveliness query failed.
        """
        if self.worker_id is not None:
            return [self.worker_id]
        key = self.keys.serves_task(task)
        found = set()
        try:
            for reply in self._owner.session.liveliness().get(key, timeout=max(timeout, 0.1)):
                if reply.ok is not None:
                    worker = self.keys.worker_of(str(reply.ok.key_expr))
                    if worker is not None:
                        found.add(worker)
        except zenoh.ZError as exc:
            raise Unavailable(f"{key}: listing runtime workers failed: {_first_line(exc)}") from None
        return sorted(found)

    def evaluate(
        self,
        task: str,
        versions: Mapping[str, int],
        seeds: Sequence[int],
        *,
        overrides: Mapping[str, bytes] | None = None,
        override_origin: Origin | None = None,
    ) -> list[EpisodeOutcome]:
        """Run the episodes on the task's live workers; one outcome per seed, in seed order.

        Args:
            task, versions, seeds: As :meth:`capevo.runtime.evaluation.Evaluator.evaluate`.
            overrides: ECM name to artifact bytes run in place of that ECM's artifact (sent
                inline; see the module docstring).
            override_origin: The origin the overrides run under (default the overridden
                version's); inline code must run in the sandbox.

        Raises:
            Invalid: bad arguments (checked here first) or refused by a worker.
            Forbidden: an override the worker would run in its own process.
            Unavailable: no worker serves the task, or every worker that could run some seed
                died or refused.
            Timeout: not every outcome within ``timeout``.
            CapevoError: whatever a worker's evaluation raised (same class and code).
        """
        spec = task_spec(task)
        if override_origin is not None and not isinstance(override_origin, Origin):
            raise Invalid(f"override_origin must be an Origin, got {override_origin!r}", details={"field": "origin"})
        request = EvaluateRequest(
            task=spec.name,
            versions=check_versions(versions),
            seeds=tuple(check_seeds(seeds)),
            overrides=check_overrides(overrides, spec.name),
            override_origin=override_origin,
            traces=self.trace_dir is not None,
        )
        deadline = time.monotonic() + self.timeout
        ledger = SeedLedger(request.seeds, max_attempts=self.max_attempts)
        events: queue.Queue[tuple[str, Any, Any]] = queue.Queue()
        tokens: dict[int, zenoh.CancellationToken] = {}
        out: set[str] = set()  # workers this call no longer sends to: dead or refusing
        used: set[str] = set()
        refusals: list[Unavailable] = []
        with self._listeners_lock:
            self._listeners.add(events)
        try:
            live = set(self.live_workers(spec.name, min(DISCOVERY_TIMEOUT_S, self.timeout)))
            while not ledger.done:
                if ledger.pool:
                    candidates = live - out
                    if not candidates:  # every worker we knew is gone: one may have joined since
                        live |= set(self.live_workers(spec.name, min(DISCOVERY_TIMEOUT_S, _left(deadline))))
                        candidates = live - out
                    if not candidates:
                        raise self._no_worker(spec.name, ledger, tried=sorted(used), refusals=refusals)
                    for part in ledger.dispatch(candidates):
                        used.add(part.worker_id)
                        tokens[part.part_id] = self._send(part, request, events, deadline)
                try:
                    kind, subject, body = events.get(timeout=_left(deadline))
                except queue.Empty:
                    raise Timeout(
                        f"{self.keys.serves_task(spec.name)}: not every outcome within {self.timeout:g}s",
                        details={"key": self.keys.serves_task(spec.name), "pending": len(ledger.in_flight())},
                    ) from None
                if kind == "gone":
                    out.add(subject)
                    for part in ledger.in_flight(subject):
                        self._lose(ledger, part, tokens, "its liveliness token went away")
                    continue
                part = next((p for p in ledger.in_flight() if p.part_id == subject), None)
                if kind == "ok":
                    payload, attachment = body
                    worker, outcomes = decode_outcomes(payload)
                    local = self._keep_trace(worker, outcomes, attachment)
                    if local is not None:
                        outcomes = [dataclasses.replace(o, trace_path=str(local)) for o in outcomes]
                    if ledger.complete(subject, outcomes) == 0 and local is not None:
                        local.unlink(missing_ok=True)  # every episode in it was counted from another part
                elif kind == "err":
                    if part is None:  # a part given up already; its late error changes nothing
                        continue
                    err = _reply_error(body, self.keys.evaluate(part.worker_id), self.timeout)
                    if not isinstance(err, Unavailable):
                        raise err
                    out.add(part.worker_id)
                    refusals.append(err)
                    self._lose(ledger, part, tokens, err.message)
                elif kind == "end" and part is not None:
                    # The query ended without a reply: its worker vanished with it.
                    out.add(part.worker_id)
                    self._lose(ledger, part, tokens, "its query ended without outcomes")
            return ledger.merged()
        finally:
            with self._listeners_lock:
                self._listeners.discard(events)
            for token in tokens.values():
                token.cancel()
            self.last_call = {
                "parts": len(tokens),
                "failed_parts": ledger.failed_parts,
                "dropped": ledger.dropped,
                "workers": sorted(used),
            }

    def _send(
        self, part: Part, request: EvaluateRequest, events: queue.Queue[tuple[str, Any, Any]], deadline: float
    ) -> zenoh.CancellationToken:
        """Query ``part``'s worker; its reply and its end land on ``events`` as ``(kind, part_id, body)``."""
        key = self.keys.evaluate(part.worker_id)
        payload = dataclasses.replace(request, seeds=part.seeds).to_json()
        token = zenoh.CancellationToken()
        pid = part.part_id

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                extra = reply.ok.attachment
                trace = extra.to_bytes() if extra is not None else None
                events.put(("ok", pid, (reply.ok.payload.to_bytes(), trace)))
            else:
                events.put(("err", pid, reply.err.payload.to_bytes() if reply.err is not None else b""))

        def on_end() -> None:
            events.put(("end", pid, None))

        try:
            self._owner.session.get(
                key,
                zenoh.handlers.Callback(on_reply, on_end),
                payload=payload,
                # a little past the call's deadline: the call's own Timeout is the one raised
                timeout=_left(deadline) + 1.0,
                target=zenoh.QueryTarget.BEST_MATCHING,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.BLOCK,
                cancellation_token=token,
            )
        except zenoh.ZError as exc:
            raise Unavailable(f"{key}: query failed: {_first_line(exc)}", details={"key": key}) from None
        log.debug("sent seeds %s to %s (part %d)", list(part.seeds), part.worker_id, pid)
        return token

    def _keep_trace(self, worker: str, outcomes: Sequence[EpisodeOutcome], trace: bytes | None) -> Path | None:
        """Write a part's trace file under :attr:`trace_dir`; its path, or None when there is none."""
        if self.trace_dir is None or not trace:
            return None
        remote = next((o.trace_path for o in outcomes if o.trace_path), None)
        name = Path(remote).name if remote else f"eval-{uuid.uuid4().hex[:12]}.mcap"
        path = self.trace_dir / f"{worker}-{name}"
        self.trace_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
        tmp.write_bytes(trace)
        os.replace(tmp, path)  # a reader never sees half a file
        return path

    @staticmethod
    def _lose(ledger: SeedLedger, part: Part, tokens: Mapping[int, zenoh.CancellationToken], why: str) -> None:
        back = ledger.fail(part.part_id)
        token = tokens.get(part.part_id)
        if token is not None:
            token.cancel()
        if back:
            log.warning(
                "runtime worker %s lost seeds %s (%s); re-running them elsewhere",
                part.worker_id,
                [ledger.seeds[i] for i in back],
                why,
            )

    def _no_worker(
        self, task: str, ledger: SeedLedger, *, tried: list[str], refusals: Sequence[Unavailable]
    ) -> Unavailable:
        if refusals and len(tried) == 1:
            return refusals[-1]  # the one worker asked said why (busy, shutting down)
        if self.worker_id is not None:
            key = self.keys.evaluate(self.worker_id)
            return Unavailable(
                f"{key}: runtime worker {self.worker_id!r} did not answer (namespace {self.keys.namespace!r}); "
                "is it running?",
                details={"key": key},
            )
        key = self.keys.serves_task(task)
        if not tried:
            return Unavailable(
                f"{key}: no runtime worker of task {task!r} answered (namespace {self.keys.namespace!r}); "
                "is one running?",
                details={"key": key},
            )
        lost = [ledger.seeds[i] for i in ledger.pool]
        return Unavailable(
            f"{key}: runtime workers {', '.join(tried)} of task {task!r} died or refused with seeds {lost} "
            "unfinished, and no other worker is alive",
            details={"key": key, "seeds": lost},
        )

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._liveliness.undeclare()
        self._owner.close()

    def __enter__(self) -> RemoteEvaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _left(deadline: float) -> float:
    return max(deadline - time.monotonic(), 0.0)


def _reply_error(body: bytes, key: str, timeout: float) -> CapevoError:
    """The error an error reply carries (Zenoh's own query timeout says ``Timeout``)."""
    if body == b"Timeout":
        return Timeout(f"{key}: no outcomes within {timeout:g}s", details={"key": key})
    return error_from_payload(body)


def list_workers(
    connect: Sequence[str] | str | None = None,
    *,
    session: zenoh.Session | None = None,
    namespace: str = DEFAULT_NAMESPACE,
    user: str | None = None,
    password: str | None = None,
    timeout: float = 3.0,
) -> list[Adoption]:
    """Every runtime worker that answers ``<ns>/runtime/*/adopted``, sorted by worker id.

    Raises:
        Invalid: neither or both of ``connect``/``session``. Unavailable: the session cannot open.
    """
    keys = RuntimeKeys(namespace)
    owner = _SessionOwner(session=session, connect=connect, user=user, password=password)
    try:
        found: dict[str, Adoption] = {}
        try:
            replies = owner.session.get(
                keys.adopted_all(),
                timeout=timeout,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    adoption = Adoption.from_dict(json.loads(reply.ok.payload.to_bytes()))
                except (Invalid, ValueError) as exc:
                    log.warning("ignoring a malformed adoption reply on %s: %s", reply.ok.key_expr, exc)
                    continue
                found[adoption.worker_id] = adoption
        except zenoh.ZError as exc:
            raise Unavailable(f"listing runtime workers failed: {_first_line(exc)}") from None
        return [found[k] for k in sorted(found)]
    finally:
        owner.close()


def new_worker_id(prefix: str = "worker") -> str:
    """A fresh random worker id (``<prefix>-<8 hex>``)."""
    return validate_worker_id(f"{prefix}-{uuid.uuid4().hex[:8]}")
