"""What one ECM call produced, and what one invoker step decided.

Invariants:
1. ``Outcome.action`` is a tuple of finite floats exactly when ``status`` is ``ok``.
2. ``StepResult.action`` is None exactly when the step ended the skill
   (``terminated`` or ``budget_exhausted``); otherwise it is the action to apply, from the
   primary ECM, a recovery, or the safe hold.
3. ``X.from_dict(x.to_dict()) == x`` for both records, and ``to_dict`` is JSON-able.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


class Status(str, enum.Enum):
    """How one ECM call ended."""

    OK = "ok"
    EXCEPTION = "exception"
    """The ECM raised, or its sandbox worker died."""
    TIMEOUT = "timeout"
    """No result within the per-call timeout (killed in the sandbox; discarded after the fact in-process)."""
    NAN = "nan"
    """The action contains NaN or infinity."""
    BAD_SHAPE = "bad_shape"
    """The action has the wrong shape or is not numeric."""
    BUDGET_EXHAUSTED = "budget_exhausted"
    """The ECM already used its step budget; it was not called."""
    TERMINATED = "terminated"
    """The ECM's termination check says it is done; no action."""


FAILURES: frozenset[Status] = frozenset({Status.EXCEPTION, Status.TIMEOUT, Status.NAN, Status.BAD_SHAPE})
"""Statuses a recovery strategy handles; the others are normal ends or successes."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Outcome:
    """One call of one ECM."""

    status: Status
    ecm: str
    version: int
    action: tuple[float, ...] | None
    duration_s: float
    error: str | None = None
    clipped: bool = False
    """The action exceeded the interface's output bounds and was clipped to them."""

    @property
    def ok(self) -> bool:
        return self.status is Status.OK

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status.value,
            "ecm": self.ecm,
            "version": self.version,
            "action": list(self.action) if self.action is not None else None,
            "duration_s": self.duration_s,
            "error": self.error,
            "clipped": self.clipped,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Outcome:
        action = d.get("action")
        return cls(
            status=Status(d["status"]),
            ecm=d["ecm"],
            version=int(d["version"]),
            action=tuple(float(a) for a in action) if action is not None else None,
            duration_s=float(d["duration_s"]),
            error=d.get("error"),
            clipped=bool(d.get("clipped", False)),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class StepResult:
    """One step of the invoker: every call made, and the action to apply.

    ``status`` is that of the call whose action is used; when the safe hold was applied it
    is the primary's failure status and ``recovery`` names the strategy chain that ended in
    the hold (``"abort"``).
    """

    step: int
    status: Status
    action: tuple[float, ...] | None
    attempts: tuple[Outcome, ...]
    recovery: str | None = None
    aborted: bool = False

    @property
    def done(self) -> bool:
        """The skill is over (terminated or out of budget); the caller moves on."""
        return self.action is None

    def to_dict(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "status": self.status.value,
            "action": list(self.action) if self.action is not None else None,
            "attempts": [a.to_dict() for a in self.attempts],
            "recovery": self.recovery,
            "aborted": self.aborted,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StepResult:
        action = d.get("action")
        return cls(
            step=int(d["step"]),
            status=Status(d["status"]),
            action=tuple(float(a) for a in action) if action is not None else None,
            attempts=tuple(Outcome.from_dict(a) for a in d.get("attempts", ())),
            recovery=d.get("recovery"),
            aborted=bool(d.get("aborted", False)),
        )
