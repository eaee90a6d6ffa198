"""Artifact bytes cached on the runtime's disk, keyed by their sha256.

A runtime worker pulls each ECM version's artifact from the registry once; afterwards it
loads from here, also while the registry is down. Layout of ``root``::

    root/ab/abcdef…        the bytes whose sha256 is ``abcdef…`` (first two hex digits shard)
    root/ab/.tmp-…         a write in progress (removed on failure; ignored on read)

Invariants:
1. :meth:`ArtifactCache.get` returns only bytes whose sha256 is the key; an entry that does
   not hash to its name is deleted and counted in ``stats["corrupt"]``, and the read is a miss.
2. :meth:`ArtifactCache.put` writes to a temporary file in the entry's directory, fsyncs it and
   renames it over the final name, so a crash never leaves a partial entry under a key.
3. :meth:`ArtifactCache.put` refuses bytes that do not hash to the key (:class:`Corrupt`), so
   nothing unverified enters the cache.
4. :meth:`ArtifactCache.fetch` calls its loader only on a miss and returns verified bytes or
   raises; the loader's errors propagate unchanged.
5. A key that is not 64 lowercase hex digits is refused with :class:`Invalid` before any path
   is built (no path traversal through a key).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Protocol, runtime_checkable

from capevo.errors import Corrupt, Invalid, Unavailable
from capevo.storage.blobs import SHA256_PATTERN, fsync_dir


def check_sha256(sha256: object) -> str:
    """Return ``sha256`` if it is 64 lowercase hex digits.

    Raises:
        Invalid: anything else.
    """
    if not isinstance(sha256, str) or not SHA256_PATTERN.fullmatch(sha256):
        raise Invalid(f"artifact key must be 64 lowercase hex digits, got {sha256!r}", details={"field": "sha256"})
    return sha256


def _verify(sha256: str, data: bytes) -> None:
    digest = hashlib.sha256(data).hexdigest()
    if digest != sha256:
        raise Corrupt(
            f"artifact bytes hash to {digest}, not to their key {sha256}",
            details={"expected": sha256, "got": digest},
        )


@runtime_checkable
class ArtifactStore(Protocol):
    """What the runtime needs of an artifact cache."""

    def get(self, sha256: str) -> bytes | None: ...

    def put(self, sha256: str, data: bytes) -> None: ...

    def fetch(self, sha256: str, load: Callable[[], bytes]) -> bytes: ...


def _read_through(store: ArtifactStore, sha256: str, load: Callable[[], bytes]) -> bytes:
    """``store.get(sha256)``, or on a miss ``load()``, stored with ``store.put`` (which verifies it)."""
    data = store.get(sha256)
    if data is None:
        data = load()
        store.put(sha256, data)
    return data


class ArtifactCache:
    """On-disk, content-addressed artifact cache; safe to share between processes.

    Args:
        root: Cache directory; created if missing.
        fsync: fsync each new entry and its directory (a power cut keeps it); renaming is
            atomic either way.

    Raises:
        Unavailable: ``root`` cannot be created.
    """

    def __init__(self, root: str | os.PathLike[str], *, fsync: bool = True) -> None:
        self.root = Path(root)
        self.fsync = fsync
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise Unavailable(f"cannot create artifact cache {self.root}: {exc.strerror or exc}") from None
        self._lock = threading.Lock()
        self.stats = {"hits": 0, "misses": 0, "corrupt": 0, "stored": 0}

    def path_for(self, sha256: str) -> Path:
        """Where the entry for ``sha256`` lives. Raises Invalid for a malformed key."""
        key = check_sha256(sha256)
        return self.root / key[:2] / key

    def _count(self, what: str) -> None:
        with self._lock:
            self.stats[what] += 1

    def __contains__(self, sha256: object) -> bool:
        return (
            isinstance(sha256, str) and SHA256_PATTERN.fullmatch(sha256) is not None and self.path_for(sha256).is_file()
        )

    def get(self, sha256: str) -> bytes | None:
        """The cached bytes of ``sha256``, verified; None on a miss (or a corrupt entry, deleted).

        Raises:
            Invalid: malformed key.
        """
        path = self.path_for(sha256)
        try:
            data = path.read_bytes()
        except OSError:  # missing or unreadable: either way a miss
            self._count("misses")
            return None
        try:
            _verify(sha256, data)
        except Corrupt:
            self._count("corrupt")
            with contextlib.suppress(OSError):
                path.unlink()
            self._count("misses")
            return None
        self._count("hits")
        return data

    def put(self, sha256: str, data: bytes) -> None:
        """Store ``data`` under ``sha256`` atomically (a no-op when the entry exists).

        Raises:
            Invalid: malformed key. Corrupt: ``data`` does not hash to ``sha256``.
            Unavailable: the file cannot be written.
        """
        path = self.path_for(sha256)
        _verify(sha256, data)
        if path.is_file():
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=path.parent)
        except OSError as exc:
            raise Unavailable(f"cannot write artifact cache entry {path}: {exc.strerror or exc}") from None
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                if self.fsync:
                    os.fsync(f.fileno())
            os.replace(tmp, path)
            if self.fsync:
                # The entry is in place already; a directory that cannot be fsynced only costs
                # durability across a power cut, so it does not fail the write.
                with contextlib.suppress(OSError):
                    fsync_dir(path.parent)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise Unavailable(f"cannot write artifact cache entry {path}: {exc.strerror or exc}") from None
        self._count("stored")

    def fetch(self, sha256: str, load: Callable[[], bytes]) -> bytes:
        """The bytes of ``sha256``: from the cache, or from ``load()`` (then verified and stored).

        Raises:
            Invalid: malformed key. Corrupt: ``load()`` returned other bytes.
            Whatever ``load`` raises (e.g. :class:`Unavailable` when the registry is down).
        """
        return _read_through(self, sha256, load)

    def __repr__(self) -> str:
        return f"ArtifactCache({str(self.root)!r})"


class MemoryArtifactCache:
    """In-memory :class:`ArtifactStore` with the same checks; for tests and one-shot runs."""

    def __init__(self) -> None:
        self._data: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self.stats = {"hits": 0, "misses": 0, "corrupt": 0, "stored": 0}

    def get(self, sha256: str) -> bytes | None:
        key = check_sha256(sha256)
        with self._lock:
            data = self._data.get(key)
            self.stats["hits" if data is not None else "misses"] += 1
        return data

    def put(self, sha256: str, data: bytes) -> None:
        key = check_sha256(sha256)
        _verify(key, data)
        with self._lock:
            if key not in self._data:
                self._data[key] = bytes(data)
                self.stats["stored"] += 1

    def fetch(self, sha256: str, load: Callable[[], bytes]) -> bytes:
        return _read_through(self, sha256, load)
