"""Request and reply encoding of the registry's Zenoh protocol.

Wire format (all JSON is UTF-8, compact, no NaN/Infinity):

* Read replies: JSON of the record (``to_dict()``), encoding ``application/json``; the list
  endpoints reply with a JSON array. Artifact replies carry the raw bytes (encoding
  ``application/octet-stream``) and a JSON attachment ``{name, version, sha256, size,
  media_type}`` so the client can check the bytes and learn which version "active" was.
* Commands: a query on ``<ns>/cmd/<op>/@<user>`` (secured registry; ``<ns>/cmd/<op>`` when
  open, see :mod:`capevo.registry.keys`). For ``publish`` the query *attachment* is the JSON
  header ``{"name", "spec": PublishSpec.to_dict(), "actor"}`` and the query *payload* is the
  artifact bytes. An artifact may instead come in parts, one ``publish`` query each, whose
  headers add ``"part": {"upload", "offset", "total"}`` (:class:`UploadPart`); only the first
  part's header carries the ``spec`` (checking it is most of a part's cost), the last part's
  reply is the version, the others' ``{"upload", "received"}`` (:mod:`capevo.registry.uploads`).
  For every other op the payload is one JSON object (fields in :data:`COMMAND_FIELDS`).
  Unknown fields are refused.
* Success reply: the record after the change (EcmVersion JSON). Failure: ``reply_err``
  whose payload is :meth:`capevo.errors.CapevoError.to_payload`, rebuilt on the client by
  :func:`capevo.errors.error_from_payload`.
* Events on ``<ns>/events/<name>``: ``{"event": AuditEvent, "record": EcmVersion}``.

Invariants:
1. ``decode_command(op, encode_command(op, **f)) == f`` for valid fields ``f`` (with the
   spec as a :class:`PublishSpec`); the client and the server run the same field checks.
2. Decoding untrusted bytes raises only :class:`Invalid` or :class:`TooLarge`, for any input;
   a decoded document holds no lone UTF-16 surrogate.
3. ``decode_event(encode_event(e, r)) == (e, r)``; reply decoders raise only
   :class:`CapevoError` (a malformed reply is the registry's fault, code ``internal``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from capevo.errors import CapevoError, Invalid, TooLarge
from capevo.records import AuditEvent, EcmVersion, PublishSpec
from capevo.records.names import validate_name, validate_version
from capevo.records.text import check_unicode
from capevo.registry.descriptor import spec_from_document
from capevo.storage.sqlite import MAX_ACTOR_CHARS, MAX_REASON_CHARS, normalize_evidence, validate_text

MAX_VERSION = 2**63 - 1
JSON_ENCODING = "application/json"
OCTETS_ENCODING = "application/octet-stream"
# Command bodies and publish headers; a descriptor alone may be 256 KiB.
MAX_JSON_BYTES = 4 * 1024 * 1024

T = TypeVar("T")


def dumps(value: Any) -> bytes:
    """Compact JSON bytes; refuses NaN and infinities (JSON has no spelling for them)."""
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text} is out of range")
    return value


def loads(data: bytes | None, *, what: str, limit: int = MAX_JSON_BYTES) -> Any:
    """Parse untrusted JSON bytes.

    Args:
        data: The bytes; None means an empty request.
        what: Names the document in error messages ("promote request", ...).
        limit: Largest accepted size in bytes.

    Raises:
        TooLarge: more than ``limit`` bytes.
        Invalid: empty, not UTF-8, not JSON, NaN/Infinity, nested too deep, or a string
            holding a lone surrogate (JSON's ``"\\ud800"`` escape), naming its field.
    """
    if not data:
        raise Invalid(f"{what}: empty body; expected a JSON document", details={"field": "<body>"})
    if len(data) > limit:
        raise TooLarge(f"{what}: {len(data)} bytes; the limit is {limit}", details={"size": len(data), "limit": limit})
    try:
        doc = json.loads(data.decode("utf-8"), parse_constant=_refuse_constant, parse_float=_finite_float)
    except UnicodeDecodeError as exc:
        raise Invalid(f"{what}: not UTF-8 ({exc.reason} at byte {exc.start})", details={"field": "<body>"}) from None
    except (ValueError, RecursionError) as exc:
        raise Invalid(f"{what}: not valid JSON: {str(exc)[:200]}", details={"field": "<body>"}) from None
    if isinstance(doc, dict):
        for key, value in doc.items():
            check_unicode(key, "<key>")
            check_unicode(value, key)
    else:
        check_unicode(doc, "<body>")
    return doc


# --- field checks shared by client and server ---------------------------------------------


def _name(value: object) -> str:
    return validate_name(value)


def _version(value: object, field: str = "version") -> int:
    version = validate_version(value)
    # SQLite integers are signed 64-bit; a bigger number can name no version.
    if version > MAX_VERSION:
        raise Invalid(f"{field} must be at most {MAX_VERSION}, got {version}", details={"field": field})
    return version


def _optional_version(value: object) -> int | None:
    return None if value is None else _version(value)


def _reason(value: object) -> str:
    return validate_text(value, "reason", MAX_REASON_CHARS)


@dataclass(frozen=True, slots=True)
class UploadPart:
    """Where one part of an artifact sent in parts goes: bytes ``offset`` onwards of the
    ``total`` the upload ``upload`` (32 lowercase hex digits, the client's random id) carries."""

    upload: str
    offset: int
    total: int

    @property
    def first(self) -> bool:
        return self.offset == 0

    def to_dict(self) -> dict[str, Any]:
        return {"upload": self.upload, "offset": self.offset, "total": self.total}


UPLOAD_ID_CHARS = 32
_HEX = frozenset("0123456789abcdef")


def _count(value: object, field: str, *, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not least <= value <= MAX_VERSION:
        raise Invalid(
            f"{field} must be an integer from {least} to {MAX_VERSION}, got {value!r:.40}", details={"field": field}
        )
    return value


def _part(value: object) -> UploadPart | None:
    if value is None:
        return None
    if isinstance(value, UploadPart):
        value = value.to_dict()
    if not isinstance(value, dict):
        raise Invalid("part: must be a JSON object {upload, offset, total}", details={"field": "part"})
    unknown = sorted(set(value) - {"upload", "offset", "total"})
    missing = sorted({"upload", "offset", "total"} - set(value))
    if unknown or missing:
        field = f"part.{(unknown or missing)[0]}"
        raise Invalid(f"{field}: {'unknown' if unknown else 'missing'} field", details={"field": field})
    upload = value["upload"]
    if not isinstance(upload, str) or len(upload) != UPLOAD_ID_CHARS or not set(upload) <= _HEX:
        raise Invalid(
            f"part.upload must be {UPLOAD_ID_CHARS} lowercase hex digits, got {upload!r:.40}",
            details={"field": "part.upload"},
        )
    total = _count(value["total"], "part.total", least=1)
    offset = _count(value["offset"], "part.offset", least=0)
    if offset >= total:
        raise Invalid(f"part.offset {offset} is not below part.total {total}", details={"field": "part.offset"})
    return UploadPart(upload, offset, total)


def validate_actor(value: object) -> str | None:
    """None, or 1-256 characters naming who asked (recorded in the audit log)."""
    return None if value is None else validate_text(value, "actor", MAX_ACTOR_CHARS, allow_empty=False)


def _evidence(value: object) -> dict[str, Any]:
    # The store's own check, so a remote caller gets the same field-path messages as a local one.
    return normalize_evidence(value)


_SPEC_FIELDS = frozenset({"kind", "descriptor", "interface", "media_type", "parent", "origin", "provenance"})
_DESCRIPTOR_FIELDS = frozenset({"description", "applicability", "termination"})


def spec_from_wire(value: object) -> PublishSpec:
    """Validate ``PublishSpec.to_dict()`` output from an untrusted peer and rebuild the spec.

    The nested wire form is flattened into a descriptor document and checked by
    :func:`capevo.registry.descriptor.spec_from_document`, the same JSON Schema as descriptor files.

    Raises:
        Invalid: whose message starts with ``spec`` and the offending field's path.
    """
    if not isinstance(value, dict):
        raise Invalid(f"spec: must be a JSON object, got {type(value).__name__}", details={"field": "spec"})
    unknown = sorted(set(value) - _SPEC_FIELDS)
    if unknown:
        raise Invalid(f"spec.{unknown[0]}: unknown field", details={"field": f"spec.{unknown[0]}"})
    descriptor = value.get("descriptor")
    if not isinstance(descriptor, dict):
        raise Invalid("spec.descriptor: must be a JSON object", details={"field": "spec.descriptor"})
    unknown = sorted(set(descriptor) - _DESCRIPTOR_FIELDS)
    if unknown:
        field = f"spec.descriptor.{unknown[0]}"
        raise Invalid(f"{field}: unknown field", details={"field": field})
    doc = {k: v for k, v in value.items() if k != "descriptor"}
    doc.update(descriptor)
    try:
        return spec_from_document(doc)
    except Invalid as exc:
        field = exc.details.get("field", "<document>")
        raise Invalid(f"spec: {exc.message}", details={"field": f"spec.{field}"}) from None


def _optional_spec(value: object) -> PublishSpec | None:
    return None if value is None else spec_from_wire(value)


@dataclass(frozen=True, slots=True)
class _Field:
    check: Callable[[Any], Any]
    required: bool = True
    default: Any = None


_ACTOR = _Field(validate_actor, required=False)
_REASON = _Field(_reason, required=False, default="")

COMMAND_FIELDS: Mapping[str, Mapping[str, _Field]] = {
    "publish": {
        "name": _Field(_name),
        "spec": _Field(_optional_spec, required=False),  # see _check_publish
        "actor": _ACTOR,
        "part": _Field(_part, required=False),
    },
    "promote": {
        "name": _Field(_name),
        "version": _Field(_version),
        "expected_active": _Field(_optional_version, required=False),
        "reason": _REASON,
        "actor": _ACTOR,
    },
    "rollback": {
        "name": _Field(_name),
        "to": _Field(_optional_version, required=False),
        "expected_active": _Field(_optional_version, required=False),
        "reason": _REASON,
        "actor": _ACTOR,
    },
    "deprecate": {"name": _Field(_name), "version": _Field(_version), "reason": _REASON, "actor": _ACTOR},
    "reject": {"name": _Field(_name), "version": _Field(_version), "reason": _REASON, "actor": _ACTOR},
    "gate": {
        "name": _Field(_name),
        "version": _Field(_version),
        "evidence": _Field(_evidence),
        "reason": _REASON,
        "actor": _ACTOR,
    },
}


def check_command(op: str, body: object) -> dict[str, Any]:
    """Validate a decoded command body: known op, object, no unknown or missing fields.

    Returns:
        The checked fields, defaults filled in (``spec`` as a :class:`PublishSpec`).

    Raises:
        Invalid: naming the field.
    """
    fields = COMMAND_FIELDS.get(op)
    if fields is None:
        raise Invalid(f"unknown command {op!r}; valid commands: {', '.join(COMMAND_FIELDS)}", details={"field": "op"})
    if not isinstance(body, dict):
        raise Invalid(f"{op} request must be a JSON object, got {type(body).__name__}", details={"field": "<body>"})
    unknown = sorted(set(body) - set(fields))
    if unknown:
        raise Invalid(
            f"{op} request: unknown field {unknown[0]!r}; fields are {', '.join(fields)}", details={"field": unknown[0]}
        )
    out: dict[str, Any] = {}
    for key, field in fields.items():
        if key in body:
            out[key] = field.check(body[key])
        elif field.required:
            raise Invalid(f"{op} request: missing field {key!r}", details={"field": key})
        else:
            out[key] = field.default
    if op == "publish":
        _check_publish(out)
    return out


def _check_publish(fields: Mapping[str, Any]) -> None:
    """A publish carries its spec in its one payload's header or its first part's, and only there."""
    part = fields["part"]
    first = part is None or part.first
    if first and fields["spec"] is None:
        raise Invalid("publish request: missing field 'spec'", details={"field": "spec"})
    if not first and fields["spec"] is not None:
        raise Invalid(
            "publish request: 'spec' goes in the first part's header only (part.offset 0)", details={"field": "spec"}
        )


def encode_command(op: str, **fields: Any) -> bytes:
    """The JSON body (for publish: the attachment header) of a command.

    Raises:
        Invalid: the same checks the server runs, so a bad request fails before it is sent.
    """
    wire = {k: (v.to_dict() if isinstance(v, (PublishSpec, UploadPart)) else v) for k, v in fields.items()}
    check_command(op, wire)
    try:
        return dumps(wire)
    except (TypeError, ValueError) as exc:
        raise Invalid(f"{op} request is not JSON-able: {exc}") from None


def decode_command(op: str, data: bytes | None) -> dict[str, Any]:
    """Parse and check an untrusted command body (publish: its attachment header).

    Raises:
        Invalid, TooLarge: see :func:`loads` and :func:`check_command`.
    """
    what = f"{op} header (query attachment)" if op == "publish" else f"{op} request"
    return check_command(op, loads(data, what=what))


# --- query parameters ----------------------------------------------------------------------


def read_parameters(endpoint: str, pairs: Iterable[tuple[str, str]]) -> dict[str, int]:
    """Check selector parameters of a read query: only ``set`` takes one, ``revision``.

    Names starting with ``_`` are Zenoh's own (``_anyke``, ``_time``) and are ignored.

    Raises:
        Invalid: unknown or repeated parameter, or a revision that is not a canonical integer.
    """
    out: dict[str, int] = {}
    for key, value in pairs:
        if key.startswith("_"):
            continue
        if endpoint != "set" or key != "revision":
            allowed = "revision" if endpoint == "set" else "none"
            raise Invalid(f"unknown parameter {key!r} (allowed: {allowed})", details={"field": key})
        if key in out:
            raise Invalid(f"parameter {key!r} given twice", details={"field": key})
        if not (value.isascii() and value.isdigit()) or len(value) > 18 or str(int(value)) != value:
            raise Invalid(f"revision must be a non-negative integer, got {value[:40]!r}", details={"field": key})
        out[key] = int(value)
    return out


# --- replies and events --------------------------------------------------------------------


def decode_reply(data: bytes, build: Callable[[Any], T], *, what: str) -> T:
    """Parse a success reply from the registry with ``build`` (e.g. ``EcmVersion.from_dict``).

    Raises:
        CapevoError: code ``internal`` when the reply is not what the protocol promises.
    """
    try:
        return build(json.loads(data.decode("utf-8")))
    except (UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
        raise CapevoError(f"malformed {what} reply from the registry: {exc!r}"[:500]) from None


def list_of(build: Callable[[Any], T]) -> Callable[[Any], list[T]]:
    """A builder for a JSON array of records."""

    def build_list(value: Any) -> list[T]:
        if not isinstance(value, list):
            raise TypeError(f"expected a JSON array, got {type(value).__name__}")
        return [build(item) for item in value]

    return build_list


def encode_event(event: AuditEvent, record: EcmVersion) -> bytes:
    return dumps({"event": event.to_dict(), "record": record.to_dict()})


def decode_event(data: bytes) -> tuple[AuditEvent, EcmVersion]:
    """Raises CapevoError (code internal) for a malformed event."""
    return decode_reply(
        data, lambda d: (AuditEvent.from_dict(d["event"]), EcmVersion.from_dict(d["record"])), what="event"
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class ArtifactMeta:
    """The attachment of an artifact reply: which version these bytes are and their hash."""

    name: str
    version: int
    sha256: str
    size: int
    media_type: str

    @classmethod
    def of(cls, record: EcmVersion) -> ArtifactMeta:
        ref = record.artifact
        return cls(
            name=record.name, version=record.version, sha256=ref.sha256, size=ref.size, media_type=ref.media_type
        )

    def encode(self) -> bytes:
        return dumps(
            {
                "name": self.name,
                "version": self.version,
                "sha256": self.sha256,
                "size": self.size,
                "media_type": self.media_type,
            }
        )

    @classmethod
    def decode(cls, data: bytes) -> ArtifactMeta:
        """Raises CapevoError (code internal) for a malformed attachment."""
        return decode_reply(
            data,
            lambda d: cls(
                name=str(d["name"]),
                version=int(d["version"]),
                sha256=str(d["sha256"]),
                size=int(d["size"]),
                media_type=str(d["media_type"]),
            ),
            what="artifact attachment",
        )
