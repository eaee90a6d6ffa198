"""Φ: the safety envelope of a run, loaded from YAML and fixed for the run's life.

Format::

    version: 1
    constraints:
      - kind: workspace_box          # a registered kind (see constraint_kinds())
        name: table_box              # optional label; defaults to the kind
        low: [-0.6, -0.6, 0.6]       # every other key is a keyword argument of the kind
        high: [0.6, 0.6, 1.3]
        margin: 0.08
      - {kind: velocity_cap, max_norm: 1.5}
      - {kind: contact_force, max_force: 20.0}
      - kind: forbidden_zone
        boxes: [{low: [0.3, -0.1, 0.8], high: [0.5, 0.1, 1.0]}]
        margin: 0.05

Keys left out take the constraint's default. Order matters: R applies constraints in order.

Invariants:
1. ``phi.hash`` is the sha256 hex digest of the canonical JSON (sorted keys, no spaces) of
   ``phi.to_dict()``: every constraint with every field filled in and coerced to its type.
   Key order, whitespace, comments, ``1`` vs ``1.0`` and omitted defaults do not change it;
   any change of a value, a label or the order of constraints does.
2. ``load_phi(phi.to_yaml()) == phi`` and has the same hash.
3. Labels are unique within Φ (interventions name constraints by label); ``governor`` is reserved.
4. Loading raises only :class:`Invalid` for any input; its message starts with the dotted
   path of the offending field (``constraints[1].margin``) and ``details["field"]`` is that path.
5. ``Phi.default()`` is the packaged ``default_phi.yaml``, which equals every default
   constraint built with no arguments: workspace_box, contact_force, velocity_cap (in that order).
6. ``phi_for_task(t, base)`` (``Phi.for_task``) starts with every constraint of ``base`` in
   order, the task's constraints (:mod:`capevo.runtime.governance.task_phi`) inserted just
   before its first ``velocity_cap`` (appended when it has none), so the cap still acts last.
7. Its result depends only on the task's name and the base: equal inputs, equal hash; the six
   built-in tasks give four distinct hashes (pick, place and pick_place_multi share a scene),
   none equal to the base's. An unknown task raises :class:`Invalid` listing the known ones.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from capevo.errors import Invalid
from capevo.records.audit import canonical_json
from capevo.runtime.governance import (  # noqa: F401 - registers the built-in kinds
    box,
    cap,
    contact_approach,
    force,
    guard,
    obstacle,
    ramp,
    reach,
    separation,
    surface,
    zone,
)
from capevo.runtime.governance.base import CONSTRAINTS, Constraint, build, constraint_kinds, prefixed
from capevo.runtime.governance.cap import VelocityCap
from capevo.runtime.governance.task_phi import TASK_GEOMETRY, task_constraints, task_name_of
from capevo.runtime.state import ActionLayout

if TYPE_CHECKING:
    from capevo.runtime.governance.governor import Governor

FORMAT_VERSION = 1
MAX_PHI_BYTES = 64 * 1024
DEFAULT_PHI_RESOURCE = "default_phi.yaml"


@dataclass(frozen=True, slots=True)
class Phi:
    """An ordered, immutable set of constraints with a content hash.

    Args:
        constraints: The constraints, in the order R applies them.

    Raises:
        Invalid: if two constraints share a label.
    """

    constraints: tuple[Constraint, ...]
    hash: str = field(init=False, compare=False)
    """sha256 hex digest of the normalized config; record it in every trace."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "constraints", tuple(self.constraints))
        seen: set[str] = set()
        for i, c in enumerate(self.constraints):
            if c.label == "governor":
                raise Invalid(
                    f"constraints[{i}].name: 'governor' is reserved for the governor's own input checks",
                    details={"field": f"constraints[{i}].name"},
                )
            if c.label in seen:
                raise Invalid(
                    f"constraints[{i}].name: label {c.label!r} is used twice; give one of them a distinct name",
                    details={"field": f"constraints[{i}].name"},
                )
            seen.add(c.label)
        digest = hashlib.sha256(canonical_json(self.to_dict()).encode()).hexdigest()
        object.__setattr__(self, "hash", digest)

    @classmethod
    def default(cls) -> Phi:
        """The paper's envelope, from the packaged ``default_phi.yaml``."""
        return _default()

    @classmethod
    def for_task(cls, task: Any, base: Phi | None = None) -> Phi:
        """The paper's envelope (or ``base``) plus the task's scene; see :func:`phi_for_task`."""
        return phi_for_task(task, base)

    @property
    def reads_proximity(self) -> bool:
        """True if some constraint reads the hands' proximity pairs, so the state must sense them.

        Sensing costs about 0.08 ms per step (MuJoCo distance queries), so environments skip
        it unless the envelope they are governed by needs it.
        """
        return any(getattr(c, "reads_proximity", False) for c in self.constraints)

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(c.label for c in self.constraints)

    def __iter__(self) -> Iterator[Constraint]:
        return iter(self.constraints)

    def __len__(self) -> int:
        return len(self.constraints)

    def to_dict(self) -> dict[str, Any]:
        """The normalized config: what the hash covers."""
        return {
            "version": FORMAT_VERSION,
            "constraints": [{"kind": c.kind, **c.to_config()} for c in self.constraints],
        }

    def to_yaml(self) -> str:
        """YAML that :func:`load_phi` reads back to an equal Φ."""
        doc = self.to_dict()
        for entry in doc["constraints"]:
            if entry.get("name") is None:
                entry.pop("name", None)
        return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)

    def governor(
        self, layout: ActionLayout, *, enforce: bool = True, frames: Sequence[Sequence[float]] | None = None
    ) -> Governor:
        """R for actions of ``layout``; see :class:`~capevo.runtime.governance.governor.Governor`.

        ``enforce=False`` is the evaluation-only governance-off mode; ``frames`` gives each
        arm's action-to-world rotation (identity by default).
        """
        from capevo.runtime.governance.governor import Governor

        return Governor(self, layout, enforce=enforce, frames=frames)


def phi_for_task(task: Any, base: Phi | None = None) -> Phi:
    """Φ for one task: ``base`` (default: the paper's) plus the task's scene constraints.

    Args:
        task: A task name (``"pick"``), a ``TaskSpec`` or a ``TaskEnv``; for a task id
            (``"T1"``) pass its spec, ``capevo.runtime.tasks.task_spec("T1")``.
        base: The envelope to extend; default :meth:`Phi.default`.

    Raises:
        Invalid: for an unknown task, or if an added label collides with one of ``base``.
    """
    base = Phi.default() if base is None else base
    added = task_constraints(TASK_GEOMETRY[task_name_of(task)], base.constraints)
    cs = list(base.constraints)
    at = next((i for i, c in enumerate(cs) if isinstance(c, VelocityCap)), len(cs))
    return Phi((*cs[:at], *added, *cs[at:]))


def phi_from_document(doc: object) -> Phi:
    """Build Φ from a parsed YAML/JSON document.

    Raises:
        Invalid: naming the offending field's dotted path.
    """
    if not isinstance(doc, Mapping):
        raise Invalid(
            "<document>: Φ must be a mapping with 'version' and 'constraints'", details={"field": "<document>"}
        )
    for key in doc:
        if key not in ("version", "constraints"):
            raise Invalid(
                f"{key}: unknown key; valid keys: constraints, version",
                details={"field": str(key), "valid": ["constraints", "version"]},
            )
    version = doc.get("version", FORMAT_VERSION)
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise Invalid(
            f"version: unsupported Φ format version {version!r}; expected {FORMAT_VERSION}",
            details={"field": "version"},
        )
    entries = doc.get("constraints")
    if not isinstance(entries, list):
        raise Invalid("constraints: expected a list of constraints", details={"field": "constraints"})
    built: list[Constraint] = []
    for i, entry in enumerate(entries):
        where = f"constraints[{i}]"
        if not isinstance(entry, Mapping):
            raise Invalid(f"{where}: expected a mapping with a 'kind'", details={"field": where})
        kind = entry.get("kind")
        cls = CONSTRAINTS.get(kind) if isinstance(kind, str) else None
        if cls is None:
            raise Invalid(
                f"{where}.kind: unknown constraint kind {kind!r}; valid kinds: {', '.join(constraint_kinds())}",
                details={"field": f"{where}.kind", "valid": constraint_kinds()},
            )
        try:
            built.append(build(cls, {k: v for k, v in entry.items() if k != "kind"}))
        except Invalid as exc:
            raise prefixed(exc, where) from None
    return Phi(tuple(built))


def load_phi(source: str | bytes | os.PathLike[str]) -> Phi:
    """Load Φ from a YAML file path or from YAML text.

    A ``PathLike``, or a ``str`` naming an existing file, is read as a file; any other
    ``str``/``bytes`` is YAML text.

    Raises:
        Invalid: on an unreadable or oversize file, YAML syntax errors, or any bad field.
    """
    if isinstance(source, os.PathLike) or (
        isinstance(source, str) and "\n" not in source and len(source) < 4096 and Path(source).is_file()
    ):
        path = Path(source)
        try:
            size = path.stat().st_size
            if size > MAX_PHI_BYTES:
                raise Invalid(
                    f"<document>: {path} is {size} bytes; the limit is {MAX_PHI_BYTES}", details={"field": "<document>"}
                )
            text: str | bytes = path.read_bytes()
        except OSError as exc:
            raise Invalid(f"<document>: cannot read {path}: {exc.strerror}", details={"field": "<document>"}) from None
    elif isinstance(source, str) and "\n" not in source and source.endswith((".yaml", ".yml", ".json")):
        raise Invalid(f"<document>: {source} is not a file", details={"field": "<document>"})
    else:
        text = source  # type: ignore[assignment]
    if len(text) > MAX_PHI_BYTES:
        raise Invalid(
            f"<document>: Φ is {len(text)} bytes; the limit is {MAX_PHI_BYTES}", details={"field": "<document>"}
        )
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise Invalid(
            f"<document>: not valid YAML{where}: {getattr(exc, 'problem', exc)}", details={"field": "<document>"}
        ) from None
    except (ValueError, RecursionError) as exc:
        raise Invalid(f"<document>: not valid YAML: {exc}", details={"field": "<document>"}) from None
    return phi_from_document(doc)


@cache
def _default() -> Phi:
    text = resources.files("capevo.runtime.governance").joinpath(DEFAULT_PHI_RESOURCE).read_text()
    return load_phi(text)
