"""The one lifecycle state machine of an ECM version.

::

    candidate ──promote──▶ active ──(another promoted / rolled back)──▶ superseded
        │                                                            │
        └──reject──▶ rejected              superseded ──rollback──▶ active
    any state but active ──deprecate──▶ deprecated   (terminal)

Invariants:
1. ``check_transition`` raises :class:`IllegalTransition` for every (from, action) pair
   not listed in ``TRANSITIONS``; it never returns a state not listed there.
2. ``active`` is never the result of ``deprecate`` or ``reject``; an active version cannot
   be deprecated (move the pointer first).
"""

from __future__ import annotations

from collections.abc import Mapping

from capevo.errors import IllegalTransition
from capevo.records import Action, State

TRANSITIONS: Mapping[tuple[State, Action], State] = {
    (State.CANDIDATE, Action.PROMOTE): State.ACTIVE,
    (State.CANDIDATE, Action.REJECT): State.REJECTED,
    (State.SUPERSEDED, Action.ROLLBACK): State.ACTIVE,
    (State.CANDIDATE, Action.DEPRECATE): State.DEPRECATED,
    (State.SUPERSEDED, Action.DEPRECATE): State.DEPRECATED,
    (State.REJECTED, Action.DEPRECATE): State.DEPRECATED,
}

# Gate evidence may be recorded on a candidate only: once decided, evidence is history.
GATEABLE: frozenset[State] = frozenset({State.CANDIDATE})


def check_transition(name: str, version: int, current: State, action: Action) -> State:
    """The state ``action`` moves version ``version`` of ``name`` to, or raise.

    Raises:
        IllegalTransition: with the current state and the allowed actions from it.
    """
    try:
        return TRANSITIONS[(current, action)]
    except KeyError:
        allowed = sorted(a.value for (s, a) in TRANSITIONS if s is current)
        raise IllegalTransition(
            f"cannot {action.value} {name} v{version}: it is {current.value}"
            + (f" (allowed: {', '.join(allowed)})" if allowed else " (no action is allowed)"),
            details={"name": name, "version": version, "state": current.value, "action": action.value},
        ) from None
