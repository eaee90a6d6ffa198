"""Frozen records of the registry: ECM versions, descriptors, audit events, capability sets.

Records are plain values: stores return them, the wire codec turns them into JSON and
back, and nothing mutates them. Every record has ``to_dict()`` (JSON-able) and a
``from_dict()`` classmethod that is its exact inverse.

Invariants:
1. ``X.from_dict(x.to_dict()) == x`` for every record ``x``.
2. ``to_dict()`` output contains only JSON types (dict, list, str, int, float, bool, None).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


class Kind(str, enum.Enum):
    """What an ECM artifact is."""

    NEURAL = "neural"
    CODE = "code"
    PROMPT = "prompt"


class Origin(str, enum.Enum):
    """How a version came to be (the paper's creation/update modalities)."""

    MANUAL = "manual"
    LLM = "llm"
    CLONE = "clone"
    RL = "rl"
    IL = "il"
    HYBRID = "hybrid"


class State(str, enum.Enum):
    """Lifecycle state of one version; transitions live in :mod:`capevo.records.lifecycle`."""

    CANDIDATE = "candidate"
    ACTIVE = "active"
    SUPERSEDED = "superseded"
    REJECTED = "rejected"
    DEPRECATED = "deprecated"


class Action(str, enum.Enum):
    """What an audit event records."""

    PUBLISH = "publish"
    GATE = "gate"
    PROMOTE = "promote"
    ROLLBACK = "rollback"
    DEPRECATE = "deprecate"
    REJECT = "reject"


DEFAULT_MEDIA_TYPES: Mapping[Kind, str] = {
    Kind.NEURAL: "application/zip",
    Kind.CODE: "text/x-python",
    Kind.PROMPT: "text/plain",
}


@dataclass(frozen=True, slots=True, kw_only=True)
class IOSpec:
    """One named input or output of an ECM interface."""

    name: str
    shape: tuple[int, ...]
    dtype: str = "float32"
    low: float | None = None
    high: float | None = None
    units: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "shape": list(self.shape),
            "dtype": self.dtype,
            "low": self.low,
            "high": self.high,
            "units": self.units,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IOSpec:
        return cls(
            name=d["name"],
            shape=tuple(int(s) for s in d["shape"]),
            dtype=d.get("dtype", "float32"),
            low=d.get("low"),
            high=d.get("high"),
            units=d.get("units"),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class Interface:
    """Typed inputs I(c) and outputs O(c) of an ECM."""

    inputs: tuple[IOSpec, ...] = ()
    outputs: tuple[IOSpec, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"inputs": [s.to_dict() for s in self.inputs], "outputs": [s.to_dict() for s in self.outputs]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Interface:
        return cls(
            inputs=tuple(IOSpec.from_dict(s) for s in d.get("inputs", ())),
            outputs=tuple(IOSpec.from_dict(s) for s in d.get("outputs", ())),
        )


COMPARISON_OPS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")


@dataclass(frozen=True, slots=True, kw_only=True)
class Condition:
    """``signal op value``, where ``signal`` names a scalar the task exposes each step."""

    signal: str
    op: str
    value: float

    def to_dict(self) -> dict[str, Any]:
        return {"signal": self.signal, "op": self.op, "value": self.value}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Condition:
        return cls(signal=d["signal"], op=d["op"], value=float(d["value"]))


@dataclass(frozen=True, slots=True, kw_only=True)
class Predicate:
    """A state predicate: the conjunction of ``all``; ``text`` is for people and planners."""

    text: str = ""
    all: tuple[Condition, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"text": self.text, "all": [c.to_dict() for c in self.all]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Predicate:
        return cls(text=d.get("text", ""), all=tuple(Condition.from_dict(c) for c in d.get("all", ())))


@dataclass(frozen=True, slots=True, kw_only=True)
class Descriptor:
    """Descriptor φ: what the ECM does, when it applies, when it is done."""

    description: str
    applicability: Predicate = field(default_factory=Predicate)
    termination: Predicate = field(default_factory=Predicate)

    def to_dict(self) -> dict[str, Any]:
        return {
            "description": self.description,
            "applicability": self.applicability.to_dict(),
            "termination": self.termination.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Descriptor:
        return cls(
            description=d["description"],
            applicability=Predicate.from_dict(d.get("applicability") or {}),
            termination=Predicate.from_dict(d.get("termination") or {}),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class ArtifactRef:
    """Artifact θ as stored: content address, size and media type."""

    sha256: str
    size: int
    media_type: str

    def to_dict(self) -> dict[str, Any]:
        return {"sha256": self.sha256, "size": self.size, "media_type": self.media_type}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ArtifactRef:
        return cls(sha256=d["sha256"], size=int(d["size"]), media_type=d["media_type"])


@dataclass(frozen=True, slots=True, kw_only=True)
class Provenance:
    """Where a learned version came from."""

    learner_id: str | None = None
    config_hash: str | None = None
    traces: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"learner_id": self.learner_id, "config_hash": self.config_hash, "traces": list(self.traces)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> Provenance:
        d = d or {}
        return cls(learner_id=d.get("learner_id"), config_hash=d.get("config_hash"), traces=tuple(d.get("traces", ())))


@dataclass(frozen=True, slots=True, kw_only=True)
class PublishSpec:
    """Everything a publisher supplies besides the artifact bytes (the descriptor YAML)."""

    kind: Kind
    descriptor: Descriptor
    interface: Interface = field(default_factory=Interface)
    media_type: str | None = None
    parent: int | None = None
    origin: Origin = Origin.MANUAL
    provenance: Provenance = field(default_factory=Provenance)

    @property
    def resolved_media_type(self) -> str:
        return self.media_type or DEFAULT_MEDIA_TYPES[self.kind]

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind.value,
            "descriptor": self.descriptor.to_dict(),
            "interface": self.interface.to_dict(),
            "media_type": self.media_type,
            "parent": self.parent,
            "origin": self.origin.value,
            "provenance": self.provenance.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PublishSpec:
        return cls(
            kind=Kind(d["kind"]),
            descriptor=Descriptor.from_dict(d["descriptor"]),
            interface=Interface.from_dict(d.get("interface") or {}),
            media_type=d.get("media_type"),
            parent=d.get("parent"),
            origin=Origin(d.get("origin", Origin.MANUAL.value)),
            provenance=Provenance.from_dict(d.get("provenance")),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class EcmVersion:
    """One immutable version k of an ECM, plus its mutable-by-store lifecycle fields."""

    name: str
    version: int
    kind: Kind
    state: State
    artifact: ArtifactRef
    descriptor: Descriptor
    interface: Interface
    parent: int | None
    origin: Origin
    provenance: Provenance
    gate_evidence: Mapping[str, Any] | None
    created_at: float
    created_by: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "version": self.version,
            "kind": self.kind.value,
            "state": self.state.value,
            "artifact": self.artifact.to_dict(),
            "descriptor": self.descriptor.to_dict(),
            "interface": self.interface.to_dict(),
            "parent": self.parent,
            "origin": self.origin.value,
            "provenance": self.provenance.to_dict(),
            "gate_evidence": dict(self.gate_evidence) if self.gate_evidence is not None else None,
            "created_at": self.created_at,
            "created_by": self.created_by,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EcmVersion:
        return cls(
            name=d["name"],
            version=int(d["version"]),
            kind=Kind(d["kind"]),
            state=State(d["state"]),
            artifact=ArtifactRef.from_dict(d["artifact"]),
            descriptor=Descriptor.from_dict(d["descriptor"]),
            interface=Interface.from_dict(d["interface"]),
            parent=d.get("parent"),
            origin=Origin(d["origin"]),
            provenance=Provenance.from_dict(d.get("provenance")),
            gate_evidence=d.get("gate_evidence"),
            created_at=float(d["created_at"]),
            created_by=d["created_by"],
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class EcmSummary:
    """One row of ``capevo ecm list``."""

    name: str
    active_version: int | None
    latest_version: int
    n_versions: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "active_version": self.active_version,
            "latest_version": self.latest_version,
            "n_versions": self.n_versions,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EcmSummary:
        return cls(
            name=d["name"],
            active_version=d.get("active_version"),
            latest_version=int(d["latest_version"]),
            n_versions=int(d["n_versions"]),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class EcmDetail:
    """One ECM with all its versions, oldest first."""

    name: str
    active_version: int | None
    versions: tuple[EcmVersion, ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "active_version": self.active_version,
            "versions": [v.to_dict() for v in self.versions],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EcmDetail:
        return cls(
            name=d["name"],
            active_version=d.get("active_version"),
            versions=tuple(EcmVersion.from_dict(v) for v in d["versions"]),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class AuditEvent:
    """One link of the append-only, hash-chained audit history.

    ``hash`` is sha256 over ``prev_hash`` and the canonical JSON of every other field
    (see :func:`capevo.records.audit.event_hash`).
    """

    seq: int
    name: str
    action: Action
    version: int | None
    from_state: State | None
    to_state: State | None
    from_version: int | None
    to_version: int | None
    actor: str
    reason: str
    at: float
    data: Mapping[str, Any]
    revision: int | None
    prev_hash: str
    hash: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "seq": self.seq,
            "name": self.name,
            "action": self.action.value,
            "version": self.version,
            "from_state": self.from_state.value if self.from_state else None,
            "to_state": self.to_state.value if self.to_state else None,
            "from_version": self.from_version,
            "to_version": self.to_version,
            "actor": self.actor,
            "reason": self.reason,
            "at": self.at,
            "data": dict(self.data),
            "revision": self.revision,
            "prev_hash": self.prev_hash,
            "hash": self.hash,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> AuditEvent:
        return cls(
            seq=int(d["seq"]),
            name=d["name"],
            action=Action(d["action"]),
            version=d.get("version"),
            from_state=State(d["from_state"]) if d.get("from_state") else None,
            to_state=State(d["to_state"]) if d.get("to_state") else None,
            from_version=d.get("from_version"),
            to_version=d.get("to_version"),
            actor=d["actor"],
            reason=d.get("reason", ""),
            at=float(d["at"]),
            data=dict(d.get("data") or {}),
            revision=d.get("revision"),
            prev_hash=d["prev_hash"],
            hash=d["hash"],
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class CapabilitySet:
    """C(t): every ECM's active version at registry ``revision``.

    Revision 0 is the empty set; each move of any active pointer adds one.
    """

    revision: int
    active: Mapping[str, int]

    def to_dict(self) -> dict[str, Any]:
        return {"revision": self.revision, "active": dict(sorted(self.active.items()))}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CapabilitySet:
        return cls(revision=int(d["revision"]), active={str(k): int(v) for k, v in d["active"].items()})


@dataclass(frozen=True, slots=True, kw_only=True)
class VerifyReport:
    """Result of ``capevo registry verify``: empty ``problems`` means all is intact."""

    events_checked: int
    blobs_checked: int
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        return {
            "events_checked": self.events_checked,
            "blobs_checked": self.blobs_checked,
            "problems": list(self.problems),
            "ok": self.ok,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VerifyReport:
        return cls(
            events_checked=int(d["events_checked"]),
            blobs_checked=int(d["blobs_checked"]),
            problems=tuple(d.get("problems", ())),
        )


class Auth(str, enum.Enum):
    """How the registry knows who made a change; kept in the audit event as ``data["auth"]``.

    An event without ``auth`` was made in-process (:class:`~capevo.registry.LocalRegistry`),
    on the word of whoever could open the registry directory.
    """

    USER = "user"
    """``actor`` is the user Zenoh authenticated (usrpwd) on a secured registry."""
    OPEN = "open"
    """``actor`` is the name a client of an open registry claimed; nothing checked it."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Attribution:
    """Who one mutation is recorded against (``actor``, ``created_by``), and how that is known.

    ``on_behalf_of`` is a name an operator gave for the change (a gate, a monitor), kept
    beside the authenticated ``actor`` and never instead of it. Both extras go into the
    audit event's ``data``, so events written before they existed hash and verify unchanged.
    """

    actor: str
    auth: Auth | None = None
    on_behalf_of: str | None = None

    def audit_data(self) -> dict[str, str]:
        """The entries this attribution adds to its audit event's ``data``."""
        out: dict[str, str] = {}
        if self.auth is not None:
            out["auth"] = self.auth.value
        if self.on_behalf_of is not None:
            out["on_behalf_of"] = self.on_behalf_of
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class Mutation:
    """What one committed mutation produced: the record after the change and its audit event."""

    record: EcmVersion
    event: AuditEvent


__all__ = [
    "COMPARISON_OPS",
    "DEFAULT_MEDIA_TYPES",
    "Action",
    "ArtifactRef",
    "Attribution",
    "AuditEvent",
    "Auth",
    "CapabilitySet",
    "Condition",
    "Descriptor",
    "EcmDetail",
    "EcmSummary",
    "EcmVersion",
    "IOSpec",
    "Interface",
    "Kind",
    "Mutation",
    "Origin",
    "Predicate",
    "Provenance",
    "PublishSpec",
    "State",
    "VerifyReport",
]
