"""M_id, the agent's identity memory: goals, beliefs and task decompositions, from YAML.

Format (``version`` 1)::

    version: 1
    name: capevo-default                 # slug naming this agent
    description: Persistent agent ...    # optional, free text
    goals:                               # optional; ids unique
      - {id: complete_task, text: Complete the assigned manipulation task.}
    beliefs:                             # optional; ids unique
      - {id: capabilities_evolve, text: ECM versions change between iterations; the agent does not.}
    decompositions:                      # task name -> ECM names, in the order they run
      pick: [pick.reach, pick.grasp, pick.lift]

The decomposition is the plan skeleton of :class:`~capevo.agent.policy.DecompositionPolicy`;
the ECMs themselves (and their descriptors) come from the capability set at run time.

Invariants:
1. ``parse_identity(identity.to_yaml()) == identity`` for every valid identity.
2. Loading raises only :class:`Invalid` for any input text; its message starts with the dotted
   path of the offending field (``decompositions.pick[1]``) and ``details["field"]`` is that path.
3. Every ECM name in a decomposition is a valid registry slug and appears once in its
   decomposition (the policy locates the previous step by name); goal and belief ids are unique.
4. ``IdentityMemory.to_dict()`` holds only JSON types and is what the identity hash covers.
5. The records are frozen; ``decompositions`` is a read-only mapping of tuples.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

import jsonschema
import yaml

from capevo.errors import Invalid
from capevo.records.names import validate_name

FORMAT_VERSION = 1
MAX_IDENTITY_BYTES = 1024 * 1024
DEFAULT_IDENTITY_RESOURCE = "default_identity.yaml"

_SLUG = r"^[a-z0-9][a-z0-9._-]{0,63}$"
_ENTRY = {
    "type": "object",
    "additionalProperties": False,
    "required": ["id", "text"],
    "properties": {
        "id": {"type": "string", "pattern": _SLUG},
        "text": {"type": "string", "minLength": 1, "maxLength": 4096},
    },
}
SCHEMA: Mapping[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "additionalProperties": False,
    "required": ["version", "name", "decompositions"],
    "properties": {
        "version": {"const": FORMAT_VERSION},
        "name": {"type": "string", "pattern": _SLUG},
        "description": {"type": "string", "maxLength": 8192},
        "goals": {"type": "array", "maxItems": 256, "items": _ENTRY},
        "beliefs": {"type": "array", "maxItems": 1024, "items": _ENTRY},
        "decompositions": {
            "type": "object",
            "minProperties": 1,
            "maxProperties": 1024,
            "propertyNames": {"pattern": _SLUG},
            "additionalProperties": {
                "type": "array",
                "minItems": 1,
                "maxItems": 256,
                "items": {"type": "string", "minLength": 1, "maxLength": 256},
            },
        },
    },
}
_VALIDATOR = jsonschema.Draft202012Validator(SCHEMA)


@dataclass(frozen=True, slots=True, kw_only=True)
class Goal:
    """One goal the agent pursues; ``text`` is for people and planners."""

    id: str
    text: str

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "text": self.text}


@dataclass(frozen=True, slots=True, kw_only=True)
class Belief:
    """One standing belief the agent holds about itself or its world."""

    id: str
    text: str

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "text": self.text}


@dataclass(frozen=True, slots=True, kw_only=True)
class IdentityMemory:
    """M_id: everything the agent is, apart from its decision policy's parameters.

    Build it with :func:`parse_identity`, :func:`load_identity` or
    :meth:`IdentityMemory.default`; the constructor does not re-validate names.
    """

    name: str
    description: str = ""
    goals: tuple[Goal, ...] = ()
    beliefs: tuple[Belief, ...] = ()
    decompositions: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # A private copy behind a read-only view: the caller's dict cannot change M_id later.
        frozen = {str(k): tuple(v) for k, v in self.decompositions.items()}
        object.__setattr__(self, "decompositions", MappingProxyType(frozen))
        object.__setattr__(self, "goals", tuple(self.goals))
        object.__setattr__(self, "beliefs", tuple(self.beliefs))

    @classmethod
    def default(cls) -> IdentityMemory:
        """The packaged ``default_identity.yaml`` (decompositions of the six built-in tasks).

        Parsed afresh on every call, so no caller can alter another caller's copy.
        """
        return _default()

    @property
    def tasks(self) -> tuple[str, ...]:
        """Task names with a decomposition, in file order."""
        return tuple(self.decompositions)

    def decomposition(self, task: str) -> tuple[str, ...]:
        """The ECM names of ``task``'s decomposition, in order.

        ``task`` may also be a built-in task id (``"T1"``), resolved through
        :func:`capevo.runtime.tasks.task_ids`.

        Raises:
            Invalid: no decomposition for ``task``; the message lists the known tasks.
        """
        steps = self.decompositions.get(task)
        if steps is None and isinstance(task, str):
            steps = self.decompositions.get(_task_name_for_id(task) or "")
        if steps is None:
            raise Invalid(
                f"identity {self.name!r} has no decomposition for task {task!r}; known: {', '.join(self.tasks)}",
                details={"field": "task", "task": task, "valid": list(self.tasks)},
            )
        return steps

    def to_dict(self) -> dict[str, Any]:
        """The document form (``version`` included): what the identity hash covers."""
        return {
            "version": FORMAT_VERSION,
            "name": self.name,
            "description": self.description,
            "goals": [g.to_dict() for g in self.goals],
            "beliefs": [b.to_dict() for b in self.beliefs],
            "decompositions": {task: list(steps) for task, steps in self.decompositions.items()},
        }

    def to_yaml(self) -> str:
        """YAML that :func:`parse_identity` reads back to an equal identity."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False, allow_unicode=True, width=120)


def _task_name_for_id(task_id: str) -> str | None:
    # Imported late: the task registry pulls in gymnasium, which pure planning never needs
    # unless the runtime names a task by its id.
    from capevo.runtime.tasks import task_ids

    return task_ids().get(task_id)


def _path(parts: Sequence[Any]) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<document>"


def _fail(field_path: str, message: str) -> Invalid:
    return Invalid(f"{field_path}: {message}", details={"field": field_path})


def identity_from_document(doc: object) -> IdentityMemory:
    """Validate a parsed document against :data:`SCHEMA` and the rules it cannot say.

    Raises:
        Invalid: whose message starts with the offending field's dotted path.
    """
    if not isinstance(doc, dict):
        raise _fail("<document>", "an identity must be a mapping with version, name and decompositions")
    errors = sorted(_VALIDATOR.iter_errors(doc), key=lambda e: (len(e.absolute_path), list(map(str, e.absolute_path))))
    if errors:
        err = jsonschema.exceptions.best_match(errors) or errors[0]
        where = _path(list(err.absolute_path))
        message = err.message
        if "propertyNames" in err.absolute_schema_path:
            # jsonschema reports a bad key at its parent mapping; name the key itself.
            where = f"{where}.{err.instance}"
        if err.validator == "pattern" and err.schema.get("pattern") == _SLUG:
            message = f"must be a slug (lowercase letters, digits, '.', '_', '-'; at most 64), got {err.instance!r}"
        raise _fail(where, message)
    for section in ("goals", "beliefs"):
        seen: set[str] = set()
        for i, entry in enumerate(doc.get(section, ())):
            if entry["id"] in seen:
                raise _fail(f"{section}[{i}].id", f"duplicate id {entry['id']!r}")
            seen.add(entry["id"])
    for task, steps in doc["decompositions"].items():
        seen = set()
        for i, ecm in enumerate(steps):
            where = f"decompositions.{task}[{i}]"
            try:
                validate_name(ecm)
            except Invalid as exc:
                raise _fail(where, exc.message) from None
            if ecm in seen:
                raise _fail(where, f"step {ecm!r} appears twice; each ECM runs at one place in a decomposition")
            seen.add(ecm)
    return IdentityMemory(
        name=doc["name"],
        description=doc.get("description", ""),
        goals=tuple(Goal(id=g["id"], text=g["text"]) for g in doc.get("goals", ())),
        beliefs=tuple(Belief(id=b["id"], text=b["text"]) for b in doc.get("beliefs", ())),
        decompositions={task: tuple(steps) for task, steps in doc["decompositions"].items()},
    )


def parse_identity(text: str | bytes) -> IdentityMemory:
    """Parse identity YAML (JSON is YAML too).

    Raises:
        Invalid: on oversize input, YAML syntax errors, or any bad field.
    """
    if len(text) > MAX_IDENTITY_BYTES:
        raise _fail("<document>", f"identity is {len(text)} bytes; the limit is {MAX_IDENTITY_BYTES}")
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise _fail("<document>", f"not valid YAML{where}: {getattr(exc, 'problem', None) or exc}") from None
    except (ValueError, RecursionError) as exc:
        raise _fail("<document>", f"not valid YAML: {exc}") from None
    return identity_from_document(doc)


def load_identity(path: str | os.PathLike[str]) -> IdentityMemory:
    """Read and parse an identity YAML file.

    Raises:
        Invalid: unreadable or oversize file, or any error :func:`parse_identity` raises.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_IDENTITY_BYTES:
            raise _fail("<document>", f"{p} is {size} bytes; the limit is {MAX_IDENTITY_BYTES}")
        data = p.read_bytes()
    except OSError as exc:
        raise _fail("<document>", f"cannot read {p}: {exc.strerror}") from None
    return parse_identity(data)


def _default() -> IdentityMemory:
    text = resources.files("capevo.agent").joinpath(DEFAULT_IDENTITY_RESOURCE).read_text(encoding="utf-8")
    return parse_identity(text)
