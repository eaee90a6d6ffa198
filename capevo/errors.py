"""One exception tree for capevo, with stable machine-readable codes.

Every error a user can see is a :class:`CapevoError` carrying an :class:`ErrorCode`.
The code survives a trip over Zenoh: :meth:`CapevoError.to_payload` encodes it into an
error reply and :func:`error_from_payload` rebuilds the same subclass on the client.

Tree::

    CapevoError
    ├── NotFound            not_found
    ├── Conflict            conflict          (lost compare-and-swap, duplicate, illegal move)
    │   └── IllegalTransition illegal_transition
    ├── Invalid             invalid           (bad name, descriptor, request payload)
    ├── Forbidden           forbidden         (access control refused the request)
    ├── Corrupt             corrupt           (blob hash or audit chain mismatch)
    ├── Timeout             timeout
    ├── Unavailable         unavailable       (registry not reachable)
    ├── TooLarge            too_large
    ├── SafetyViolation     safety_violation  (governance rejected an action)
    ├── SandboxViolation    sandbox_violation (untrusted code broke the sandbox rules)
    └── IdentityViolation   identity_violation (the persistent agent changed)
"""

from __future__ import annotations

import enum
import json
from collections.abc import Sequence
from typing import Any


class ErrorCode(str, enum.Enum):
    """Stable codes; never renumber or rename, clients match on them."""

    INTERNAL = "internal"
    NOT_FOUND = "not_found"
    CONFLICT = "conflict"
    ILLEGAL_TRANSITION = "illegal_transition"
    INVALID = "invalid"
    FORBIDDEN = "forbidden"
    CORRUPT = "corrupt"
    TIMEOUT = "timeout"
    UNAVAILABLE = "unavailable"
    TOO_LARGE = "too_large"
    SAFETY_VIOLATION = "safety_violation"
    SANDBOX_VIOLATION = "sandbox_violation"
    IDENTITY_VIOLATION = "identity_violation"


class CapevoError(Exception):
    """Root of every capevo error.

    Args:
        message: Human-readable explanation; names the offending field or key.
        details: Optional JSON-able context (field path, expected value, ...).
    """

    code: ErrorCode = ErrorCode.INTERNAL

    def __init__(self, message: str, *, details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.details = details or {}

    def __str__(self) -> str:
        return f"[{self.code.value}] {self.message}"

    def to_dict(self) -> dict[str, Any]:
        return {"error": {"code": self.code.value, "message": self.message, "details": self.details}}

    def to_payload(self) -> bytes:
        """Encode for a Zenoh error reply."""
        return json.dumps(self.to_dict()).encode()


class NotFound(CapevoError):
    code = ErrorCode.NOT_FOUND


class Conflict(CapevoError):
    code = ErrorCode.CONFLICT


class IllegalTransition(Conflict):
    code = ErrorCode.ILLEGAL_TRANSITION


class Invalid(CapevoError):
    code = ErrorCode.INVALID


class Forbidden(CapevoError):
    code = ErrorCode.FORBIDDEN


class Corrupt(CapevoError):
    code = ErrorCode.CORRUPT


class Timeout(CapevoError):
    code = ErrorCode.TIMEOUT


class Unavailable(CapevoError):
    code = ErrorCode.UNAVAILABLE


class TooLarge(CapevoError):
    code = ErrorCode.TOO_LARGE


class SafetyViolation(CapevoError):
    code = ErrorCode.SAFETY_VIOLATION


class SandboxViolation(CapevoError):
    code = ErrorCode.SANDBOX_VIOLATION


class IdentityViolation(CapevoError):
    code = ErrorCode.IDENTITY_VIOLATION


_BY_CODE: dict[ErrorCode, type[CapevoError]] = {
    cls.code: cls
    for cls in (
        CapevoError,
        NotFound,
        Conflict,
        IllegalTransition,
        Invalid,
        Forbidden,
        Corrupt,
        Timeout,
        Unavailable,
        TooLarge,
        SafetyViolation,
        SandboxViolation,
        IdentityViolation,
    )
}


def check_choice(value: object, valid: Sequence[str], *, what: str, field: str) -> str:
    """``value`` if it is one of ``valid``.

    Raises:
        Invalid: anything else, naming ``what`` and listing the valid values (details ``field``).
    """
    if not isinstance(value, str) or value not in valid:
        raise Invalid(f"unknown {what} {value!r}; valid: {', '.join(valid)}", details={"field": field})
    return value


def error_class(code: ErrorCode | str) -> type[CapevoError]:
    """The exception class for a code; unknown codes map to the root class."""
    try:
        return _BY_CODE[ErrorCode(code)]
    except ValueError:
        return CapevoError


def error_from_payload(payload: bytes | str) -> CapevoError:
    """Rebuild the error a remote side encoded with :meth:`CapevoError.to_payload`.

    A payload that is not our error envelope becomes a plain :class:`CapevoError`
    holding the raw text, so a foreign error reply is never lost.
    """
    text = payload.decode(errors="replace") if isinstance(payload, bytes) else payload
    try:
        body = json.loads(text)["error"]
        cls = error_class(body["code"])
        err = cls(str(body["message"]), details=dict(body.get("details") or {}))
        if cls is CapevoError and body["code"] != ErrorCode.INTERNAL.value:
            err.details.setdefault("remote_code", body["code"])
        return err
    except (ValueError, KeyError, TypeError):
        return CapevoError(f"unrecognised error reply: {text[:500]}")
