"""ECM name rules.

Invariants:
1. A valid name matches ``[a-z0-9][a-z0-9._-]{0,63}``: at most 64 characters, never a
   Zenoh wildcard (``*``, ``$*``), never ``/``, never ``.`` or ``..`` alone.
2. Names that collide with the key space's own words (``active``, ``history``) are refused
   as ECM names only where they would be ambiguous; see ``RESERVED``.
"""

from __future__ import annotations

import re

from capevo.errors import Invalid

NAME_PATTERN = re.compile(r"[a-z0-9][a-z0-9._-]{0,63}")
MAX_NAME_LENGTH = 64
RESERVED: frozenset[str] = frozenset({"active", "history", "set", "cmd", "events"})


def validate_name(name: object) -> str:
    """Return ``name`` if it is a valid ECM slug.

    Raises:
        Invalid: naming why (type, length, characters, reserved word).
    """
    if not isinstance(name, str):
        raise Invalid(f"ECM name must be a string, got {type(name).__name__}", details={"field": "name"})
    if len(name) > MAX_NAME_LENGTH:
        raise Invalid(f"ECM name is {len(name)} characters; the limit is {MAX_NAME_LENGTH}", details={"field": "name"})
    if not NAME_PATTERN.fullmatch(name) or ".." in name:
        raise Invalid(
            f"ECM name {name!r} is not a slug: use lowercase letters, digits, '.', '_' and '-', "
            "starting with a letter or digit, with no '..'",
            details={"field": "name"},
        )
    if name in RESERVED:
        raise Invalid(f"ECM name {name!r} is a reserved word", details={"field": "name"})
    return name


MAX_VERSION = 2**63 - 1
"""Largest version SQLite's INTEGER (and so any store) can hold."""


def validate_version(version: object) -> int:
    """Return ``version`` as an int if it is an integer in ``0..MAX_VERSION`` (bools refused)."""
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise Invalid(f"version must be a non-negative integer, got {version!r}", details={"field": "version"})
    if version > MAX_VERSION:
        raise Invalid(f"version must be at most {MAX_VERSION}, got {version}", details={"field": "version"})
    return version
