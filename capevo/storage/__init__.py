"""Persistent storage: the metadata store (SQLite) and the content-addressed blob store.

Names are resolved lazily so that importing :mod:`capevo.storage` never drags
:mod:`capevo.registry` into a half-initialised import cycle.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from capevo._lazy import lazy_getattr

if TYPE_CHECKING:
    from capevo.storage.abstract import AbstractStore
    from capevo.storage.blobs import BlobStore
    from capevo.storage.sqlite import SqliteStore

__all__ = ["AbstractStore", "BlobStore", "SqliteStore"]

_HOMES = {
    "AbstractStore": "capevo.storage.abstract",
    "BlobStore": "capevo.storage.blobs",
    "SqliteStore": "capevo.storage.sqlite",
}


__getattr__ = lazy_getattr(__name__, _HOMES)
