"""SQLite implementation of :class:`~capevo.storage.abstract.AbstractStore`.

One database file holds ECMs, versions, the per-ECM active pointers, the log of pointer
moves (from which any past capability set is rebuilt) and the hash-chained audit history.
The file runs in WAL mode with ``synchronous=FULL``: a commit returns only after the WAL
is fsynced, so an acknowledged mutation survives SIGKILL and power loss. Several threads
and several processes may use the same file at once; every mutation is one
``BEGIN IMMEDIATE`` transaction, so writers queue on SQLite's write lock (up to
``busy_timeout_s``) instead of interleaving.

This is the only module that sees :mod:`sqlite3` exceptions; they leave it translated:
``IntegrityError`` -> :class:`Conflict`, a lock not obtained in time -> :class:`Timeout`,
a damaged or foreign file -> :class:`Corrupt`, any other I/O failure -> :class:`Unavailable`.

Invariants:
1. Version numbers of one ECM are 0, 1, 2, … with no gap and no duplicate, however many
   threads or processes publish at once (``max + 1`` inside ``BEGIN IMMEDIATE``, backed
   by ``PRIMARY KEY (name, version)``).
2. At most one version of an ECM is ``active`` and ``ecms.active_version`` names it
   (backed by a partial unique index).
3. Each mutation writes its changes and exactly one audit event in one transaction, or
   nothing. Events carry a global ``seq`` 1, 2, 3, … and form one hash chain from
   ``GENESIS`` across all ECMs.
4. Revision 0 is the empty capability set; each pointer move adds exactly one revision,
   and ``capability_set(R)`` returns C exactly as it was after the R-th move.
5. ``move_active`` with ``expected_active`` is a compare-and-swap: on mismatch it raises
   :class:`Conflict` naming both versions and writes nothing.
6. A mutation that returned has been fsynced (WAL + ``synchronous=FULL``).
7. No :mod:`sqlite3` exception escapes; every error is a :class:`CapevoError`.
8. A mutation's :class:`Attribution` extras (``auth``, ``on_behalf_of``) are stored only in
   its event's ``data``; an event without them hashes exactly as before they existed.
9. ``changes_since(seq)`` reads one snapshot: every version an audit event after ``seq``
   created or moved, the active pointer of every ECM such an event names, the chain tip,
   the revision and this connection's ``PRAGMA data_version``, all as of the same commit.
10. Every write transaction that committed moves the :meth:`commit_word
    <SqliteStore.commit_word>` before the method that wrote returns.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import sqlite3
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.errors import (
    CapevoError,
    Conflict,
    Corrupt,
    IllegalTransition,
    Invalid,
    NotFound,
    Timeout,
    TooLarge,
    Unavailable,
)
from capevo.records import (
    Action,
    ArtifactRef,
    Attribution,
    AuditEvent,
    CapabilitySet,
    Descriptor,
    EcmDetail,
    EcmSummary,
    EcmVersion,
    Interface,
    Kind,
    Mutation,
    Origin,
    Provenance,
    PublishSpec,
    State,
)
from capevo.records.audit import GENESIS, canonical_json, event_hash
from capevo.records.lifecycle import GATEABLE, check_transition
from capevo.records.names import validate_name, validate_version
from capevo.records.text import check_unicode
from capevo.storage.abstract import AbstractStore
from capevo.storage.commit_word import CommitWord

SCHEMA_VERSION = 1
MAX_EVIDENCE_BYTES = 1 << 20
MAX_REASON_CHARS = 4096
MAX_ACTOR_CHARS = 256

_STATES_SQL = ", ".join(f"'{s.value}'" for s in State)
_ACTIONS_SQL = ", ".join(f"'{a.value}'" for a in Action)

_SCHEMA_V1 = f"""
CREATE TABLE ecms (
    name            TEXT PRIMARY KEY,
    active_version  INTEGER,
    created_at      REAL NOT NULL,
    FOREIGN KEY (name, active_version) REFERENCES versions (name, version) DEFERRABLE INITIALLY DEFERRED
);
CREATE TABLE versions (
    name            TEXT NOT NULL REFERENCES ecms (name),
    version         INTEGER NOT NULL CHECK (version >= 0),
    kind            TEXT NOT NULL,
    state           TEXT NOT NULL CHECK (state IN ({_STATES_SQL})),
    sha256          TEXT NOT NULL CHECK (length(sha256) = 64),
    size            INTEGER NOT NULL CHECK (size >= 0),
    media_type      TEXT NOT NULL,
    descriptor      TEXT NOT NULL,
    interface       TEXT NOT NULL,
    parent          INTEGER,
    origin          TEXT NOT NULL,
    provenance      TEXT NOT NULL,
    gate_evidence   TEXT,
    created_at      REAL NOT NULL,
    created_by      TEXT NOT NULL,
    PRIMARY KEY (name, version)
);
CREATE UNIQUE INDEX versions_one_active ON versions (name) WHERE state = 'active';
CREATE TABLE events (
    seq             INTEGER PRIMARY KEY CHECK (seq >= 1),
    name            TEXT NOT NULL,
    action          TEXT NOT NULL CHECK (action IN ({_ACTIONS_SQL})),
    version         INTEGER,
    from_state      TEXT,
    to_state        TEXT,
    from_version    INTEGER,
    to_version      INTEGER,
    actor           TEXT NOT NULL,
    reason          TEXT NOT NULL,
    at              REAL NOT NULL,
    data            TEXT NOT NULL,
    revision        INTEGER UNIQUE,
    prev_hash       TEXT NOT NULL,
    hash            TEXT NOT NULL UNIQUE
);
CREATE INDEX events_by_name ON events (name, seq);
CREATE TABLE pointer_moves (
    revision        INTEGER PRIMARY KEY CHECK (revision >= 1),
    name            TEXT NOT NULL REFERENCES ecms (name),
    from_version    INTEGER,
    to_version      INTEGER NOT NULL,
    at              REAL NOT NULL,
    seq             INTEGER NOT NULL UNIQUE REFERENCES events (seq)
);
CREATE INDEX pointer_moves_by_name ON pointer_moves (name, revision);
"""

_ACTIVE_ACTIONS = frozenset({Action.PROMOTE, Action.ROLLBACK})
_STATE_ACTIONS = frozenset({Action.REJECT, Action.DEPRECATE})


@dataclass(frozen=True, slots=True, kw_only=True)
class StoreChanges:
    """What the audit events after some ``seq`` changed, read in one snapshot (:meth:`SqliteStore.changes_since`).

    Attributes:
        data_version: This connection's ``PRAGMA data_version`` in that snapshot.
        seq: The chain tip: the last event's ``seq`` (0 for an empty registry).
        revision: The registry revision (0 before the first pointer move).
        versions: Every version those events created or moved, as stored now.
        active: The active pointer of every ECM those events name.
    """

    data_version: int
    seq: int
    revision: int
    versions: tuple[EcmVersion, ...]
    active: Mapping[str, int | None]


def normalize_evidence(evidence: object) -> dict[str, Any]:
    """Gate evidence as the plain JSON object that will be stored and hashed.

    Raises:
        Invalid: not a mapping with string keys, holds a non-JSON value, NaN or infinity.
        TooLarge: its JSON exceeds :data:`MAX_EVIDENCE_BYTES`.
    """
    if not isinstance(evidence, Mapping):
        raise Invalid(f"evidence must be a mapping, got {type(evidence).__name__}", details={"field": "evidence"})
    _check_json(evidence, "evidence")
    try:
        text = canonical_json(evidence)
    except (TypeError, ValueError, RecursionError) as exc:
        raise Invalid(f"evidence: not JSON-able: {exc}", details={"field": "evidence"}) from None
    if len(text.encode()) > MAX_EVIDENCE_BYTES:
        raise TooLarge(f"evidence is {len(text.encode())} bytes of JSON; the limit is {MAX_EVIDENCE_BYTES}")
    return json.loads(text)


def _check_json(value: object, path: str, depth: int = 0) -> None:
    # Stricter than json.dumps: int keys, NaN and infinity would not read back equal.
    if depth > 64:
        raise Invalid(f"{path}: nested too deeply", details={"field": path})
    if isinstance(value, str):
        check_unicode(value, path)
        return
    if value is None or isinstance(value, (bool, int)):
        return
    if isinstance(value, float):
        if not math.isfinite(value):
            raise Invalid(f"{path}: must be a finite number, got {value}", details={"field": path})
        return
    if isinstance(value, Mapping):
        for k, v in value.items():
            if not isinstance(k, str):
                raise Invalid(f"{path}: keys must be strings, got {k!r}", details={"field": path})
            check_unicode(k, f"{path}.<key>")
            _check_json(v, f"{path}.{k}", depth + 1)
        return
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_json(v, f"{path}[{i}]", depth + 1)
        return
    raise Invalid(f"{path}: {type(value).__name__} is not a JSON value", details={"field": path})


def validate_text(value: object, field: str, limit: int, *, allow_empty: bool = True) -> str:
    """Return ``value`` if it is a string of at most ``limit`` characters.

    Raises:
        Invalid: wrong type, too long, empty when ``allow_empty`` is false, or a lone surrogate.
    """
    if not isinstance(value, str):
        raise Invalid(f"{field} must be a string, got {type(value).__name__}", details={"field": field})
    check_unicode(value, field)
    if len(value) > limit:
        raise Invalid(f"{field} is {len(value)} characters; the limit is {limit}", details={"field": field})
    if not allow_empty and not value:
        raise Invalid(f"{field} must not be empty", details={"field": field})
    return value


def _action(action: object, allowed: frozenset[Action], method: str) -> Action:
    try:
        act = Action(action)
    except ValueError:
        act = None
    if act not in allowed:
        names = ", ".join(sorted(a.value for a in allowed))
        raise Invalid(f"{method}: action must be one of {names}, got {action!r}", details={"field": "action"})
    return act


class SqliteStore(AbstractStore):
    """The metadata store in one SQLite file (WAL, ``synchronous=FULL``).

    One connection serves every thread of the process, guarded by a lock; other
    processes may open the same file at the same time.

    Args:
        path: Database file; created (with its parent directory) if missing.
        busy_timeout_s: How long to wait for another writer's lock before :class:`Timeout`.

    Raises:
        Unavailable: the file cannot be opened, or its schema is newer than this code.
        Corrupt: the file is not an SQLite database or is damaged.
        Timeout: another process held the lock longer than ``busy_timeout_s`` during setup.
    """

    def __init__(self, path: str | os.PathLike[str], *, busy_timeout_s: float = 10.0) -> None:
        self._path = Path(path)
        self._busy_timeout_s = float(busy_timeout_s)
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = None
        try:
            self._path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise Unavailable(f"cannot create directory for {self._path}: {exc}") from exc
        self._word = CommitWord(self._path)
        try:
            conn = sqlite3.connect(
                self._path, timeout=self._busy_timeout_s, isolation_level=None, check_same_thread=False
            )
        except sqlite3.Error as exc:
            self._word.close()
            raise self._translate(exc, "open") from exc
        conn.row_factory = sqlite3.Row
        self._conn = conn
        try:
            self._configure(conn)
            self._migrate()
        except BaseException:
            self.close()
            raise

    # --- setup ------------------------------------------------------------------------
    @property
    def path(self) -> Path:
        return self._path

    def _configure(self, conn: sqlite3.Connection) -> None:
        deadline = time.monotonic() + self._busy_timeout_s
        while True:
            try:
                conn.execute(f"PRAGMA busy_timeout = {int(self._busy_timeout_s * 1000)}")
                conn.execute("PRAGMA foreign_keys = ON")
                mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
                conn.execute("PRAGMA synchronous = FULL")
                break
            except sqlite3.OperationalError as exc:
                # Switching a fresh file to WAL needs an exclusive lock the busy handler
                # does not always wait for; another process may be doing the same.
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise self._translate(exc, "open") from exc
                time.sleep(0.01)
            except sqlite3.Error as exc:
                raise self._translate(exc, "open") from exc
        if str(mode).lower() != "wal":
            raise Unavailable(f"{self._path}: SQLite refused WAL mode (got {mode!r}); use a local filesystem")

    def _migrate(self) -> None:
        with self._write("open") as c:
            c.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
            row = c.execute("SELECT MAX(version) FROM schema_version").fetchone()
            current = row[0]
            if current is None:
                for stmt in _SCHEMA_V1.split(";"):
                    if stmt.strip():
                        c.execute(stmt)
                c.execute("INSERT INTO schema_version (version) VALUES (?)", (SCHEMA_VERSION,))
            elif current > SCHEMA_VERSION:
                raise Unavailable(
                    f"{self._path} has schema version {current}; this capevo understands up to {SCHEMA_VERSION}"
                )
            # Future versions: apply migrations current+1 .. SCHEMA_VERSION here, in this transaction.

    def schema_version(self) -> int:
        """The schema version recorded in the file."""
        with self._read("schema_version") as c:
            return int(c.execute("SELECT MAX(version) FROM schema_version").fetchone()[0])

    def pragma(self, name: str) -> Any:
        """Read one connection setting (``journal_mode``, ``synchronous``, …) for checks and tests.

        Raises:
            Invalid: ``name`` is not a plain identifier.
        """
        if not name.isidentifier():
            raise Invalid(f"not a pragma name: {name!r}")
        with self._lock:
            conn = self._require_open()
            try:
                return conn.execute(f"PRAGMA {name}").fetchone()[0]
            except sqlite3.Error as exc:
                raise self._translate(exc, f"pragma {name}") from exc

    # --- transactions -----------------------------------------------------------------
    def _require_open(self) -> sqlite3.Connection:
        if self._conn is None:
            raise Unavailable(f"the store at {self._path} is closed")
        return self._conn

    @contextlib.contextmanager
    def _tx(self, what: str, begin: str) -> Iterator[sqlite3.Connection]:
        with self._lock:
            conn = self._require_open()
            try:
                conn.execute(begin)
            except sqlite3.Error as exc:
                raise self._translate(exc, what) from exc
            try:
                yield conn
                conn.execute("COMMIT")
                if begin != "BEGIN":
                    self._word.move()  # durable now, and not yet acknowledged (commit_word)
            except BaseException as exc:
                if conn.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        conn.execute("ROLLBACK")
                if isinstance(exc, sqlite3.Error):
                    raise self._translate(exc, what) from exc
                raise

    def _write(self, what: str) -> contextlib.AbstractContextManager[sqlite3.Connection]:
        # IMMEDIATE takes the write lock up front: a deferred transaction that later
        # upgrades can fail with BUSY at once, without the busy handler ever waiting.
        return self._tx(what, "BEGIN IMMEDIATE")

    def _read(self, what: str) -> contextlib.AbstractContextManager[sqlite3.Connection]:
        # A read transaction gives multi-statement reads one consistent WAL snapshot.
        return self._tx(what, "BEGIN")

    def _translate(self, exc: sqlite3.Error, what: str) -> CapevoError:
        msg = str(exc)
        name = getattr(exc, "sqlite_errorname", "") or ""
        low = f"{name} {msg}".lower()
        where = f"{what} on {self._path}"
        if isinstance(exc, sqlite3.IntegrityError):
            return Conflict(f"{where}: constraint failed: {msg}", details={"sqlite": msg})
        if "busy" in low or "locked" in low:
            return Timeout(
                f"{where}: the database stayed locked by another writer for over {self._busy_timeout_s:g}s",
                details={"sqlite": msg},
            )
        if "corrupt" in low or "malformed" in low or "notadb" in low or "not a database" in low:
            return Corrupt(f"{where}: the database file is damaged or not SQLite: {msg}", details={"sqlite": msg})
        if isinstance(exc, sqlite3.ProgrammingError) and "closed" in low:
            return Unavailable(f"{where}: the store is closed", details={"sqlite": msg})
        return Unavailable(f"{where}: {msg}", details={"sqlite": msg})

    # --- row mapping ------------------------------------------------------------------
    @staticmethod
    def _version_from_row(row: sqlite3.Row) -> EcmVersion:
        try:
            return EcmVersion(
                name=row["name"],
                version=int(row["version"]),
                kind=Kind(row["kind"]),
                state=State(row["state"]),
                artifact=ArtifactRef(sha256=row["sha256"], size=int(row["size"]), media_type=row["media_type"]),
                descriptor=Descriptor.from_dict(json.loads(row["descriptor"])),
                interface=Interface.from_dict(json.loads(row["interface"])),
                parent=row["parent"],
                origin=Origin(row["origin"]),
                provenance=Provenance.from_dict(json.loads(row["provenance"])),
                gate_evidence=json.loads(row["gate_evidence"]) if row["gate_evidence"] is not None else None,
                created_at=float(row["created_at"]),
                created_by=row["created_by"],
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise Corrupt(f"version row {row['name']} v{row['version']} cannot be read: {exc}") from exc

    @staticmethod
    def _event_from_row(row: sqlite3.Row) -> AuditEvent:
        try:
            d = dict(row)
            d["data"] = json.loads(d["data"])
            return AuditEvent.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:
            raise Corrupt(f"audit event seq {row['seq']} cannot be read: {exc}") from exc

    def _fetch_version(self, c: sqlite3.Connection, name: str, version: int) -> EcmVersion:
        row = c.execute("SELECT * FROM versions WHERE name = ? AND version = ?", (name, version)).fetchone()
        if row is None:
            ecm = c.execute("SELECT MAX(version) FROM versions WHERE name = ?", (name,)).fetchone()[0]
            if ecm is None:
                raise NotFound(f"no ECM named {name!r}", details={"name": name})
            raise NotFound(
                f"{name} has no version {version} (latest is v{ecm})", details={"name": name, "version": version}
            )
        return self._version_from_row(row)

    def _fetch_active_pointer(self, c: sqlite3.Connection, name: str) -> int | None:
        row = c.execute("SELECT active_version FROM ecms WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise NotFound(f"no ECM named {name!r}", details={"name": name})
        return row[0]

    def _append_event(
        self,
        c: sqlite3.Connection,
        *,
        name: str,
        action: Action,
        version: int | None,
        from_state: State | None,
        to_state: State | None,
        actor: Attribution,
        reason: str,
        at: float,
        from_version: int | None = None,
        to_version: int | None = None,
        data: Mapping[str, Any] | None = None,
        revision: int | None = None,
    ) -> AuditEvent:
        last = c.execute("SELECT seq, hash FROM events ORDER BY seq DESC LIMIT 1").fetchone()
        seq, prev = (int(last["seq"]) + 1, last["hash"]) if last else (1, GENESIS)
        draft = AuditEvent(
            seq=seq,
            name=name,
            action=action,
            version=version,
            from_state=from_state,
            to_state=to_state,
            from_version=from_version,
            to_version=to_version,
            actor=actor.actor,
            reason=reason,
            at=at,
            data=json.loads(canonical_json({**(data or {}), **actor.audit_data()})),
            revision=revision,
            prev_hash=prev,
            hash="",
        )
        # Hash exactly what to_dict() yields, the form chain_problems re-hashes on verify.
        event = dataclasses.replace(draft, hash=event_hash(draft.to_dict()))
        d = event.to_dict()
        c.execute(
            "INSERT INTO events (seq, name, action, version, from_state, to_state, from_version, to_version,"
            " actor, reason, at, data, revision, prev_hash, hash)"
            " VALUES (:seq, :name, :action, :version, :from_state, :to_state, :from_version, :to_version,"
            " :actor, :reason, :at, :data, :revision, :prev_hash, :hash)",
            {**d, "data": canonical_json(d["data"])},
        )
        return event

    @staticmethod
    def _check_common(name: str, actor: str | Attribution, reason: str) -> Attribution:
        validate_name(name)
        who = actor if isinstance(actor, Attribution) else Attribution(actor=actor)
        validate_text(who.actor, "actor", MAX_ACTOR_CHARS, allow_empty=False)
        if who.on_behalf_of is not None:
            validate_text(who.on_behalf_of, "on_behalf_of", MAX_ACTOR_CHARS, allow_empty=False)
        validate_text(reason, "reason", MAX_REASON_CHARS)
        return who

    # --- ECMs -------------------------------------------------------------------------
    def list_ecms(self) -> list[EcmSummary]:
        with self._read("list_ecms") as c:
            rows = c.execute(
                "SELECT e.name, e.active_version, MAX(v.version) AS latest, COUNT(v.version) AS n"
                " FROM ecms e JOIN versions v ON v.name = e.name GROUP BY e.name ORDER BY e.name"
            ).fetchall()
        return [
            EcmSummary(
                name=r["name"], active_version=r["active_version"], latest_version=r["latest"], n_versions=r["n"]
            )
            for r in rows
        ]

    def get_ecm(self, name: str) -> EcmDetail:
        validate_name(name)
        with self._read("get_ecm") as c:
            active = self._fetch_active_pointer(c, name)
            rows = c.execute("SELECT * FROM versions WHERE name = ? ORDER BY version", (name,)).fetchall()
        return EcmDetail(name=name, active_version=active, versions=tuple(self._version_from_row(r) for r in rows))

    # --- versions ---------------------------------------------------------------------
    def create_version(
        self, name: str, spec: PublishSpec, artifact: ArtifactRef, *, actor: str | Attribution
    ) -> Mutation:
        who = self._check_common(name, actor, "")
        if not isinstance(spec, PublishSpec):
            raise Invalid(f"spec must be a PublishSpec, got {type(spec).__name__}", details={"field": "spec"})
        if not isinstance(artifact, ArtifactRef):
            raise Invalid(f"artifact must be an ArtifactRef, got {type(artifact).__name__}")
        if spec.parent is not None and (
            isinstance(spec.parent, bool) or not isinstance(spec.parent, int) or spec.parent < 0
        ):
            raise Invalid(
                f"parent must be a non-negative integer version, got {spec.parent!r}", details={"field": "parent"}
            )
        descriptor = canonical_json(spec.descriptor.to_dict())
        interface = canonical_json(spec.interface.to_dict())
        provenance = canonical_json(spec.provenance.to_dict())
        with self._write("publish") as c:
            now = time.time()
            if c.execute("SELECT 1 FROM ecms WHERE name = ?", (name,)).fetchone() is None:
                c.execute("INSERT INTO ecms (name, active_version, created_at) VALUES (?, NULL, ?)", (name, now))
            version = int(
                c.execute("SELECT COALESCE(MAX(version), -1) + 1 FROM versions WHERE name = ?", (name,)).fetchone()[0]
            )
            if (
                spec.parent is not None
                and c.execute("SELECT 1 FROM versions WHERE name = ? AND version = ?", (name, spec.parent)).fetchone()
                is None
            ):
                raise NotFound(
                    f"parent: {name} has no version {spec.parent} to derive from",
                    details={"field": "parent", "name": name, "version": spec.parent},
                )
            c.execute(
                "INSERT INTO versions (name, version, kind, state, sha256, size, media_type, descriptor, interface,"
                " parent, origin, provenance, gate_evidence, created_at, created_by)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, NULL, ?, ?)",
                (
                    name,
                    version,
                    spec.kind.value,
                    State.CANDIDATE.value,
                    artifact.sha256,
                    artifact.size,
                    artifact.media_type,
                    descriptor,
                    interface,
                    spec.parent,
                    spec.origin.value,
                    provenance,
                    now,
                    who.actor,
                ),
            )
            event = self._append_event(
                c,
                name=name,
                action=Action.PUBLISH,
                version=version,
                from_state=None,
                to_state=State.CANDIDATE,
                actor=who,
                reason="",
                at=now,
                data={
                    "sha256": artifact.sha256,
                    "size": artifact.size,
                    "media_type": artifact.media_type,
                    "kind": spec.kind.value,
                    "parent": spec.parent,
                    "origin": spec.origin.value,
                },
            )
            record = self._fetch_version(c, name, version)
        return Mutation(record=record, event=event)

    def get_version(self, name: str, version: int) -> EcmVersion:
        validate_name(name)
        validate_version(version)
        with self._read("get_version") as c:
            return self._fetch_version(c, name, version)

    def get_active(self, name: str) -> EcmVersion:
        validate_name(name)
        with self._read("get_active") as c:
            active = self._fetch_active_pointer(c, name)
            if active is None:
                raise NotFound(f"{name} has no active version (promote one first)", details={"name": name})
            return self._fetch_version(c, name, active)

    def record_gate(
        self, name: str, version: int, evidence: Mapping[str, Any], *, actor: str | Attribution, reason: str = ""
    ) -> Mutation:
        who = self._check_common(name, actor, reason)
        validate_version(version)
        stored = normalize_evidence(evidence)
        with self._write("record_gate") as c:
            current = self._fetch_version(c, name, version)
            if current.state not in GATEABLE:
                raise IllegalTransition(
                    f"cannot gate {name} v{version}: it is {current.state.value}"
                    " (gate evidence is recorded on candidates only)",
                    details={"name": name, "version": version, "state": current.state.value, "action": "gate"},
                )
            c.execute(
                "UPDATE versions SET gate_evidence = ? WHERE name = ? AND version = ?",
                (canonical_json(stored), name, version),
            )
            event = self._append_event(
                c,
                name=name,
                action=Action.GATE,
                version=version,
                from_state=current.state,
                to_state=current.state,
                actor=who,
                reason=reason,
                at=time.time(),
                data={"evidence": stored},
            )
            record = self._fetch_version(c, name, version)
        return Mutation(record=record, event=event)

    def set_state(
        self, name: str, version: int, action: str, *, actor: str | Attribution, reason: str = ""
    ) -> Mutation:
        act = _action(action, _STATE_ACTIONS, "set_state")
        who = self._check_common(name, actor, reason)
        validate_version(version)
        with self._write(act.value) as c:
            current = self._fetch_version(c, name, version)
            to_state = check_transition(name, version, current.state, act)
            c.execute("UPDATE versions SET state = ? WHERE name = ? AND version = ?", (to_state.value, name, version))
            event = self._append_event(
                c,
                name=name,
                action=act,
                version=version,
                from_state=current.state,
                to_state=to_state,
                actor=who,
                reason=reason,
                at=time.time(),
            )
            record = self._fetch_version(c, name, version)
        return Mutation(record=record, event=event)

    def move_active(
        self,
        name: str,
        version: int | None,
        action: str,
        *,
        expected_active: int | None = None,
        actor: str | Attribution,
        reason: str = "",
    ) -> Mutation:
        act = _action(action, _ACTIVE_ACTIONS, "move_active")
        who = self._check_common(name, actor, reason)
        if version is None and act is Action.PROMOTE:
            raise Invalid("promote needs a version", details={"field": "version"})
        if version is not None:
            validate_version(version)
        if expected_active is not None:
            validate_version(expected_active)
        with self._write(act.value) as c:
            current = self._fetch_active_pointer(c, name)
            if expected_active is not None and expected_active != current:
                shown = f"v{current}" if current is not None else "none"
                raise Conflict(
                    f"cannot {act.value} {name}: expected active v{expected_active}, but the active version is {shown}",
                    details={"name": name, "expected_active": expected_active, "active": current},
                )
            target = version if version is not None else self._previous_active(c, name, current)
            record = self._fetch_version(c, name, target)
            to_state = check_transition(name, target, record.state, act)
            at = time.time()
            if current is not None:
                c.execute(
                    "UPDATE versions SET state = ? WHERE name = ? AND version = ?",
                    (State.SUPERSEDED.value, name, current),
                )
            c.execute("UPDATE versions SET state = ? WHERE name = ? AND version = ?", (to_state.value, name, target))
            c.execute("UPDATE ecms SET active_version = ? WHERE name = ?", (target, name))
            revision = int(c.execute("SELECT COALESCE(MAX(revision), 0) + 1 FROM pointer_moves").fetchone()[0])
            event = self._append_event(
                c,
                name=name,
                action=act,
                version=target,
                from_state=record.state,
                to_state=to_state,
                from_version=current,
                to_version=target,
                actor=who,
                reason=reason,
                at=at,
                revision=revision,
            )
            c.execute(
                "INSERT INTO pointer_moves (revision, name, from_version, to_version, at, seq)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                (revision, name, current, target, at, event.seq),
            )
            after = self._fetch_version(c, name, target)
        return Mutation(record=after, event=event)

    def _previous_active(self, c: sqlite3.Connection, name: str, current: int | None) -> int:
        # "Previous" is whatever the pointer left when it last moved, not version - 1.
        if current is None:
            raise NotFound(f"cannot roll back {name}: it has no active version", details={"name": name})
        row = c.execute(
            "SELECT from_version FROM pointer_moves WHERE name = ? ORDER BY revision DESC LIMIT 1", (name,)
        ).fetchone()
        if row is None or row[0] is None:
            raise NotFound(
                f"cannot roll back {name}: v{current} is the first version ever active, nothing was active before it",
                details={"name": name, "active": current},
            )
        return int(row[0])

    # --- capability set ---------------------------------------------------------------
    def capability_set(self, revision: int | None = None) -> CapabilitySet:
        if revision is not None and (isinstance(revision, bool) or not isinstance(revision, int) or revision < 0):
            raise Invalid(f"revision must be a non-negative integer, got {revision!r}", details={"field": "revision"})
        with self._read("capability_set") as c:
            now = int(c.execute("SELECT COALESCE(MAX(revision), 0) FROM pointer_moves").fetchone()[0])
            at = now if revision is None else revision
            if at > now:
                raise NotFound(
                    f"revision {at} has not been reached; the registry is at revision {now}",
                    details={"revision": at, "current": now},
                )
            rows = c.execute(
                "SELECT p.name, p.to_version FROM pointer_moves p"
                " JOIN (SELECT name, MAX(revision) AS r FROM pointer_moves WHERE revision <= ? GROUP BY name) m"
                " ON p.name = m.name AND p.revision = m.r",
                (at,),
            ).fetchall()
        return CapabilitySet(revision=at, active={r["name"]: int(r["to_version"]) for r in rows})

    # --- history ----------------------------------------------------------------------
    def history(self, name: str | None = None) -> list[AuditEvent]:
        if name is not None:
            validate_name(name)
        with self._read("history") as c:
            if name is None:
                rows = c.execute("SELECT * FROM events ORDER BY seq").fetchall()
            else:
                self._fetch_active_pointer(c, name)  # NotFound for an unknown ECM
                rows = c.execute("SELECT * FROM events WHERE name = ? ORDER BY seq", (name,)).fetchall()
        return [self._event_from_row(r) for r in rows]

    # --- change tracking ------------------------------------------------------------
    def data_version(self) -> int:
        """SQLite's ``PRAGMA data_version`` on this connection.

        It changes whenever another connection, of this process or any other, commits to the
        file, and costs microseconds: the cheap "has anything changed?" of a read cache.
        """
        with self._lock:
            conn = self._require_open()
            try:
                return int(conn.execute("PRAGMA data_version").fetchone()[0])
            except sqlite3.Error as exc:
                raise self._translate(exc, "data_version") from exc

    def commit_word(self) -> bytes:
        """8 bytes that every capevo writer of this file changes after each commit, before it returns.

        Loading them costs well under a microsecond, against a read transaction for
        :meth:`data_version`: a reader that kept the word it loaded before its last full check
        knows, while the word is unchanged, that no commit was acknowledged since. See
        :mod:`capevo.storage.commit_word` for the protocol and its limits.

        Raises:
            Unavailable: the store is closed.
        """
        return self._word.load()

    def changes_since(self, seq: int) -> StoreChanges:
        """Everything the audit events after ``seq`` changed (``0``: the whole registry).

        Every mutation appends one event in its own transaction, naming the version it
        created or moved and, for a pointer move, the version the pointer left; so these
        rows are exactly the ones that differ from the state after event ``seq``.

        Raises:
            Invalid: ``seq`` is not a non-negative integer.
        """
        if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
            raise Invalid(f"seq must be a non-negative integer, got {seq!r}", details={"field": "seq"})
        with self._read("changes_since") as c:
            # The pragma starts the read transaction, so it describes the snapshot read below.
            data_version = int(c.execute("PRAGMA data_version").fetchone()[0])
            tip = int(c.execute("SELECT COALESCE(MAX(seq), 0) FROM events").fetchone()[0])
            revision = int(c.execute("SELECT COALESCE(MAX(revision), 0) FROM pointer_moves").fetchone()[0])
            if tip == seq:
                return StoreChanges(data_version=data_version, seq=tip, revision=revision, versions=(), active={})
            rows = c.execute(
                "SELECT v.* FROM versions v JOIN ("
                " SELECT name, version AS k FROM events WHERE seq > :seq AND version IS NOT NULL"
                " UNION SELECT name, from_version AS k FROM events WHERE seq > :seq AND from_version IS NOT NULL"
                ") changed ON v.name = changed.name AND v.version = changed.k ORDER BY v.name, v.version",
                {"seq": seq},
            ).fetchall()
            pointers = c.execute(
                "SELECT name, active_version FROM ecms WHERE name IN (SELECT name FROM events WHERE seq > ?)", (seq,)
            ).fetchall()
        return StoreChanges(
            data_version=data_version,
            seq=tip,
            revision=revision,
            versions=tuple(self._version_from_row(r) for r in rows),
            active={r["name"]: r["active_version"] for r in pointers},
        )

    def artifact_refs(self) -> list[ArtifactRef]:
        with self._read("artifact_refs") as c:
            rows = c.execute(
                "SELECT DISTINCT sha256, size, media_type FROM versions ORDER BY sha256, media_type"
            ).fetchall()
        return [ArtifactRef(sha256=r["sha256"], size=int(r["size"]), media_type=r["media_type"]) for r in rows]

    def close(self) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
            if conn is not None:
                with contextlib.suppress(sqlite3.Error):
                    conn.close()
                self._word.close()

    def __enter__(self) -> SqliteStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
