"""Type-checking a plan: c_i ∘ c_j only when O(c_i) fits I(c_j).

A plan is a sequence of ECM versions, each feeding the next. For every consecutive pair
(producer ``c_i``, consumer ``c_j``), every input of ``c_j`` must be among the outputs of
``c_i`` with the same name, shape and dtype; when both specs give a bound, the producer's
range must lie inside the consumer's (``out.low >= in.low``, ``out.high <= in.high``).
Extra outputs of ``c_i`` are allowed.

Invariants:
1. :func:`check_composition` returns None for sequences shorter than two.
2. Every rejection is an :class:`Invalid` whose message names both ECMs (``name@version``),
   the input and the field (``missing``, ``shape``, ``dtype``, ``low`` or ``high``) with the
   expected and actual values; ``details`` carries the same as ``producer``, ``consumer``,
   ``position``, ``input``, ``field``, ``expected`` and ``got``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from capevo.errors import Invalid
from capevo.records import EcmVersion, IOSpec


def _label(v: EcmVersion) -> str:
    return f"{v.name}@{v.version}"


def _fail(
    producer: EcmVersion,
    consumer: EcmVersion,
    position: int,
    spec: IOSpec,
    field: str,
    expected: Any,
    got: Any,
    why: str,
) -> Invalid:
    return Invalid(
        f"plan step {position}: {_label(producer)} ∘ {_label(consumer)}: input {spec.name!r} of "
        f"{_label(consumer)}: {field} {why}: expected {expected!r}, got {got!r} from {_label(producer)}",
        details={
            "producer": _label(producer),
            "consumer": _label(consumer),
            "position": position,
            "input": spec.name,
            "field": field,
            "expected": expected,
            "got": got,
        },
    )


def check_pair(producer: EcmVersion, consumer: EcmVersion, *, position: int = 0) -> None:
    """Check that ``producer``'s outputs satisfy ``consumer``'s inputs.

    Args:
        producer: The ECM that runs first (``c_i``).
        consumer: The ECM fed by it (``c_j``).
        position: Index of ``producer`` in the plan, for messages.

    Raises:
        Invalid: the first mismatch found, in the consumer's input order.
    """
    outputs = {s.name: s for s in producer.interface.outputs}
    for want in consumer.interface.inputs:
        have = outputs.get(want.name)
        if have is None:
            raise _fail(
                producer, consumer, position, want, "missing", want.name, sorted(outputs), "is not among the outputs"
            )
        if tuple(have.shape) != tuple(want.shape):
            raise _fail(producer, consumer, position, want, "shape", list(want.shape), list(have.shape), "differs")
        if have.dtype != want.dtype:
            raise _fail(producer, consumer, position, want, "dtype", want.dtype, have.dtype, "differs")
        if want.low is not None and have.low is not None and have.low < want.low:
            raise _fail(producer, consumer, position, want, "low", want.low, have.low, "is below the accepted range")
        if want.high is not None and have.high is not None and have.high > want.high:
            raise _fail(producer, consumer, position, want, "high", want.high, have.high, "is above the accepted range")


def check_composition(ecms: Sequence[EcmVersion]) -> None:
    """Check a plan ``ecms[0] -> ecms[1] -> ...`` pair by pair.

    Raises:
        Invalid: the first incompatible pair, naming the ECMs, input and field.
    """
    for i in range(len(ecms) - 1):
        check_pair(ecms[i], ecms[i + 1], position=i)
