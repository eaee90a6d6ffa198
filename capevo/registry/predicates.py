"""Evaluating descriptor predicates (applicability, termination) against task signals.

Invariants:
1. An empty predicate (no conditions) holds in every state.
2. A condition on a signal the task does not expose is an error (:class:`Invalid`), never
   silently false: a typo in a descriptor must not make an ECM run forever.
3. A NaN signal makes every comparison false except ``!=``, as IEEE 754 says.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Mapping

from capevo.errors import Invalid
from capevo.records import Condition, Predicate

_OPS: Mapping[str, Callable[[float, float], bool]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
    "==": operator.eq,
    "!=": operator.ne,
}


def condition_holds(condition: Condition, signals: Mapping[str, float]) -> bool:
    """Whether ``signal op value`` holds.

    Raises:
        Invalid: the signal is not among ``signals``, or the operator is unknown.
    """
    try:
        value = signals[condition.signal]
    except KeyError:
        raise Invalid(
            f"predicate uses signal {condition.signal!r}, which the task does not expose "
            f"(it has: {', '.join(sorted(signals))})",
            details={"field": "signal", "signal": condition.signal},
        ) from None
    try:
        return bool(_OPS[condition.op](float(value), condition.value))
    except KeyError:
        raise Invalid(f"unknown comparison operator {condition.op!r}", details={"field": "op"}) from None


def predicate_holds(predicate: Predicate, signals: Mapping[str, float]) -> bool:
    """Whether every condition of ``predicate`` holds (the empty conjunction is true)."""
    return all(condition_holds(c, signals) for c in predicate.all)


def missing_signals(predicate: Predicate, available: frozenset[str] | set[str]) -> list[str]:
    """Signals ``predicate`` names that ``available`` lacks: checked when a plan is built."""
    return sorted({c.signal for c in predicate.all} - set(available))
