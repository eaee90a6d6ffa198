"""The embedded registry: :class:`Registry` over a directory on local disk.

Layout of ``root``::

    root/registry.sqlite3       metadata, pointers, pointer-move log, audit chain (WAL mode)
    root/registry.sqlite3-wal   SQLite's write-ahead log (present while open)
    root/registry.sqlite3-commit  8 bytes every writer changes after each commit (capevo.storage.commit_word)
    root/blobs/ab/cdef…         artifact bytes, named by their sha256

Invariants:
1. ``publish`` makes the artifact blob durable before the metadata transaction starts, so
   every version row names a blob that exists; a crash in between leaves at most an
   orphan blob, never a version without its bytes.
2. Every argument is validated (name, version, spec, artifact type and size, actor,
   reason) before anything is written.
3. Listeners run after the commit, one event at a time and in commit order (for the
   mutations made through this object); a listener that raises is logged and cannot undo
   or fail the mutation, nor stop the other listeners.
4. ``get_artifact`` returns only bytes whose sha256 matches the version's record.
5. ``verify`` reports every break of the audit chain, every disagreement between the
   stored state and a replay of the audit history, and every missing or corrupt blob; an
   intact registry yields no problems.
6. Opening a registry removes the temporary blob files of writers that no longer run (a
   publish killed mid-write), never a live writer's.
7. A mutation is recorded against ``actor``; an :class:`Attribution` (what the Zenoh service
   passes) also puts how the actor is known, and any ``on_behalf_of``, into the audit event.
"""

from __future__ import annotations

import getpass
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from capevo.errors import Corrupt, Invalid, NotFound, TooLarge, Unavailable
from capevo.records import (
    Action,
    ArtifactRef,
    Attribution,
    AuditEvent,
    CapabilitySet,
    EcmDetail,
    EcmSummary,
    EcmVersion,
    Mutation,
    PublishSpec,
    State,
    VerifyReport,
)
from capevo.records.audit import chain_problems
from capevo.records.names import validate_name, validate_version
from capevo.registry.descriptor import spec_to_document, validate_document

# Submodule imports (not names) keep this module importable while capevo.storage is
# itself still initialising, whichever side of the registry/storage pair loads first.
from capevo.storage import blobs as _blobs
from capevo.storage import sqlite as _sqlite

log = logging.getLogger(__name__)

DB_FILENAME = "registry.sqlite3"
BLOB_DIRNAME = "blobs"
DEFAULT_MAX_ARTIFACT_BYTES = 256 * 2**20
_VERIFY_ATTEMPTS = 5


@runtime_checkable
class EventListener(Protocol):
    """Told about each committed mutation (e.g. the Zenoh server publishing events)."""

    def on_event(self, event: AuditEvent, record: EcmVersion) -> None: ...


def default_actor() -> str:
    """The OS user name, or ``"unknown"`` where there is none (some containers)."""
    try:
        return getpass.getuser() or "unknown"
    except (KeyError, OSError, ImportError):
        return "unknown"


def validate_spec(spec: object) -> PublishSpec:
    """Return ``spec`` if it is a :class:`PublishSpec` the descriptor schema accepts.

    A spec built in code is held to the same rules as one parsed from YAML.

    Raises:
        Invalid: wrong type, or a field the schema refuses (message starts with its path).
    """
    if not isinstance(spec, PublishSpec):
        raise Invalid(f"spec must be a PublishSpec, got {type(spec).__name__}", details={"field": "spec"})
    try:
        doc = spec_to_document(spec)
    except (AttributeError, TypeError, ValueError, KeyError) as exc:
        raise Invalid(f"spec: cannot be written as a descriptor: {exc}", details={"field": "spec"}) from None
    validate_document(doc)
    return spec


class LocalRegistry:
    """A :class:`~capevo.registry.api.Registry` stored under one directory.

    Several ``LocalRegistry`` objects, in one or many processes, may share a ``root``:
    SQLite serialises their writes and each mutation is one transaction.

    Args:
        root: Registry directory; created if missing.
        actor: Who mutations are attributed to unless a call passes ``actor=``;
            defaults to the OS user.
        max_artifact_bytes: Larger artifacts are refused with :class:`TooLarge`.
        listeners: Told about each committed mutation, in order.
        busy_timeout_s: How long a write waits for another writer before :class:`Timeout`.

    Raises:
        Invalid: bad ``actor`` or ``max_artifact_bytes``.
        Unavailable: ``root`` cannot be created or the database cannot be opened.
        Corrupt: ``registry.sqlite3`` is not a readable SQLite database.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        actor: str | None = None,
        max_artifact_bytes: int = DEFAULT_MAX_ARTIFACT_BYTES,
        listeners: Sequence[EventListener] = (),
        busy_timeout_s: float = 10.0,
    ) -> None:
        self._actor = _sqlite.validate_text(
            actor if actor is not None else default_actor(), "actor", _sqlite.MAX_ACTOR_CHARS, allow_empty=False
        )
        if isinstance(max_artifact_bytes, bool) or not isinstance(max_artifact_bytes, int) or max_artifact_bytes < 0:
            raise Invalid(
                f"max_artifact_bytes must be a non-negative integer, got {max_artifact_bytes!r}",
                details={"field": "max_artifact_bytes"},
            )
        self._max_artifact_bytes = max_artifact_bytes
        self._root = Path(root)
        try:
            _blobs.make_dir_durably(self._root)
        except OSError as exc:
            raise Unavailable(f"cannot create registry directory {self._root}: {exc}") from exc
        self._blobs = _blobs.BlobStore(self._root / BLOB_DIRNAME)
        swept = self._blobs.sweep_temp(writer_gone=True)
        if swept:
            log.info("removed %d temporary blob file(s) left by killed writers under %s", swept, self._blobs.root)
        self._store = _sqlite.SqliteStore(self._root / DB_FILENAME, busy_timeout_s=busy_timeout_s)
        self._listeners: list[EventListener] = list(listeners)
        self._listeners_lock = threading.Lock()
        self._mutation_lock = threading.RLock()
        self._closed = False

    # --- plumbing ---------------------------------------------------------------------
    @property
    def root(self) -> Path:
        return self._root

    @property
    def store(self) -> _sqlite.SqliteStore:
        return self._store

    @property
    def blobs(self) -> _blobs.BlobStore:
        return self._blobs

    @property
    def actor(self) -> str:
        return self._actor

    def add_listener(self, listener: EventListener) -> None:
        """Tell ``listener`` about every mutation committed from now on."""
        if not isinstance(listener, EventListener):
            raise Invalid(f"listener must have on_event(event, record), got {type(listener).__name__}")
        with self._listeners_lock:
            self._listeners.append(listener)

    def remove_listener(self, listener: EventListener) -> None:
        """Stop telling ``listener``; a listener never added is ignored."""
        with self._listeners_lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def _check_open(self) -> None:
        if self._closed:
            raise Unavailable(f"the registry at {self._root} is closed")

    def _who(self, actor: str | Attribution | None) -> Attribution:
        if actor is None:
            return Attribution(actor=self._actor)
        if isinstance(actor, Attribution):
            _sqlite.validate_text(actor.actor, "actor", _sqlite.MAX_ACTOR_CHARS, allow_empty=False)
            return actor
        return Attribution(actor=_sqlite.validate_text(actor, "actor", _sqlite.MAX_ACTOR_CHARS, allow_empty=False))

    def _mutate(self, commit: Callable[[], Mutation]) -> EcmVersion:
        # Holding one lock from commit through notification hands listeners this
        # process's events in commit order: a subscriber hot-swapping on promote events
        # must never see v2's promotion before v1's.
        with self._mutation_lock:
            mutation = commit()
            with self._listeners_lock:
                listeners = list(self._listeners)
            for listener in listeners:
                try:
                    listener.on_event(mutation.event, mutation.record)
                except Exception:
                    # The mutation is already durable; a broken listener must not turn it into an error.
                    log.exception(
                        "listener %r failed on audit event seq %d (%s %s)",
                        listener,
                        mutation.event.seq,
                        mutation.event.action.value,
                        mutation.event.name,
                    )
        return mutation.record

    # --- reads ------------------------------------------------------------------------
    def list_ecms(self) -> list[EcmSummary]:
        """Every ECM, sorted by name."""
        self._check_open()
        return self._store.list_ecms()

    def get_ecm(self, name: str) -> EcmDetail:
        """One ECM with all its versions, oldest first.

        Raises:
            Invalid: bad name. NotFound: no such ECM.
        """
        self._check_open()
        return self._store.get_ecm(validate_name(name))

    def get_version(self, name: str, version: int | None = None) -> EcmVersion:
        """Version ``version`` of ``name``, or its active version when ``version`` is None.

        Raises:
            Invalid: bad name or version. NotFound: no such ECM/version, or none active.
        """
        self._check_open()
        validate_name(name)
        if version is None:
            return self._store.get_active(name)
        return self._store.get_version(name, validate_version(version))

    def get_artifact(self, name: str, version: int | None = None) -> bytes:
        """The artifact bytes of a version (the active one when ``version`` is None).

        Raises:
            Invalid: bad name or version. NotFound: no such ECM/version.
            Corrupt: the blob is missing or its bytes do not match the recorded hash/size.
        """
        record = self.get_version(name, version)
        ref = record.artifact
        where = f"{record.name} v{record.version}"
        try:
            data = self._blobs.get(ref.sha256)
        except NotFound:
            raise Corrupt(
                f"{where}: its artifact blob {ref.sha256} is missing from {self._blobs.root}",
                details={"name": record.name, "version": record.version, "sha256": ref.sha256},
            ) from None
        except Corrupt as exc:
            raise Corrupt(f"{where}: {exc.message}", details={**exc.details, "name": record.name}) from None
        if len(data) != ref.size:
            raise Corrupt(f"{where}: artifact is {len(data)} bytes but the record says {ref.size}")
        return data

    def history(self, name: str | None = None) -> list[AuditEvent]:
        """Audit events of ``name`` in order (every ECM's when None).

        Raises:
            Invalid: bad name. NotFound: no such ECM.
        """
        self._check_open()
        return self._store.history(name)

    def capability_set(self, revision: int | None = None) -> CapabilitySet:
        """C at ``revision`` (default: now).

        Raises:
            Invalid: negative or non-integer revision. NotFound: revision not reached yet.
        """
        self._check_open()
        return self._store.capability_set(revision)

    # --- mutations --------------------------------------------------------------------
    def publish(
        self, name: str, artifact: bytes, spec: PublishSpec, *, actor: str | Attribution | None = None
    ) -> EcmVersion:
        """Store ``artifact`` and add it as the next candidate version of ``name``.

        Returns:
            The new version (state ``candidate``).

        Raises:
            Invalid: bad name, spec or artifact type. TooLarge: artifact over the limit.
            NotFound: ``spec.parent`` does not exist.
        """
        self._check_open()
        validate_name(name)
        validate_spec(spec)
        who = self._who(actor)
        if not isinstance(artifact, (bytes, bytearray, memoryview)):
            raise Invalid(f"artifact must be bytes, got {type(artifact).__name__}", details={"field": "artifact"})
        size = memoryview(artifact).nbytes
        if size > self._max_artifact_bytes:
            raise TooLarge(
                f"artifact is {size} bytes; the limit is {self._max_artifact_bytes}",
                details={"size": size, "limit": self._max_artifact_bytes},
            )
        # Bytes first: a version row must never name a blob that is not on disk.
        sha, size = self._blobs.put(artifact)
        return self._add_version(name, spec, sha, size, who)

    def artifact_writer(self) -> _blobs.BlobWriter:
        """A writer for an artifact that arrives in pieces (an upload in parts): write them,
        then :meth:`publish_written`; nothing is visible before. Raises Unavailable."""
        self._check_open()
        return self._blobs.writer(max_bytes=self._max_artifact_bytes)

    def publish_written(
        self, name: str, writer: _blobs.BlobWriter, spec: PublishSpec, *, actor: str | Attribution | None = None
    ) -> EcmVersion:
        """:meth:`publish` of the bytes written to ``writer`` (from :meth:`artifact_writer`),
        which it finishes, or discards when anything is refused.

        Raises:
            As :meth:`publish`.
        """
        try:
            self._check_open()
            validate_name(name)
            validate_spec(spec)
            who = self._who(actor)
            sha, size = writer.finish()
        finally:
            writer.discard()
        return self._add_version(name, spec, sha, size, who)

    def _add_version(self, name: str, spec: PublishSpec, sha: str, size: int, who: Attribution) -> EcmVersion:
        ref = ArtifactRef(sha256=sha, size=size, media_type=spec.resolved_media_type)
        return self._mutate(lambda: self._store.create_version(name, spec, ref, actor=who))

    def promote(
        self,
        name: str,
        version: int,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | Attribution | None = None,
    ) -> EcmVersion:
        """Make candidate ``version`` active; the previous active version becomes superseded.

        Raises:
            Conflict: ``expected_active`` given and not the active version.
            IllegalTransition: ``version`` is not a candidate. NotFound, Invalid.
        """
        self._check_open()
        return self._mutate(
            lambda: self._store.move_active(
                name,
                version,
                Action.PROMOTE.value,
                expected_active=expected_active,
                actor=self._who(actor),
                reason=reason,
            )
        )

    def rollback(
        self,
        name: str,
        to: int | None = None,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | Attribution | None = None,
    ) -> EcmVersion:
        """Re-activate superseded version ``to`` (default: the one active before the current one).

        Raises:
            Conflict: ``expected_active`` given and not the active version.
            IllegalTransition: the target is not superseded.
            NotFound: no such ECM/version, or nothing was active before the current version.
        """
        self._check_open()
        return self._mutate(
            lambda: self._store.move_active(
                name, to, Action.ROLLBACK.value, expected_active=expected_active, actor=self._who(actor), reason=reason
            )
        )

    def deprecate(
        self, name: str, version: int, *, reason: str = "", actor: str | Attribution | None = None
    ) -> EcmVersion:
        """Retire a version that is not active.

        Raises:
            IllegalTransition: the version is active or already deprecated. NotFound, Invalid.
        """
        self._check_open()
        return self._mutate(
            lambda: self._store.set_state(name, version, Action.DEPRECATE.value, actor=self._who(actor), reason=reason)
        )

    def reject(
        self, name: str, version: int, *, reason: str = "", actor: str | Attribution | None = None
    ) -> EcmVersion:
        """Mark a candidate as rejected by its gate.

        Raises:
            IllegalTransition: the version is not a candidate. NotFound, Invalid.
        """
        self._check_open()
        return self._mutate(
            lambda: self._store.set_state(name, version, Action.REJECT.value, actor=self._who(actor), reason=reason)
        )

    def record_gate(
        self,
        name: str,
        version: int,
        evidence: Mapping[str, Any],
        *,
        reason: str = "",
        actor: str | Attribution | None = None,
    ) -> EcmVersion:
        """Attach gate evidence (a JSON object with finite numbers) to a candidate.

        Raises:
            Invalid: evidence not JSON-able or holding NaN/inf. TooLarge: evidence over 1 MiB.
            IllegalTransition: the version is not a candidate. NotFound.
        """
        self._check_open()
        return self._mutate(
            lambda: self._store.record_gate(name, version, evidence, actor=self._who(actor), reason=reason)
        )

    # --- integrity --------------------------------------------------------------------
    def verify(self) -> VerifyReport:
        """Check the audit chain, the stored state against a replay of it, and every blob.

        Returns:
            A report whose ``problems`` is empty when everything is intact.
        """
        self._check_open()
        for _ in range(_VERIFY_ATTEMPTS):
            events = self._store.history()
            details = [self._store.get_ecm(s.name) for s in self._store.list_ecms()]
            cap = self._store.capability_set()
            after = self._store.history()
            # Every mutation appends an event in its own transaction, so an unchanged
            # chain tip means the reads above saw one consistent state.
            if [e.hash for e in after[-1:]] == [e.hash for e in events[-1:]] and len(after) == len(events):
                break
        else:
            raise Unavailable(f"the registry at {self._root} kept changing during verify; retry when it is quieter")
        problems: list[str] = list(chain_problems(events))
        problems += _replay_problems(events, details, cap)
        users: dict[str, list[str]] = {}
        for detail in details:
            for v in detail.versions:
                users.setdefault(v.artifact.sha256, []).append(f"{v.name} v{v.version}")
        for sha in sorted(users):
            try:
                problem = self._blobs.verify(sha)
            except Invalid as exc:
                problem = f"blob {sha!r}: {exc.message}"
            if problem:
                problems.append(f"{problem}; used by {', '.join(users[sha])}")
        return VerifyReport(events_checked=len(events), blobs_checked=len(users), problems=tuple(problems))

    # --- lifetime ---------------------------------------------------------------------
    def close(self) -> None:
        """Close the database connection. Idempotent; later calls raise Unavailable."""
        self._closed = True
        self._store.close()

    def __enter__(self) -> LocalRegistry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"LocalRegistry({str(self._root)!r})"


def _replay_problems(events: Sequence[AuditEvent], details: Sequence[EcmDetail], cap: CapabilitySet) -> list[str]:
    """Where the stored versions, pointers and capability set disagree with the audit history."""
    problems: list[str] = []
    states: dict[tuple[str, int], State] = {}
    artifacts: dict[tuple[str, int], tuple[Any, Any, Any]] = {}
    evidence: dict[tuple[str, int], Any] = {}
    active: dict[str, int] = {}
    revision = 0
    for ev in events:
        key = (ev.name, ev.version if ev.version is not None else -1)
        at = f"audit event seq {ev.seq} ({ev.action.value} {ev.name} v{ev.version})"
        if ev.action is Action.PUBLISH:
            if key in states:
                problems.append(f"{at}: publishes a version that already exists")
            states[key] = State.CANDIDATE
            artifacts[key] = (ev.data.get("sha256"), ev.data.get("size"), ev.data.get("media_type"))
            continue
        before = states.get(key)
        if before is None:
            problems.append(f"{at}: names a version that was never published")
        elif ev.from_state is not None and ev.from_state is not before:
            problems.append(f"{at}: says it moved from {ev.from_state.value}, replay has {before.value}")
        if ev.action is Action.GATE:
            evidence[key] = ev.data.get("evidence")
        elif ev.action in (Action.PROMOTE, Action.ROLLBACK):
            revision += 1
            if ev.revision != revision:
                problems.append(f"{at}: carries revision {ev.revision}, replay expects {revision}")
            previous = active.get(ev.name)
            if ev.from_version != previous:
                problems.append(f"{at}: says the pointer left v{ev.from_version}, replay has v{previous}")
            if previous is not None:
                states[(ev.name, previous)] = State.SUPERSEDED
            states[key] = State.ACTIVE
            active[ev.name] = key[1]
        elif ev.to_state is not None:
            states[key] = ev.to_state
    stored: dict[tuple[str, int], EcmVersion] = {}
    for detail in details:
        for v in detail.versions:
            stored[(v.name, v.version)] = v
        if detail.active_version != active.get(detail.name):
            problems.append(
                f"{detail.name}: active pointer is v{detail.active_version}, "
                f"the audit history says v{active.get(detail.name)}"
            )
    for key in sorted(set(states) | set(stored)):
        name, version = key
        if key not in stored:
            problems.append(f"{name} v{version}: in the audit history but not stored")
            continue
        if key not in states:
            problems.append(f"{name} v{version}: stored but never published in the audit history")
            continue
        v = stored[key]
        if v.state is not states[key]:
            problems.append(f"{name} v{version}: stored state {v.state.value}, audit history says {states[key].value}")
        art = (v.artifact.sha256, v.artifact.size, v.artifact.media_type)
        if art != artifacts.get(key):
            problems.append(f"{name} v{version}: stored artifact {art} differs from the published {artifacts.get(key)}")
        if (v.gate_evidence if v.gate_evidence is None else dict(v.gate_evidence)) != evidence.get(key):
            problems.append(f"{name} v{version}: stored gate evidence differs from the audit history")
    if cap.revision != revision or dict(cap.active) != active:
        problems.append(
            f"capability set at revision {cap.revision} is {dict(cap.active)}, "
            f"the audit history gives revision {revision} with {active}"
        )
    return problems
