"""Text the registry stores must be real Unicode: no lone UTF-16 surrogates.

JSON's ``"\\ud800"`` escape and Python strings can both hold a lone surrogate, which no
UTF-8 encoder accepts. Let one through and it fails deep inside the JSON writer or SQLite
(an ``internal`` error, after the artifact blob was already written), so every boundary
refuses it up front as :class:`Invalid`, naming the field.

Invariants:
1. :func:`check_unicode` raises :class:`Invalid` exactly when some string or mapping key
   inside ``value`` cannot be encoded as UTF-8, and its ``details["field"]`` is the path to
   the first such string; otherwise it returns ``value`` unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar

from capevo.errors import Invalid

T = TypeVar("T")
# Deeper documents are refused elsewhere (JSON parsers, the descriptor schema); this only walks.
_MAX_DEPTH = 128


def _encodable(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _first_bad(value: Any, path: str, depth: int) -> str | None:
    if isinstance(value, str):
        return None if _encodable(value) else path
    if depth > _MAX_DEPTH:
        return None
    if isinstance(value, Mapping):
        for key, item in value.items():
            where = f"{path}.{key}" if isinstance(key, str) and _encodable(key) else f"{path}.<key>"
            if isinstance(key, str) and not _encodable(key):
                return where
            found = _first_bad(item, where, depth + 1)
            if found is not None:
                return found
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            found = _first_bad(item, f"{path}[{i}]", depth + 1)
            if found is not None:
                return found
    return None


def check_unicode(value: T, field: str) -> T:
    """Return ``value`` if every string and key in it is valid Unicode (encodable as UTF-8).

    Args:
        value: A string, or a JSON-like tree of mappings, lists and scalars.
        field: Its name, the start of the path in the error.

    Raises:
        Invalid: a lone surrogate such as ``"\\ud800"``; ``details["field"]`` is its path.
    """
    bad = _first_bad(value, field, 0)
    if bad is not None:
        raise Invalid(
            f"{bad}: not valid Unicode text (a lone UTF-16 surrogate such as \\ud800)", details={"field": bad}
        )
    return value
