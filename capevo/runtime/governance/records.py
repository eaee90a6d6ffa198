"""What governance reports: one frozen record per intervention, and run counters.

Invariants:
1. ``Intervention.from_dict(i.to_dict()) == i`` for every intervention with finite actions;
   non-finite floats survive the trip as the strings ``"nan"``, ``"inf"``, ``"-inf"``.
2. ``to_dict()`` output contains only JSON types and never a non-finite float, so a trace
   writer can use strict JSON (``allow_nan=False``).
3. :func:`verdict_of` depends only on the interventions: none is ALLOW, a last one with no
   result is REJECT, anything else is MODIFY. It is the same in enforcing and counting mode.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from capevo.errors import Invalid


class Verdict(str, enum.Enum):
    """R(a, Φ) is the action itself, a safe replacement a′, or ⊥."""

    ALLOW = "allow"
    MODIFY = "modify"
    REJECT = "reject"


def _encode(x: float) -> float | str:
    x = float(x)  # also turns ints and numpy scalars into plain JSON numbers
    return x if math.isfinite(x) else repr(x)


def _decode(x: object, key: str) -> float:
    if isinstance(x, str) and x in ("nan", "inf", "-inf"):
        return float(x)
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise Invalid(f"{key}: expected a number, got {type(x).__name__}", details={"field": key})
    return float(x)


def _floats(values: object, key: str) -> tuple[float, ...]:
    if not isinstance(values, (list, tuple)):
        raise Invalid(f"{key}: expected a list of numbers", details={"field": key})
    return tuple(_decode(v, f"{key}[{i}]") for i, v in enumerate(values))


@dataclass(frozen=True, slots=True, kw_only=True)
class Intervention:
    """One constraint changing or refusing an action.

    ``original`` is the action that constraint saw (the proposed action for the first
    constraint in Φ that intervened, the previous constraint's output after that).
    """

    constraint: str
    """Label of the constraint in Φ (its ``name``, or its kind when unnamed)."""
    original: tuple[float, ...]
    result: tuple[float, ...] | None
    """The safe replacement a′, or None for ⊥ (reject)."""
    reason: str
    enforced: bool = True
    """False in governance-off mode: the action went through unchanged; this is what R would have done."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "constraint": self.constraint,
            "original": [_encode(x) for x in self.original],
            "result": None if self.result is None else [_encode(x) for x in self.result],
            "reason": self.reason,
            "enforced": self.enforced,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Intervention:
        """Inverse of :meth:`to_dict`.

        Raises:
            Invalid: on a missing key or a wrongly typed value.
        """
        try:
            constraint, reason, enforced = d["constraint"], d["reason"], d.get("enforced", True)
            original, result = d["original"], d["result"]
        except (KeyError, TypeError) as exc:
            raise Invalid(f"intervention: missing key {exc}", details={"field": str(exc)}) from None
        if not isinstance(constraint, str) or not isinstance(reason, str) or not isinstance(enforced, bool):
            raise Invalid("intervention: constraint and reason must be strings, enforced a bool")
        return cls(
            constraint=constraint,
            original=_floats(original, "original"),
            result=None if result is None else _floats(result, "result"),
            reason=reason,
            enforced=enforced,
        )


# The slot setters new_intervention writes through, looked up once.
_NEW = object.__new__
_SET_CONSTRAINT, _SET_ORIGINAL, _SET_RESULT, _SET_REASON, _SET_ENFORCED = (
    Intervention.__dict__[f].__set__ for f in ("constraint", "original", "result", "reason", "enforced")
)


def new_intervention(
    constraint: str, original: tuple[float, ...], result: tuple[float, ...] | None, reason: str, enforced: bool
) -> Intervention:
    """Build an :class:`Intervention` about 5x faster than its ``__init__``, for the governor's hot path.

    It writes the slots directly instead of going through the frozen ``__setattr__`` detour;
    the result is an ordinary frozen instance. Arguments must already have the field types.
    """
    obj = _NEW(Intervention)
    _SET_CONSTRAINT(obj, constraint)
    _SET_ORIGINAL(obj, original)
    _SET_RESULT(obj, result)
    _SET_REASON(obj, reason)
    _SET_ENFORCED(obj, enforced)
    return obj


def verdict_of(interventions: Sequence[Intervention]) -> Verdict:
    """The verdict a governor's interventions for one action amount to."""
    if not interventions:
        return Verdict.ALLOW
    return Verdict.REJECT if interventions[-1].result is None else Verdict.MODIFY


@dataclass(frozen=True, slots=True, kw_only=True)
class GovernanceStats:
    """Counters of one governor since it was built (or last reset)."""

    enforced: bool
    """False for a governance-off (counting) governor."""
    steps: int
    """Actions seen."""
    modified: int
    """Actions R changed (or, when not enforced, would have changed)."""
    rejected: int
    """Actions R refused (or would have refused)."""
    by_constraint: Mapping[str, int] = field(default_factory=dict)
    """Interventions per constraint label."""

    @property
    def intervened(self) -> int:
        """Actions R changed or refused: the violations it prevented (or would have)."""
        return self.modified + self.rejected

    def to_dict(self) -> dict[str, Any]:
        return {
            "enforced": self.enforced,
            "steps": self.steps,
            "modified": self.modified,
            "rejected": self.rejected,
            "by_constraint": dict(self.by_constraint),
        }
