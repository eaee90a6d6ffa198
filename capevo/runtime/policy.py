"""What the episode loop asks of the persistent agent's decision policy π_A.

The runtime executes; the agent decides. Each time the running ECM finishes (its
termination predicate holds, its code ``done()`` says so, it fails, or its step budget runs
out), the loop calls :meth:`DecisionPolicy.decide` with the task's current signals and what
just happened, and runs the ECM it names next. The policy never sees or changes ECM
parameters: that is what keeps the agent fixed while its capabilities evolve.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from capevo.records import EcmVersion


class StepEnd(str, enum.Enum):
    """Why the previous ECM stopped running."""

    STARTED = "started"
    """No ECM ran yet: the episode just began."""
    TERMINATED = "terminated"
    """Its termination predicate held (success of the step)."""
    FAILED = "failed"
    """Exception, timeout, NaN or bad output that recovery could not mend."""
    BUDGET_EXHAUSTED = "budget_exhausted"
    """It ran its per-ECM step budget without reaching its termination predicate."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Decision:
    """The policy's answer: run ``ecm`` next, or finish the episode (``ecm`` None)."""

    ecm: str | None
    reason: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class DecisionContext:
    """What the policy may look at when it decides."""

    task: str
    signals: Mapping[str, float]
    previous_ecm: str | None
    previous_end: StepEnd
    capabilities: Mapping[str, EcmVersion]
    """The active version of every ECM the runtime has loaded, with its descriptor."""
    attempts: Mapping[str, int]
    """How many times each ECM has been started in this episode (for retry limits)."""


@runtime_checkable
class DecisionPolicy(Protocol):
    """π_A as the runtime sees it."""

    def decide(self, context: DecisionContext) -> Decision:
        """The next ECM to run, or ``Decision(ecm=None)`` to end the episode."""
        ...
