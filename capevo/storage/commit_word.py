"""An 8-byte word in shared memory that every capevo writer of a database moves after each commit.

Why it exists (issue 21): the registry server answers hot reads from memory, and must never
answer one that misses a commit another process has acknowledged. SQLite's ``PRAGMA
data_version`` tells exactly whether anything changed, but it opens a read transaction: on
2026-12-07 it was about 20 µs of the ~65 µs the server's answering thread spent per resolve,
and the Zenoh threads waiting on that thread spent more besides. Loading this word costs well
under a microsecond, so a reader asks SQLite only when the word has moved.

The word lives in ``<database>-commit``, next to SQLite's own ``-wal`` and ``-shm`` files, and is
mapped with :mod:`mmap` by every process that opens the database. Like SQLite's WAL index, it
needs the processes to share one host's page cache (a local filesystem).

Protocol:
1. A writer stores 8 fresh random bytes after its ``COMMIT`` returned (the commit is durable)
   and before it returns to its caller, so before anything about the commit is acknowledged.
2. A reader loads the word *before* each full check (``PRAGMA data_version`` and catch-up) and
   keeps it. While later loads return the same bytes, no commit was acknowledged since that
   check: every store writes bytes never seen before (a collision has probability 2⁻⁶⁴), so
   an unchanged word means the last store a reader sees is one it saw before its check.

Limits, and why readers still re-check on a timer (see
:class:`~capevo.registry.read_cache.ReadCache`): a process writing the file without
:class:`~capevo.storage.sqlite.SqliteStore` (the ``sqlite3`` shell) does not move the word,
and a writer killed between ``COMMIT`` and its store leaves a commit that was never
acknowledged unsignalled.
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path

from capevo.errors import Unavailable

WORD_BYTES = 8
SUFFIX = "-commit"


class CommitWord:
    """The mapped word of one database file.

    Args:
        database: The SQLite file; the word is ``<database>-commit``, created if missing.

    Raises:
        Unavailable: the word's file cannot be created, sized or mapped.
    """

    def __init__(self, database: str | os.PathLike[str]) -> None:
        self.path = Path(f"{os.fspath(database)}{SUFFIX}")
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise Unavailable(f"cannot open {self.path}: {exc}") from exc
        try:
            # Several processes may create it at once: growing a file to the size it already
            # has changes nothing, so the race is harmless.
            if os.fstat(fd).st_size < WORD_BYTES:
                os.ftruncate(fd, WORD_BYTES)
            self._map = mmap.mmap(fd, WORD_BYTES, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        except (OSError, ValueError) as exc:
            raise Unavailable(f"cannot map {self.path}: {exc}") from exc
        finally:
            os.close(fd)

    def load(self) -> bytes:
        """The word now.

        Raises:
            Unavailable: the word was closed.
        """
        try:
            return self._map[:WORD_BYTES]
        except ValueError:
            raise Unavailable(f"{self.path} is closed") from None

    def move(self) -> None:
        """Store fresh random bytes: call after each durable commit, before acknowledging it."""
        try:
            self._map[:WORD_BYTES] = os.urandom(WORD_BYTES)
        except ValueError:
            raise Unavailable(f"{self.path} is closed") from None

    def close(self) -> None:
        """Unmap the word. Idempotent."""
        self._map.close()
