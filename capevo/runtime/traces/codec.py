"""JSON payloads of trace records for MCAP ``json`` channels: one :func:`orjson.dumps` per record.

A payload is the record's ``to_dict()`` with its vectors as numpy arrays, which orjson prints in
one call:

- a float32 array (the env's observations, as the episode loop passes them) as its float32
  values, the shortest text that names each;
- any other vector (the runtime's own float64 actions, key state, outputs) as float64 values,
  exactly; records' ``from_dict`` rounds every vector to float32 on reading.

Scalars are checked against the record's schema before printing (an ``integer`` field must be an
integer, a ``string`` a str; ``number`` and ``boolean`` fields are converted with ``float`` and
``bool``), so a wrong type fails the write instead of landing in the file.

Invariants:
1. Every payload is strict JSON (RFC 8259): no ``NaN``/``Infinity`` tokens; a non-finite
   float becomes ``null`` (decoded as NaN).
2. ``decode(topic, encode(r)) == r`` for every record ``r`` with finite floats whose vectors
   hold float32 values; a float64 vector value comes back as the float32 nearest to it (beyond
   float32's range, as it was); scalar floats come back exactly.
3. A float32 array and the tuple of its values encode to payloads that decode to the same record.
4. A field that does not fit its schema's type (a string where an integer belongs, a vector
   component that is not a real number, a name that is not UTF-8) fails with :class:`Invalid`.
"""

from __future__ import annotations

import operator
from array import array
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import orjson

from capevo.errors import Corrupt, Invalid
from capevo.runtime.traces.records import TraceRecord, record_type, topics

_NUMPY = orjson.OPT_SERIALIZE_NUMPY


_FLOAT = frozenset((float,))


def vector(values: Any) -> np.ndarray | tuple[float, ...]:
    """A vector field as orjson prints it: a float32 array's own values, anything else as float64.

    A tuple of floats (the runtime's actions and key state) is printed as it is, which is the same
    text as its float64 array, without the conversion.

    Raises:
        TypeError: a component is not a real number (``array("d")`` takes exactly those).
    """
    if type(values) is np.ndarray and values.dtype == np.float32:
        return values.ravel()  # orjson prints only C-contiguous arrays; ravel copies only when it must
    if type(values) is tuple and set(map(type, values)) <= _FLOAT:
        return values
    return np.frombuffer(array("d", values), dtype=np.float64)


def _text(value: Any) -> str:
    if type(value) is not str:
        raise TypeError(f"expected a str, got {type(value).__name__}")
    return value


_CONVERSIONS: Mapping[str, Callable[[Any], Any]] = {
    "integer": operator.index,
    "string": _text,
    "number": float,
    "boolean": bool,
}


def _scalar_checks(schema: Mapping[str, Any]) -> tuple[tuple[str, Callable[[Any], Any], bool], ...]:
    """(field, conversion, None allowed) for each scalar property of ``schema``."""
    checks = []
    for name, prop in schema["properties"].items():
        kinds = prop["type"] if isinstance(prop["type"], list) else [prop["type"]]
        convert = _CONVERSIONS.get(kinds[0])
        if convert is not None:
            # A number's null stands for a non-finite value, never for None.
            checks.append((name, convert, "null" in kinds and kinds[0] != "number"))
    return tuple(checks)


_CHECKS = {topic: _scalar_checks(record_type(topic).SCHEMA) for topic in topics()}


def _not_encodable(record: object, exc: Exception) -> Invalid:
    return Invalid(
        f"{type(record).__name__} does not encode as JSON: {type(exc).__name__}: {exc}",
        details={"record": type(record).__name__},
    )


def encode(record: TraceRecord) -> bytes:
    """The JSON payload of a trace record.

    Raises:
        Invalid: a field does not fit its schema's type (invariant 4).
    """
    try:
        d = record.to_dict(vector=vector)
        for name, convert, nullable in _CHECKS[record.TOPIC]:
            value = d[name]
            if value is not None or not nullable:
                d[name] = convert(value)
        return orjson.dumps(d, option=_NUMPY)
    except (TypeError, ValueError, OverflowError) as exc:  # orjson.JSONEncodeError is a TypeError
        raise _not_encodable(record, exc) from None


def decode(topic: str, data: bytes | bytearray | memoryview) -> TraceRecord:
    """The record of ``topic`` that ``data`` encodes.

    Raises:
        Invalid: unknown topic.
        Corrupt: the payload is not JSON or lacks a field the record needs.
    """
    cls = record_type(topic)
    try:
        return cls.from_dict(orjson.loads(data))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise Corrupt(
            f"message on {topic} does not decode as {cls.__name__}: {type(exc).__name__}: {exc}",
            details={"topic": topic},
        ) from None
