"""The registry server's hot reads, answered from memory and derived from SQLite (issue 21).

Resolving a version is the registry's most frequent job. The server keeps, for every ECM,
the reply bytes of each version and of ``active``, plus those of the ECM list and of the
current capability set. They are read from SQLite at start and brought up to date by
:meth:`ReadCache.current`, which the commit path calls after each commit is durable (the
cache is the registry's first :class:`~capevo.registry.local.EventListener`) and every
read calls before it answers.

Other processes may write the same root (``LocalRegistry`` directly, another server).
Each read first loads the store's commit word (:mod:`capevo.storage.commit_word`), which
every capevo writer moves after each commit and before acknowledging it. Only when the word
has moved since the last full check, or that check is ``recheck_s`` old, does it ask SQLite
for ``PRAGMA data_version`` on the cache's own connection (which changes whenever any other
connection has committed), and on a change read what the audit events since the cached
chain tip touched. The cache owns that connection, so neither the check nor the catch-up
waits for the registry's writes: in WAL mode a reader never waits for a writer. The word
saves the check's read transaction on nearly every resolve (issue 21; BENCHMARKS.md); the
timer bounds how long a write that bypasses capevo (the ``sqlite3`` shell) goes unseen.

Invariants:
1. :meth:`ReadCache.current` returns a snapshot that contains every commit that a capevo
   writer, of any process, had acknowledged when the call began; a commit made without
   capevo's store is in it at most ``recheck_s`` after it.
2. Each reply a snapshot holds is byte for byte what the SQLite read handlers in
   :mod:`capevo.registry.service` reply for the same state.
3. A snapshot answers only what it holds: a key it has no bytes for (unknown ECM or
   version, no active version, a past revision) gets None, and the SQLite path answers it,
   errors included.
4. Snapshots are immutable; a catch-up builds a new one and swaps it in whole.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from capevo.errors import Invalid
from capevo.records import AuditEvent, CapabilitySet, EcmSummary, EcmVersion
from capevo.registry.keys import Route
from capevo.registry.wire import dumps
from capevo.storage.sqlite import SqliteStore, StoreChanges

# How stale a write that bypasses capevo's store (which moves no commit word) may be served.
RECHECK_S = 1.0
# The read endpoints a snapshot answers; the rest (artifacts, history, verify, ...) read disk.
MEMORY_ENDPOINTS = frozenset({"version", "list", "set"})


@dataclass(frozen=True, slots=True, kw_only=True)
class ReadSnapshot:
    """The reply bytes of the hot reads as of one commit (audit chain tip ``seq``).

    Attributes:
        data_version: The cache connection's ``PRAGMA data_version`` when this was read.
        seq: The last audit event it includes.
        revision: The registry revision.
        versions: ``{name: {version: EcmVersion JSON}}`` of every version.
        active: ``{name: active version or None}``.
        summaries: ``{name: EcmSummary}``, the rows of the list.
        listing: Reply of ``<ns>/ecm``.
        capability_set: Reply of ``<ns>/set`` at ``revision``.
    """

    data_version: int
    seq: int
    revision: int
    versions: Mapping[str, Mapping[int, bytes]]
    active: Mapping[str, int | None]
    summaries: Mapping[str, EcmSummary]
    listing: bytes
    capability_set: bytes

    def reply(self, route: Route, params: Mapping[str, int]) -> bytes | None:
        """The reply bytes for ``route``, or None when this snapshot does not hold them (invariant 3)."""
        if route.endpoint == "version":
            name = str(route.name)
            version = self.active.get(name) if route.version is None else route.version
            return None if version is None else self.versions.get(name, {}).get(version)
        if route.endpoint == "list":
            return self.listing
        if route.endpoint == "set" and params.get("revision", self.revision) == self.revision:
            return self.capability_set
        return None


def _apply(snapshot: ReadSnapshot | None, changes: StoreChanges) -> ReadSnapshot:
    """``snapshot`` with ``changes`` applied (a full load when ``snapshot`` is None).

    Only the ECMs the changes name are copied and re-summarised; the others' mappings are
    shared with ``snapshot`` (they are immutable), so a catch-up costs what changed plus
    one encoding of the list and the capability set.
    """
    versions: dict[str, Mapping[int, bytes]] = {} if snapshot is None else dict(snapshot.versions)
    summaries: dict[str, EcmSummary] = {} if snapshot is None else dict(snapshot.summaries)
    active: dict[str, int | None] = {} if snapshot is None else dict(snapshot.active)
    active.update(changes.active)
    touched: dict[str, dict[int, bytes]] = {}
    for record in changes.versions:
        if record.name not in touched:
            touched[record.name] = dict(versions.get(record.name, {}))
        touched[record.name][record.version] = dumps(record.to_dict())
    for name in touched.keys() | changes.active.keys():
        held = touched.get(name) or versions.get(name, {})
        versions[name] = MappingProxyType(held)
        # The same records and encoding as the SQLite handlers' list_ecms and capability_set.
        summaries[name] = EcmSummary(
            name=name, active_version=active.get(name), latest_version=max(held), n_versions=len(held)
        )
    current = CapabilitySet(revision=changes.revision, active={n: a for n, a in active.items() if a is not None})
    return ReadSnapshot(
        data_version=changes.data_version,
        seq=changes.seq,
        revision=changes.revision,
        versions=MappingProxyType(versions),
        active=MappingProxyType(active),
        summaries=MappingProxyType(summaries),
        listing=dumps([summaries[n].to_dict() for n in sorted(summaries)]),
        capability_set=dumps(current.to_dict()),
    )


class ReadCache:
    """The hot reads of the registry at ``path``, in memory, on a connection of their own.

    Args:
        path: The registry's ``registry.sqlite3``.
        recheck_s: The longest time between two full checks while the commit word stays put.

    Raises:
        Unavailable, Corrupt, Timeout: the database cannot be opened or read.
        Invalid: ``recheck_s`` is negative or not finite.
    """

    def __init__(self, path: str | os.PathLike[str], *, recheck_s: float = RECHECK_S) -> None:
        if not math.isfinite(recheck_s) or recheck_s < 0:
            raise Invalid(f"recheck_s must be a finite number >= 0, got {recheck_s!r}", details={"field": "recheck_s"})
        self._recheck_s = float(recheck_s)
        self._store = SqliteStore(path)
        self._lock = threading.Lock()
        try:
            # Loaded before the read, as before every full check (commit_word's protocol).
            self._checked_word = self._store.commit_word()
            self._recheck_at = time.monotonic() + self._recheck_s
            self._snapshot = _apply(None, self._store.changes_since(0))
        except BaseException:
            self._store.close()
            raise

    def current(self) -> ReadSnapshot:
        """A snapshot holding every commit acknowledged before this call (invariant 1).

        Costs one load of the commit word while it stays put and the last full check is
        younger than ``recheck_s``; otherwise one ``PRAGMA data_version``, and after a change
        also a read of the versions the new audit events touched.

        Raises:
            CapevoError: the database cannot be read (the caller falls back to SQLite reads).
        """
        with self._lock:
            snapshot = self._snapshot
            word = self._store.commit_word()
            now = time.monotonic()
            if word == self._checked_word and now < self._recheck_at:
                return snapshot
            self._checked_word, self._recheck_at = word, now + self._recheck_s
            if self._store.data_version() != snapshot.data_version:
                changes = self._store.changes_since(snapshot.seq)
                # A chain shorter than the cached one is another database put in place: start over.
                self._snapshot = snapshot = (
                    _apply(None, self._store.changes_since(0))
                    if changes.seq < snapshot.seq
                    else _apply(snapshot, changes)
                )
            return snapshot

    def on_event(self, event: AuditEvent, record: EcmVersion) -> None:
        """:class:`~capevo.registry.local.EventListener`: after a commit of this process, catch up."""
        self.current()

    def close(self) -> None:
        """Close the cache's connection. Idempotent."""
        with self._lock:
            self._store.close()
