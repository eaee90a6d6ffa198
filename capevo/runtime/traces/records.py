"""Trace records: one frozen record per MCAP topic, each with the JSON Schema that describes it.

A record class owns its topic (``TOPIC``), its schema name (``SCHEMA_NAME``) and its JSON
Schema (``SCHEMA``, draft 2020-12, ``"type": "object"`` at the root as Foxglove requires).
``to_dict`` produces exactly the object the schema describes and ``from_dict`` is its inverse;
nothing else in the package spells a field name, so the schema and the data cannot drift.

Vectors (obs, action, next_obs, key_state, input_state, output, original/result action) are
float32 data: ``from_dict`` rounds every vector to float32, so float32 values come back bit-exact
and a float64 value comes back as the float32 nearest to it. A non-finite float (NaN, +-inf) is
written as JSON ``null`` and read back as NaN, because JSON has no NaN; every float field's schema
is therefore ``number | null``. Scalar floats (reward, durations, total reward) are float64. How
a record is printed is :mod:`capevo.runtime.traces.codec`'s.

Invariants:
1. For every record ``r`` whose floats are finite and whose vectors hold float32 values:
   ``type(r).from_dict(r.to_dict()) == r``.
2. ``r.to_dict()`` validates against ``type(r).SCHEMA``; its keys are exactly the schema's
   ``properties``, and every property is ``required``.
3. Every record class is registered under its own topic exactly once; ``record_type(topic)``
   returns it, and an unknown topic raises :class:`Invalid` listing the known topics.
4. ``TraceMetadata.from_mcap(m.to_mcap()) == m``; every key and value in ``to_mcap()`` is a
   ``str`` (MCAP metadata records are string maps).
5. Env steps and invocations compare and hash by value: a record whose vector is an array
   equals the same record with the tuple of that array's values.
"""

from __future__ import annotations

import enum
import importlib.metadata
import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import numpy as np
import numpy.typing as npt

from capevo.errors import Conflict, Corrupt, Invalid
from capevo.records import CapabilitySet

TRACE_FORMAT = "1"
"""Version of the trace layout (topics, schemas, metadata names); bump on incompatible change."""

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

_NAN = float("nan")

NOT_ENFORCED_PREFIX = "not enforced: "
"""How the episode loop starts the reason of an intervention governance only counted."""


class Outcome(str, enum.Enum):
    """How one ECM invocation ended. Add new values here; the schema's enum follows."""

    OK = "ok"
    TIMEOUT = "timeout"
    EXCEPTION = "exception"
    NAN = "nan"
    BAD_SHAPE = "bad_shape"
    BUDGET_EXHAUSTED = "budget_exhausted"
    SANDBOX_VIOLATION = "sandbox_violation"
    SAFETY_VIOLATION = "safety_violation"
    TERMINATED = "terminated"
    """The ECM's own termination check (``done()``) said it is finished: no action, no failure."""


# ---------------------------------------------------------------------------------------
# Schema building blocks
# ---------------------------------------------------------------------------------------

_NUMBER: dict[str, Any] = {"type": ["number", "null"], "description": "null encodes a non-finite value (read as NaN)"}


def _int(description: str, *, minimum: int | None = 0) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "integer", "description": description}
    if minimum is not None:
        out["minimum"] = minimum
    return out


def _str(description: str) -> dict[str, Any]:
    return {"type": "string", "description": description}


def _bool(description: str) -> dict[str, Any]:
    return {"type": "boolean", "description": description}


def _num(description: str) -> dict[str, Any]:
    return {"type": ["number", "null"], "description": description + " (null = non-finite)"}


def _vector(description: str) -> dict[str, Any]:
    return {"type": "array", "items": _NUMBER, "description": description + " (float32)"}


def _nullable_vector(description: str) -> dict[str, Any]:
    return {"type": ["array", "null"], "items": _NUMBER, "description": description + " (float32)"}


def _version_map(description: str) -> dict[str, Any]:
    return {
        "type": "object",
        "additionalProperties": {"type": "integer", "minimum": 0},
        "description": description,
    }


_EPISODE = _int("Episode index within the run")
_ECM = _str("ECM name")
_VERSION = _int("ECM version")


def _object_schema(title: str, description: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "title": title,
        "description": description,
        "type": "object",
        # each schema owns its property dicts (the shared building blocks are copied)
        "properties": {k: dict(v) for k, v in properties.items()},
        "required": list(properties),
        "additionalProperties": False,
    }


def _floats32(values: Iterable[Any]) -> tuple[float, ...]:
    """Decode a vector written with 9 significant digits back to the float32 values it names.

    The text names a float32 uniquely but parses to a nearby float64; rounding to float32
    restores the written value exactly. Values beyond float32 range (only a float64 input
    can produce them) are kept as parsed rather than turned into infinities.
    """
    parsed = np.array([_NAN if v is None else v for v in values], dtype=np.float64)
    with np.errstate(over="ignore"):
        rounded = parsed.astype(np.float32).astype(np.float64)
    rounded = np.where(np.isinf(rounded) & np.isfinite(parsed), parsed, rounded)
    return tuple(rounded.tolist())


def _float(value: Any) -> float:
    return _NAN if value is None else float(value)


FloatVector = tuple[float, ...] | npt.NDArray[np.float32]
"""A vector field's value: a tuple of floats, or a 1-D float32 array nobody changes afterwards
(the episode loop passes the env's own observation arrays, read-only: the writer prints them
without a conversion)."""


def _plain(value: Any) -> Any:
    """``value`` with arrays as tuples of floats, so records compare and hash by value."""
    if isinstance(value, np.ndarray):
        return tuple(value.tolist())
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _as_list(vector: FloatVector) -> list[float]:
    return vector.tolist() if isinstance(vector, np.ndarray) else list(vector)


class _ByValue:
    """Equality and hashing by field values, an array equal to the tuple of its values (a
    dataclass's own ``__eq__`` would compare arrays elementwise and fail)."""

    __slots__ = ()

    def _values(self) -> tuple[Any, ...]:
        return tuple(_plain(getattr(self, f.name)) for f in fields(self))  # type: ignore[arg-type]

    def __eq__(self, other: object) -> bool:
        if other is self:
            return True  # a record holding NaN equals itself, as a dataclass's does
        if type(other) is not type(self):
            return NotImplemented
        return self._values() == other._values()  # type: ignore[attr-defined, no-any-return]

    def __hash__(self) -> int:
        return hash(self._values())


# ---------------------------------------------------------------------------------------
# Topic registry
# ---------------------------------------------------------------------------------------

R = TypeVar("R")

_RECORD_TYPES: dict[str, type[Any]] = {}


def register_topic(cls: type[R]) -> type[R]:
    """Class decorator: make ``cls`` the record type of its ``TOPIC``.

    Raises:
        Conflict: another class already owns the topic.
    """
    topic: str = cls.TOPIC  # type: ignore[attr-defined]
    if topic in _RECORD_TYPES and _RECORD_TYPES[topic] is not cls:
        raise Conflict(f"trace topic {topic!r} is already registered to {_RECORD_TYPES[topic].__name__}")
    _RECORD_TYPES[topic] = cls
    return cls


def record_type(topic: str) -> type[TraceRecord]:
    """The record class of ``topic``.

    Raises:
        Invalid: unknown topic; the message lists the known ones.
    """
    try:
        return _RECORD_TYPES[topic]
    except KeyError:
        raise Invalid(
            f"unknown trace topic {topic!r}; known topics: {', '.join(sorted(_RECORD_TYPES))}",
            details={"field": "topic"},
        ) from None


def topics() -> tuple[str, ...]:
    """Every registered topic, in registration order."""
    return tuple(_RECORD_TYPES)


# ---------------------------------------------------------------------------------------
# Records
# ---------------------------------------------------------------------------------------


@register_topic
@dataclass(frozen=True, slots=True, kw_only=True)
class PlanStep:
    """The planner chose ECM ``ecm`` version ``version`` for plan step ``step`` of an episode."""

    TOPIC: ClassVar[str] = "/plan"
    SCHEMA_NAME: ClassVar[str] = "capevo.PlanStep"
    SCHEMA: ClassVar[dict[str, Any]] = _object_schema(
        SCHEMA_NAME,
        "One plan step: which ECM version the planner chose and why.",
        {
            "episode": _EPISODE,
            "step": _int("Plan step index within the episode"),
            "ecm": _ECM,
            "version": _VERSION,
            "reason": _str("Why the planner chose it"),
        },
    )

    episode: int
    step: int
    ecm: str
    version: int
    reason: str = ""

    def to_dict(self, *, vector: Callable[[Any], Any] = _as_list) -> dict[str, Any]:
        """The object :attr:`SCHEMA` describes (no vector fields: ``vector`` is not called)."""
        return {
            "episode": self.episode,
            "step": self.step,
            "ecm": self.ecm,
            "version": self.version,
            "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PlanStep:
        return cls(
            episode=int(d["episode"]),
            step=int(d["step"]),
            ecm=str(d["ecm"]),
            version=int(d["version"]),
            reason=str(d.get("reason", "")),
        )


@register_topic
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class EcmInvocation(_ByValue):
    """One call of an ECM version: what went in, what came out, how long it took, how it ended.

    ``output`` is None when the ECM produced nothing usable (timeout, exception); for
    ``nan``/``bad_shape`` it holds what the ECM returned.
    """

    TOPIC: ClassVar[str] = "/ecm/invocation"
    SCHEMA_NAME: ClassVar[str] = "capevo.EcmInvocation"
    SCHEMA: ClassVar[dict[str, Any]] = _object_schema(
        SCHEMA_NAME,
        "One ECM invocation with its input state, output, duration and outcome.",
        {
            "episode": _EPISODE,
            "step": _int("Env step index at which the ECM was invoked"),
            "ecm": _ECM,
            "version": _VERSION,
            "input_state": _vector("Flat input state given to the ECM"),
            "output": _nullable_vector("Flat output of the ECM; null when it produced none"),
            "duration_s": _num("Wall time of the call in seconds"),
            "outcome": {
                "type": "string",
                "enum": [o.value for o in Outcome],
                "description": "How the invocation ended",
            },
            "error": {"type": ["string", "null"], "description": "Error text when the outcome is not ok"},
        },
    )

    episode: int
    step: int
    ecm: str
    version: int
    input_state: FloatVector
    output: tuple[float, ...] | None
    duration_s: float
    outcome: Outcome = Outcome.OK
    error: str | None = None

    def to_dict(self, *, vector: Callable[[Any], Any] = _as_list) -> dict[str, Any]:
        """The object :attr:`SCHEMA` describes; ``vector`` makes each vector field (default: a list of floats)."""
        return {
            "episode": self.episode,
            "step": self.step,
            "ecm": self.ecm,
            "version": self.version,
            "input_state": vector(self.input_state),
            "output": None if self.output is None else vector(self.output),
            "duration_s": self.duration_s,
            "outcome": Outcome(self.outcome).value,
            "error": self.error,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EcmInvocation:
        output = d.get("output")
        return cls(
            episode=int(d["episode"]),
            step=int(d["step"]),
            ecm=str(d["ecm"]),
            version=int(d["version"]),
            input_state=_floats32(d["input_state"]),
            output=None if output is None else _floats32(output),
            duration_s=_float(d["duration_s"]),
            outcome=Outcome(d["outcome"]),
            error=d.get("error"),
        )


@register_topic
@dataclass(frozen=True, slots=True, kw_only=True)
class Intervention:
    """Governance changed or refused an action; ``result_action`` is None for a reject.

    ``enforced`` tells an enforcing governor (``result_action`` ran instead of the original)
    from counting mode (governance would have intervened, but the action ran unchanged; the
    episode loop then records what ran as ``result_action``). Reading a file written before
    the field, it is inferred from the reason's :data:`NOT_ENFORCED_PREFIX`.
    """

    TOPIC: ClassVar[str] = "/governance/intervention"
    SCHEMA_NAME: ClassVar[str] = "capevo.Intervention"
    SCHEMA: ClassVar[dict[str, Any]] = _object_schema(
        SCHEMA_NAME,
        "A governance intervention: the constraint, the proposed action and what was executed instead.",
        {
            "episode": _EPISODE,
            "step": _int("Env step index"),
            "constraint": _str("Name of the safety constraint that fired"),
            "original_action": _vector("Action the ECM proposed"),
            "result_action": _nullable_vector("Action executed instead; null when the action was rejected"),
            "reason": _str("Why governance intervened"),
            "enforced": _bool(
                "True: governance enforced, result_action ran instead. False: counting mode, governance "
                "would have intervened but the action ran unchanged (result_action is what ran)"
            ),
        },
    )

    episode: int
    step: int
    constraint: str
    original_action: tuple[float, ...]
    result_action: tuple[float, ...] | None
    reason: str = ""
    enforced: bool = True

    @property
    def rejected(self) -> bool:
        return self.result_action is None

    def to_dict(self, *, vector: Callable[[Any], Any] = _as_list) -> dict[str, Any]:
        """The object :attr:`SCHEMA` describes; ``vector`` makes each vector field (default: a list of floats)."""
        return {
            "episode": self.episode,
            "step": self.step,
            "constraint": self.constraint,
            "original_action": vector(self.original_action),
            "result_action": None if self.result_action is None else vector(self.result_action),
            "reason": self.reason,
            "enforced": self.enforced,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Intervention:
        result = d.get("result_action")
        reason = str(d.get("reason", ""))
        enforced = d.get("enforced")
        if enforced is None:
            # Files from before the field: counting mode marked its reasons instead.
            enforced = not reason.startswith(NOT_ENFORCED_PREFIX)
        return cls(
            episode=int(d["episode"]),
            step=int(d["step"]),
            constraint=str(d["constraint"]),
            original_action=_floats32(d["original_action"]),
            result_action=None if result is None else _floats32(result),
            reason=reason,
            enforced=bool(enforced),
        )


@register_topic
@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class EnvStep(_ByValue):
    """One environment transition, as executed (after governance).

    Vectors are tuples of floats; ``obs`` and ``next_obs`` may also be 1-D float32 arrays that
    nobody changes afterwards (see :data:`FloatVector`). Passing the previous step's
    ``next_obs`` tuple as this step's ``obs`` lets the writer reuse its conversion.
    ``key_state`` holds a few named vectors worth plotting, e.g. ``arm0_eef_pos``.
    """

    TOPIC: ClassVar[str] = "/env/step"
    SCHEMA_NAME: ClassVar[str] = "capevo.EnvStep"
    SCHEMA: ClassVar[dict[str, Any]] = _object_schema(
        SCHEMA_NAME,
        "One environment step: observation, executed action, reward and next observation.",
        {
            "episode": _EPISODE,
            "step": _int("Env step index within the episode"),
            "ecm": _str("ECM that produced the action"),
            "version": _int("Version of that ECM"),
            "obs": _vector("Flat observation before the step"),
            "action": _vector("Action executed (after governance)"),
            "reward": _num("Reward of the step"),
            "next_obs": _vector("Flat observation after the step"),
            "terminated": _bool("The episode ended in a terminal state"),
            "truncated": _bool("The episode was cut off (horizon, budget)"),
            "is_success": _bool("The task reports success after this step"),
            "key_state": {
                "type": "object",
                "additionalProperties": {"type": "array", "items": _NUMBER},
                "description": "Named state vectors worth plotting, e.g. arm0_eef_pos",
            },
        },
    )

    episode: int
    step: int
    ecm: str
    version: int
    obs: FloatVector
    action: tuple[float, ...]
    reward: float
    next_obs: FloatVector
    terminated: bool = False
    truncated: bool = False
    is_success: bool = False
    key_state: Mapping[str, tuple[float, ...]] = field(default_factory=dict)

    @property
    def done(self) -> bool:
        return self.terminated or self.truncated

    def to_dict(self, *, vector: Callable[[Any], Any] = _as_list) -> dict[str, Any]:
        """The object :attr:`SCHEMA` describes; ``vector`` makes each vector field (default: a list of floats)."""
        return {
            "episode": self.episode,
            "step": self.step,
            "ecm": self.ecm,
            "version": self.version,
            "obs": vector(self.obs),
            "action": vector(self.action),
            "reward": self.reward,
            "next_obs": vector(self.next_obs),
            "terminated": self.terminated,
            "truncated": self.truncated,
            "is_success": self.is_success,
            "key_state": {k: vector(v) for k, v in self.key_state.items()},
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EnvStep:
        return cls(
            episode=int(d["episode"]),
            step=int(d["step"]),
            ecm=str(d["ecm"]),
            version=int(d["version"]),
            obs=_floats32(d["obs"]),
            action=_floats32(d["action"]),
            reward=_float(d["reward"]),
            next_obs=_floats32(d["next_obs"]),
            terminated=bool(d["terminated"]),
            truncated=bool(d["truncated"]),
            is_success=bool(d["is_success"]),
            key_state={str(k): _floats32(v) for k, v in (d.get("key_state") or {}).items()},
        )


def _strings(description: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": "string"}, "description": description}


@register_topic
@dataclass(frozen=True, slots=True, kw_only=True)
class UnsafeStep:
    """A step the independent safety monitor graded unsafe (after governance, from ground truth)."""

    TOPIC: ClassVar[str] = "/safety/unsafe"
    SCHEMA_NAME: ClassVar[str] = "capevo.UnsafeStep"
    SCHEMA: ClassVar[dict[str, Any]] = _object_schema(
        SCHEMA_NAME,
        "An executed step the safety monitor graded unsafe: which limits broke and why.",
        {
            "episode": _EPISODE,
            "step": _int("Env step index"),
            "broken": _strings("Limits broken: box, cap, force, non_finite"),
            "reasons": _strings("One reason per broken limit"),
        },
    )

    episode: int
    step: int
    broken: tuple[str, ...]
    reasons: tuple[str, ...] = ()

    def to_dict(self, *, vector: Callable[[Any], Any] = _as_list) -> dict[str, Any]:
        """The object :attr:`SCHEMA` describes (no vector fields: ``vector`` is not called)."""
        return {"episode": self.episode, "step": self.step, "broken": list(self.broken), "reasons": list(self.reasons)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> UnsafeStep:
        return cls(
            episode=int(d["episode"]),
            step=int(d["step"]),
            broken=tuple(str(x) for x in d["broken"]),
            reasons=tuple(str(x) for x in d.get("reasons", ())),
        )


@register_topic
@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeSummary:
    """How one episode went, with the capability set it ran under."""

    TOPIC: ClassVar[str] = "/episode/summary"
    SCHEMA_NAME: ClassVar[str] = "capevo.EpisodeSummary"
    SCHEMA: ClassVar[dict[str, Any]] = _object_schema(
        SCHEMA_NAME,
        "Outcome of one episode and the capability set (ECM -> version) it ran with.",
        {
            "episode": _EPISODE,
            "seed": {"type": ["integer", "null"], "description": "Env seed of the episode, if seeded"},
            "success": _bool("The task succeeded"),
            "total_reward": _num("Sum of rewards"),
            "steps": _int("Env steps taken"),
            "interventions": _int("Governance interventions"),
            "unsafe_steps": _int("Steps that violated the safety envelope after governance"),
            "capability_set": _version_map("Active version of every ECM during the episode"),
            "revision": {"type": ["integer", "null"], "minimum": 0, "description": "Registry revision of that set"},
            "duration_s": _num("Wall time of the episode in seconds"),
        },
    )

    episode: int
    seed: int | None
    success: bool
    total_reward: float
    steps: int
    interventions: int
    unsafe_steps: int
    capability_set: Mapping[str, int]
    duration_s: float
    revision: int | None = None

    def to_dict(self, *, vector: Callable[[Any], Any] = _as_list) -> dict[str, Any]:
        """The object :attr:`SCHEMA` describes (no vector fields: ``vector`` is not called)."""
        return {
            "episode": self.episode,
            "seed": self.seed,
            "success": self.success,
            "total_reward": self.total_reward,
            "steps": self.steps,
            "interventions": self.interventions,
            "unsafe_steps": self.unsafe_steps,
            "capability_set": dict(sorted(self.capability_set.items())),
            "revision": self.revision,
            "duration_s": self.duration_s,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EpisodeSummary:
        seed = d.get("seed")
        revision = d.get("revision")
        return cls(
            episode=int(d["episode"]),
            seed=None if seed is None else int(seed),
            success=bool(d["success"]),
            total_reward=_float(d["total_reward"]),
            steps=int(d["steps"]),
            interventions=int(d["interventions"]),
            unsafe_steps=int(d["unsafe_steps"]),
            capability_set={str(k): int(v) for k, v in d["capability_set"].items()},
            duration_s=_float(d["duration_s"]),
            revision=None if revision is None else int(revision),
        )


TraceRecord = PlanStep | EcmInvocation | Intervention | EnvStep | UnsafeStep | EpisodeSummary
"""Any record a trace holds."""


# ---------------------------------------------------------------------------------------
# File metadata
# ---------------------------------------------------------------------------------------

PACKAGES: Mapping[str, str] = {
    "capevo": "capevo",
    "robosuite": "robosuite",
    "mujoco": "mujoco",
    "numpy": "numpy",
    "torch": "torch",
    "stable-baselines3": "stable-baselines3",
    "zenoh": "eclipse-zenoh",
    "mcap": "mcap",
}
"""Key in the trace's package table -> distribution name to ask importlib.metadata about."""

NOT_INSTALLED = "not installed"

RUN_METADATA = "capevo.run"
PACKAGES_METADATA = "capevo.packages"


def package_versions(
    packages: Mapping[str, str] = PACKAGES, *, lookup: Callable[[str], str] = importlib.metadata.version
) -> dict[str, str]:
    """Installed version of each package, without importing any of them.

    Returns:
        ``{key: version}``; a package that is not installed maps to ``"not installed"``.
    """
    out: dict[str, str] = {}
    for key, dist in packages.items():
        try:
            out[key] = lookup(dist)
        except importlib.metadata.PackageNotFoundError:
            out[key] = NOT_INSTALLED
    return out


def _require_str(value: object, name: str) -> str:
    if not isinstance(value, str) or not value:
        raise Invalid(f"trace metadata {name} must be a non-empty string, got {value!r}", details={"field": name})
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class TraceMetadata:
    """What a trace file says about the run that wrote it (MCAP metadata records).

    Args:
        run_id: Unique id of the run.
        task: Task name, e.g. ``Lift``.
        capability_set: Registry revision and the active version of every ECM at start.
        phi_hash: Hash of the governance safety envelope Φ.
        agent_identity_hash: Hash of the persistent agent's identity.
        seeds: Seeds the run used (run seed first, then per-episode seeds if known).
        package_versions: ``{package: version}``; see :func:`package_versions`.
        worker_id: Which runtime worker wrote the file.

    Raises:
        Invalid: an empty or non-string id, task or hash, or a non-integer seed.
    """

    run_id: str
    task: str
    capability_set: CapabilitySet
    phi_hash: str
    agent_identity_hash: str
    seeds: tuple[int, ...] = ()
    package_versions: Mapping[str, str] = field(default_factory=dict)
    worker_id: str = ""

    def __post_init__(self) -> None:
        _require_str(self.run_id, "run_id")
        _require_str(self.task, "task")
        _require_str(self.phi_hash, "phi_hash")
        _require_str(self.agent_identity_hash, "agent_identity_hash")
        if not isinstance(self.capability_set, CapabilitySet):
            raise Invalid("trace metadata capability_set must be a CapabilitySet", details={"field": "capability_set"})
        for seed in self.seeds:
            if isinstance(seed, bool) or not isinstance(seed, int):
                raise Invalid(f"trace metadata seeds must be integers, got {seed!r}", details={"field": "seeds"})

    @property
    def registry_revision(self) -> int:
        return self.capability_set.revision

    @classmethod
    def collect(
        cls,
        *,
        run_id: str,
        task: str,
        capability_set: CapabilitySet,
        phi_hash: str,
        agent_identity_hash: str,
        seeds: Iterable[int] = (),
        worker_id: str = "",
    ) -> TraceMetadata:
        """Metadata for a run starting now, with the installed package versions filled in."""
        return cls(
            run_id=run_id,
            task=task,
            capability_set=capability_set,
            phi_hash=phi_hash,
            agent_identity_hash=agent_identity_hash,
            seeds=tuple(seeds),
            package_versions=package_versions(),
            worker_id=worker_id,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "trace_format": TRACE_FORMAT,
            "run_id": self.run_id,
            "task": self.task,
            "registry_revision": self.capability_set.revision,
            "capability_set": self.capability_set.to_dict()["active"],
            "phi_hash": self.phi_hash,
            "agent_identity_hash": self.agent_identity_hash,
            "seeds": list(self.seeds),
            "package_versions": dict(sorted(self.package_versions.items())),
            "worker_id": self.worker_id,
        }

    def to_mcap(self) -> dict[str, dict[str, str]]:
        """The MCAP metadata records: ``{record name: {key: value}}``, all strings."""
        return {
            RUN_METADATA: {
                "trace_format": TRACE_FORMAT,
                "run_id": self.run_id,
                "task": self.task,
                "registry_revision": str(self.capability_set.revision),
                "capability_set": json.dumps(self.capability_set.to_dict()["active"], separators=(",", ":")),
                "phi_hash": self.phi_hash,
                "agent_identity_hash": self.agent_identity_hash,
                "seeds": json.dumps(list(self.seeds)),
                "worker_id": self.worker_id,
            },
            PACKAGES_METADATA: {str(k): str(v) for k, v in sorted(self.package_versions.items())},
        }

    @classmethod
    def from_mcap(cls, records: Mapping[str, Mapping[str, str]]) -> TraceMetadata:
        """Inverse of :meth:`to_mcap`.

        Raises:
            Corrupt: the ``capevo.run`` record is missing or a field does not parse.
        """
        run = records.get(RUN_METADATA)
        if run is None:
            found = ", ".join(sorted(records)) or "none"
            raise Corrupt(f"not a capevo trace: no {RUN_METADATA!r} metadata record (found: {found})")
        try:
            active = json.loads(run["capability_set"])
            return cls(
                run_id=run["run_id"],
                task=run["task"],
                capability_set=CapabilitySet(
                    revision=int(run["registry_revision"]), active={str(k): int(v) for k, v in active.items()}
                ),
                phi_hash=run["phi_hash"],
                agent_identity_hash=run["agent_identity_hash"],
                seeds=tuple(int(s) for s in json.loads(run["seeds"])),
                package_versions=dict(records.get(PACKAGES_METADATA, {})),
                worker_id=run.get("worker_id", ""),
            )
        except (KeyError, ValueError, TypeError, AttributeError, Invalid) as exc:
            raise Corrupt(f"trace metadata {RUN_METADATA!r} does not parse: {type(exc).__name__}: {exc}") from None
