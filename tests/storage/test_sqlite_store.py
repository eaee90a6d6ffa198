"""SqliteStore used directly; invariant numbers refer to :mod:`capevo.storage.sqlite`."""

from __future__ import annotations

import contextlib
import sqlite3
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from procs import run_in_threads

from capevo.errors import (
    CapevoError,
    Conflict,
    Corrupt,
    ErrorCode,
    IllegalTransition,
    Invalid,
    NotFound,
    Timeout,
    TooLarge,
    Unavailable,
)
from capevo.records import Action, ArtifactRef, Mutation, PublishSpec, State
from capevo.records.audit import GENESIS, chain_problems
from capevo.registry.descriptor import parse_publish_spec
from capevo.storage.sqlite import MAX_EVIDENCE_BYTES, SqliteStore

SPEC = parse_publish_spec("kind: prompt\ndescription: say hello\n")
REF = ArtifactRef(sha256="ab" * 32, size=5, media_type="text/plain")


@pytest.fixture
def store(tmp_path: Path) -> Iterator[SqliteStore]:
    with SqliteStore(tmp_path / "registry.sqlite3") as s:
        yield s


def _raw(store: SqliteStore) -> contextlib.closing[sqlite3.Connection]:
    return contextlib.closing(sqlite3.connect(store.path, timeout=5))


def _publish(store: SqliteStore, name: str = "hello", n: int = 1) -> list[Mutation]:
    return [store.create_version(name, SPEC, REF, actor="t") for _ in range(n)]


# --- invariant 1: version numbers --------------------------------------------------------------
def test_inv1_versions_count_from_zero_per_ecm(store: SqliteStore) -> None:
    assert [m.record.version for m in _publish(store, "a", 3)] == [0, 1, 2]
    assert [m.record.version for m in _publish(store, "b", 2)] == [0, 1]
    assert [m.record.version for m in _publish(store, "a", 1)] == [3]


def test_inv1_schema_refuses_a_duplicate_version(store: SqliteStore) -> None:
    _publish(store)
    with _raw(store) as conn, pytest.raises(sqlite3.IntegrityError, match="UNIQUE"):
        conn.execute("INSERT INTO versions SELECT * FROM versions WHERE version = 0")


def test_inv1_threads_get_unique_gap_free_versions(store: SqliteStore) -> None:
    def work(_: int) -> list[int]:
        return [store.create_version("hello", SPEC, REF, actor="t").record.version for _ in range(10)]

    got = [v for versions in run_in_threads(work, 6) for v in versions]
    assert sorted(got) == list(range(60))


# --- invariant 2: one active version -----------------------------------------------------------
def test_inv2_schema_refuses_a_second_active_version(store: SqliteStore) -> None:
    _publish(store, n=2)
    store.move_active("hello", 0, "promote", actor="t")
    with _raw(store) as conn, pytest.raises(sqlite3.IntegrityError, match="UNIQUE"):
        conn.execute("UPDATE versions SET state = 'active' WHERE version = 1")
    assert store.get_active("hello").version == 0


# --- invariant 3: one transaction, one event, one chain ----------------------------------------
def test_inv3_events_form_one_global_chain(store: SqliteStore) -> None:
    _publish(store, "a")
    _publish(store, "b")
    store.move_active("b", 0, "promote", actor="t")
    store.record_gate("a", 0, {"curve": (1, 2.5)}, actor="t", reason="r")
    events = store.history()
    assert [e.seq for e in events] == [1, 2, 3, 4]
    assert events[0].prev_hash == GENESIS and chain_problems(events) == []
    assert [e.seq for e in store.history("a")] == [1, 4]
    assert [e.revision for e in events] == [None, None, 1, None]
    assert events[3].data == {"evidence": {"curve": [1, 2.5]}}  # stored as JSON
    assert store.get_version("a", 0).gate_evidence == {"curve": [1, 2.5]}


def test_inv3_a_refused_mutation_writes_nothing(store: SqliteStore) -> None:
    bad_parent = PublishSpec.from_dict({**SPEC.to_dict(), "parent": 0})
    with pytest.raises(NotFound, match="parent: fresh has no version 0 to derive from"):
        store.create_version("fresh", bad_parent, REF, actor="t")
    assert store.list_ecms() == [] and store.history() == []
    _publish(store)
    with pytest.raises(IllegalTransition):
        store.move_active("hello", 0, "rollback", actor="t")
    with pytest.raises(TooLarge):
        store.record_gate("hello", 0, {"blob": "x" * MAX_EVIDENCE_BYTES}, actor="t")
    assert len(store.history()) == 1 and store.capability_set().revision == 0


def test_inv3_mutation_returns_the_record_as_stored(store: SqliteStore) -> None:
    m = store.create_version("hello", SPEC, REF, actor="t")
    assert m.record == store.get_version("hello", 0)
    assert m.event == store.history("hello")[-1]
    assert m.event.data == {
        "sha256": REF.sha256,
        "size": 5,
        "media_type": "text/plain",
        "kind": "prompt",
        "parent": None,
        "origin": "manual",
    }


# --- invariants 3-5 against a model ------------------------------------------------------------
NAMES = ("a", "b")
ops = st.lists(
    st.one_of(
        st.tuples(st.just("publish"), st.sampled_from(NAMES)),
        st.tuples(
            st.sampled_from(["promote", "rollback"]),
            st.sampled_from(NAMES),
            st.one_of(st.none(), st.integers(0, 4)),
            st.one_of(st.none(), st.integers(0, 4)),
        ),
        st.tuples(st.sampled_from(["deprecate", "reject", "gate"]), st.sampled_from(NAMES), st.integers(0, 4)),
    ),
    max_size=30,
)


class Model:
    """An independent, in-memory statement of what the store must do."""

    def __init__(self) -> None:
        self.states: dict[str, list[State]] = {}
        self.active: dict[str, int | None] = {}
        self.last_from: dict[str, int | None] = {}
        self.caps: list[dict[str, int]] = [{}]
        self.events = 0

    def apply(self, op: tuple[Any, ...]) -> type[CapevoError] | None:
        kind, name = op[0], op[1]
        if kind == "publish":
            self.states.setdefault(name, []).append(State.CANDIDATE)
            self.active.setdefault(name, None)
            self.events += 1
            return None
        if kind == "promote" and op[2] is None:
            return Invalid  # arguments are checked before anything is read
        if name not in self.states:
            return NotFound
        states = self.states[name]
        if kind in ("promote", "rollback"):
            _, _, version, expected = op
            current = self.active[name]
            if expected is not None and expected != current:
                return Conflict
            if version is None:
                if current is None or self.last_from.get(name) is None:
                    return NotFound
                version = self.last_from[name]
            if version >= len(states):
                return NotFound
            need = State.CANDIDATE if kind == "promote" else State.SUPERSEDED
            if states[version] is not need:
                return IllegalTransition
            if current is not None:
                states[current] = State.SUPERSEDED
            states[version] = State.ACTIVE
            self.active[name], self.last_from[name] = version, current
            self.caps.append({**self.caps[-1], name: version})
            self.events += 1
            return None
        version = op[2]
        if version >= len(states):
            return NotFound
        allowed = {
            "deprecate": {State.CANDIDATE, State.SUPERSEDED, State.REJECTED},
            "reject": {State.CANDIDATE},
            "gate": {State.CANDIDATE},
        }[kind]
        if states[version] not in allowed:
            return IllegalTransition
        if kind != "gate":
            states[version] = State.DEPRECATED if kind == "deprecate" else State.REJECTED
        self.events += 1
        return None


def _run(store: SqliteStore, op: tuple[Any, ...]) -> None:
    kind, name = op[0], op[1]
    if kind == "publish":
        store.create_version(name, SPEC, REF, actor="m")
    elif kind in ("promote", "rollback"):
        store.move_active(name, op[2], kind, expected_active=op[3], actor="m")
    elif kind == "gate":
        store.record_gate(name, op[2], {"op": len(kind)}, actor="m")
    else:
        store.set_state(name, op[2], kind, actor="m")


@settings(max_examples=40, deadline=None)
@given(ops)
def test_inv3_inv4_inv5_store_matches_the_model(sequence: list[tuple[Any, ...]]) -> None:
    model = Model()
    with tempfile.TemporaryDirectory() as tmp, SqliteStore(Path(tmp) / "m.sqlite3") as store:
        for op in sequence:
            expected = model.apply(op)
            try:
                _run(store, op)
                got: type[CapevoError] | None = None
            except CapevoError as exc:
                got = type(exc)
            assert got is expected, op
        for name, states in model.states.items():
            detail = store.get_ecm(name)
            assert [v.state for v in detail.versions] == states
            assert detail.active_version == model.active[name]
        assert [dict(store.capability_set(r).active) for r in range(len(model.caps))] == model.caps
        events = store.history()
        assert len(events) == model.events and chain_problems(events) == []


# --- invariant 5: compare-and-swap -------------------------------------------------------------
def test_inv5_only_one_of_many_racing_threads_wins(store: SqliteStore) -> None:
    _publish(store, n=9)
    store.move_active("hello", 0, "promote", actor="t")
    barrier = threading.Barrier(8)

    def race(i: int) -> str:
        barrier.wait()
        try:
            store.move_active("hello", i + 1, "promote", expected_active=0, actor="t")
            return "won"
        except Conflict as exc:
            return exc.code.value

    assert sorted(run_in_threads(race, 8)) == ["conflict"] * 7 + ["won"]
    assert store.capability_set().revision == 2


def test_inv5_conflict_details_name_both_versions(store: SqliteStore) -> None:
    _publish(store, n=2)
    store.move_active("hello", 0, "promote", actor="t")
    with pytest.raises(Conflict) as info:
        store.move_active("hello", 1, "promote", expected_active=1, actor="t")
    assert type(info.value) is Conflict
    assert info.value.details == {"name": "hello", "expected_active": 1, "active": 0}


# --- invariant 6: durability settings ----------------------------------------------------------
def test_inv6_wal_and_full_sync(store: SqliteStore) -> None:
    assert store.pragma("journal_mode") == "wal"
    assert store.pragma("synchronous") == 2
    assert store.pragma("foreign_keys") == 1
    assert store.pragma("busy_timeout") == 10_000
    with pytest.raises(Invalid):
        store.pragma("synchronous = OFF")


# --- invariant 7: sqlite3 errors leave translated -------------------------------------------------
def test_inv7_lock_held_too_long_is_timeout(tmp_path: Path) -> None:
    with SqliteStore(tmp_path / "r.sqlite3", busy_timeout_s=0.2) as store:
        _publish(store)
        with _raw(store) as other:
            other.execute("BEGIN IMMEDIATE")
            with pytest.raises(Timeout) as info:
                _publish(store)
            other.execute("ROLLBACK")
        assert info.value.code is ErrorCode.TIMEOUT
        assert info.value.message == (
            f"publish on {store.path}: the database stayed locked by another writer for over 0.2s"
        )
        assert store.get_version("hello", 0).version == 0  # reads are not blocked in WAL
        assert _publish(store)[0].record.version == 1  # and it recovers


def test_inv7_not_a_database_is_corrupt(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite3"
    path.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(Corrupt) as info:
        SqliteStore(path)
    assert info.value.code is ErrorCode.CORRUPT
    assert "the database file is damaged or not SQLite" in info.value.message


def test_inv7_integrity_error_is_conflict(store: SqliteStore) -> None:
    _publish(store, n=2)
    # A hand-inserted event that claims revision 1 collides with the next pointer move.
    with _raw(store) as conn, conn:
        conn.execute(
            "INSERT INTO events (seq, name, action, actor, reason, at, data, revision, prev_hash, hash)"
            " VALUES (99, 'hello', 'promote', 'x', '', 0, '{}', 1, 'p', 'h')"
        )
    with pytest.raises(Conflict) as info:
        store.move_active("hello", 0, "promote", actor="t")
    assert type(info.value) is Conflict
    assert info.value.message.startswith(f"promote on {store.path}: constraint failed: UNIQUE")
    assert store.get_version("hello", 0).state is State.CANDIDATE  # rolled back


def test_inv7_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite3"
    SqliteStore(path).close()
    with contextlib.closing(sqlite3.connect(path)) as conn, conn:
        conn.execute("INSERT INTO schema_version VALUES (99)")
    with pytest.raises(Unavailable, match="has schema version 99; this capevo understands up to 1"):
        SqliteStore(path)


def test_inv7_closed_and_unopenable(tmp_path: Path) -> None:
    store = SqliteStore(tmp_path / "r.sqlite3")
    store.close()
    store.close()
    with pytest.raises(Unavailable, match="is closed"):
        store.list_ecms()
    (tmp_path / "dir.sqlite3").mkdir()
    with pytest.raises(Unavailable) as info:
        SqliteStore(tmp_path / "dir.sqlite3")
    assert info.value.code is ErrorCode.UNAVAILABLE


# --- argument checks -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda s: s.set_state("hello", 0, "promote", actor="t"), "set_state: action must be one of deprecate, reject"),
        (lambda s: s.move_active("hello", 0, "reject", actor="t"), "move_active: action must be one of promote"),
        (lambda s: s.move_active("hello", None, Action.PROMOTE, actor="t"), "promote needs a version"),
        (lambda s: s.move_active("hello", 0, "promote", expected_active=-1, actor="t"), "version must be"),
        (lambda s: s.create_version("hello", SPEC, "ab" * 32, actor="t"), "artifact must be an ArtifactRef"),
        (lambda s: s.create_version("hello", SPEC.to_dict(), REF, actor="t"), "spec must be a PublishSpec"),
        (lambda s: s.record_gate("hello", 0, ["not", "a", "mapping"], actor="t"), "evidence must be a mapping"),
        (lambda s: s.record_gate("hello", 0, {"s": {1, 2}}, actor="t"), "evidence.s: set is not a JSON value"),
        (
            lambda s: s.create_version(
                "hello", PublishSpec.from_dict({**SPEC.to_dict(), "parent": 0.0}), REF, actor="t"
            ),
            "parent must be a non-negative integer version, got 0.0",
        ),
        (lambda s: s.capability_set("1"), "revision must be a non-negative integer"),
        (lambda s: s.history("Bad"), "ECM name 'Bad' is not a slug"),
    ],
)
def test_arguments_are_checked(store: SqliteStore, call: Any, message: str) -> None:
    _publish(store)
    with pytest.raises(Invalid) as info:
        call(store)
    assert info.value.message.startswith(message), info.value.message
    assert len(store.history()) == 1


def test_artifact_refs_lists_each_blob_once(store: SqliteStore) -> None:
    _publish(store, n=3)
    other = ArtifactRef(sha256="cd" * 32, size=1, media_type="text/plain")
    store.create_version("x", SPEC, other, actor="t")
    assert store.artifact_refs() == [REF, other]
