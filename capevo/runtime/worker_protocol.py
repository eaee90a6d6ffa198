"""What runtime workers and their clients say to each other over Zenoh: keys, requests, replies.

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
never as paths on a shared disk. The reply is JSON ``{"worker_id", "outcomes":
[EpisodeOutcome.to_dict(), ...]}``, or an error reply carrying :meth:`CapevoError.to_payload`.
With ``"traces": true`` the reply's attachment is the call's MCAP trace file, so the caller can
read the episodes without sharing the worker's disk.

The server side is :mod:`capevo.runtime.worker`, the client side
:mod:`capevo.runtime.remote_evaluator`.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import re
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from capevo.errors import CapevoError, Invalid, TooLarge
from capevo.records import Origin
from capevo.registry.keys import DEFAULT_NAMESPACE, validate_namespace
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.evaluator import check_seeds, check_versions
from capevo.runtime.tasks import task_spec

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


def zenoh_client_config(connect: Sequence[str], user: str | None, password: str | None) -> zenoh.Config:
    from capevo.registry.zconfig import client_config

    return client_config(connect=list(connect), user=user, password=password)


def first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /", 1)[0].splitlines()[0][:300] if text else type(exc).__name__
