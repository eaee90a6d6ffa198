"""Descriptor documents: the YAML a publisher writes, validated against a JSON Schema.

A descriptor file is flat, for people to write::

    kind: code                      # neural | code | prompt
    description: Move the open gripper above the object.
    applicability: {text: object on table, all: [{signal: object_height, op: "<", value: 0.05}]}
    termination:   {text: above object,    all: [{signal: eef_object_xy_dist, op: "<", value: 0.01}]}
    interface:
      inputs:  [{name: eef_pos, shape: [3], dtype: float32, units: m}]
      outputs: [{name: action, shape: [7], dtype: float32, low: -1, high: 1}]
    media_type: text/x-python       # optional, defaults by kind
    parent: 0                       # optional
    origin: manual                  # optional
    provenance: {learner_id: sac-1, config_hash: ab12, traces: [runs/1.mcap]}

Invariants:
1. ``parse_publish_spec(dump_publish_spec(s)) == s`` for every valid spec ``s``.
2. Every rejection is an :class:`Invalid` whose message starts with the dotted path of the
   offending field (``interface.inputs[0].shape``) and whose ``details["field"]`` is that path.
3. Parsing never raises anything but :class:`Invalid` for any input text.
4. Integers are JSON integers: ``parent: 1.0`` or ``shape: [3.0]`` is refused, as is any
   string holding a lone UTF-16 surrogate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import jsonschema
import yaml

from capevo.errors import Invalid
from capevo.records import (
    COMPARISON_OPS,
    Descriptor,
    Interface,
    Kind,
    Origin,
    Predicate,
    Provenance,
    PublishSpec,
)
from capevo.records.text import check_unicode

MAX_DESCRIPTOR_BYTES = 256 * 1024

_NUMBER = {"type": "number"}
_PREDICATE = {
    "type": "object",
    "additionalProperties": False,
    "properties": {
        "text": {"type": "string", "maxLength": 4096},
        "all": {
            "type": "array",
            "maxItems": 64,
            "items": {
                "type": "object",
                "additionalProperties": False,
                "required": ["signal", "op", "value"],
                "properties": {
                    "signal": {"type": "string", "pattern": r"^[A-Za-z_][A-Za-z0-9_]{0,63}$"},
                    "op": {"enum": list(COMPARISON_OPS)},
                    "value": _NUMBER,
                },
            },
        },
    },
}
_IOSPEC = {
    "type": "object",
    "additionalProperties": False,
    "required": ["name", "shape"],
    "properties": {
        "name": {"type": "string", "pattern": r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$"},
        "shape": {"type": "array", "maxItems": 8, "items": {"type": "integer", "minimum": 1, "maximum": 1_000_000}},
        "dtype": {"enum": ["float32", "float64", "int32", "int64", "bool", "uint8"]},
        "low": {"type": ["number", "null"]},
        "high": {"type": ["number", "null"]},
        "units": {"type": ["string", "null"], "maxLength": 32},
    },
}
SCHEMA: Mapping[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "additionalProperties": False,
    "required": ["kind", "description"],
    "properties": {
        "kind": {"enum": [k.value for k in Kind]},
        "description": {"type": "string", "minLength": 1, "maxLength": 8192},
        "applicability": _PREDICATE,
        "termination": _PREDICATE,
        "interface": {
            "type": "object",
            "additionalProperties": False,
            "properties": {
                "inputs": {"type": "array", "maxItems": 64, "items": _IOSPEC},
                "outputs": {"type": "array", "maxItems": 64, "items": _IOSPEC},
            },
        },
        "media_type": {"type": ["string", "null"], "pattern": r"^[\w.+-]+/[\w.+-]+$", "maxLength": 128},
        # Versions are SQLite INTEGERs (int64): a larger parent is no version, not an internal error.
        "parent": {"type": ["integer", "null"], "minimum": 0, "maximum": 2**63 - 1},
        "origin": {"enum": [o.value for o in Origin]},
        "provenance": {
            "type": ["object", "null"],
            "additionalProperties": False,
            "properties": {
                "learner_id": {"type": ["string", "null"], "maxLength": 256},
                "config_hash": {"type": ["string", "null"], "maxLength": 256},
                "traces": {"type": "array", "maxItems": 10_000, "items": {"type": "string", "maxLength": 1024}},
            },
        },
    },
}
# JSON Schema counts 1.0 as an integer; a version or a shape written 1.0 is not canonical and is
# refused like a key chunk "01" (see capevo.registry.keys), never silently truncated.
_STRICT_TYPES = jsonschema.Draft202012Validator.TYPE_CHECKER.redefine(
    "integer", lambda _checker, value: isinstance(value, int) and not isinstance(value, bool)
)
_VALIDATOR = jsonschema.validators.extend(jsonschema.Draft202012Validator, type_checker=_STRICT_TYPES)(SCHEMA)


def _path(parts: Any) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<document>"


def validate_document(doc: object) -> dict[str, Any]:
    """Check a parsed descriptor document against :data:`SCHEMA` and the rules it cannot say.

    Raises:
        Invalid: whose message starts with the offending field's dotted path.
    """
    if not isinstance(doc, dict):
        raise Invalid("<document>: a descriptor must be a mapping", details={"field": "<document>"})
    for key, value in doc.items():
        check_unicode(value, str(key) if isinstance(key, str) else "<key>")
    errors = sorted(_VALIDATOR.iter_errors(doc), key=lambda e: (len(e.absolute_path), list(map(str, e.absolute_path))))
    if errors:
        err = jsonschema.exceptions.best_match(errors) or errors[0]
        field = _path(err.absolute_path)
        raise Invalid(f"{field}: {err.message}", details={"field": field})
    _check_numbers(doc)
    for side in ("inputs", "outputs"):
        specs = (doc.get("interface") or {}).get(side, [])
        seen: set[str] = set()
        for i, spec in enumerate(specs):
            field = f"interface.{side}[{i}]"
            if spec["name"] in seen:
                raise Invalid(f"{field}.name: duplicate name {spec['name']!r}", details={"field": f"{field}.name"})
            seen.add(spec["name"])
            low, high = spec.get("low"), spec.get("high")
            if low is not None and high is not None and low > high:
                raise Invalid(f"{field}: low {low} is above high {high}", details={"field": field})
    return doc


def _check_numbers(value: Any, path: tuple[Any, ...] = ()) -> None:
    # JSON Schema accepts NaN and inf as numbers; a bound or threshold never may be one.
    if isinstance(value, float) and not math.isfinite(value):
        field = _path(path)
        raise Invalid(f"{field}: must be a finite number, got {value}", details={"field": field})
    if isinstance(value, dict):
        for k, v in value.items():
            _check_numbers(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _check_numbers(v, (*path, i))


def spec_from_document(doc: object) -> PublishSpec:
    """Validate a parsed document and build the :class:`PublishSpec` it describes."""
    d = validate_document(doc)
    return PublishSpec(
        kind=Kind(d["kind"]),
        descriptor=Descriptor(
            description=d["description"],
            applicability=Predicate.from_dict(d.get("applicability") or {}),
            termination=Predicate.from_dict(d.get("termination") or {}),
        ),
        interface=Interface.from_dict(d.get("interface") or {}),
        media_type=d.get("media_type"),
        parent=d.get("parent"),
        origin=Origin(d.get("origin", Origin.MANUAL.value)),
        provenance=Provenance.from_dict(d.get("provenance")),
    )


def spec_to_document(spec: PublishSpec) -> dict[str, Any]:
    """The flat document for ``spec``; the inverse of :func:`spec_from_document`."""
    wire = spec.to_dict()
    doc: dict[str, Any] = {"kind": wire["kind"], **wire["descriptor"], "interface": wire["interface"]}
    for key in ("media_type", "parent"):
        if wire[key] is not None:
            doc[key] = wire[key]
    doc["origin"] = wire["origin"]
    doc["provenance"] = wire["provenance"]
    return doc


def parse_publish_spec(text: str | bytes) -> PublishSpec:
    """Parse descriptor YAML (JSON is YAML too) into a validated :class:`PublishSpec`.

    Raises:
        Invalid: on oversize input, YAML syntax errors, or any schema violation.
    """
    if len(text) > MAX_DESCRIPTOR_BYTES:
        raise Invalid(f"<document>: descriptor is {len(text)} bytes; the limit is {MAX_DESCRIPTOR_BYTES}")
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise Invalid(f"<document>: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    except (ValueError, RecursionError) as exc:
        raise Invalid(f"<document>: not valid YAML: {exc}") from None
    return spec_from_document(doc)


def dump_publish_spec(spec: PublishSpec) -> str:
    """YAML text for ``spec`` that :func:`parse_publish_spec` reads back to an equal spec."""
    return yaml.safe_dump(spec_to_document(spec), sort_keys=False)
