"""LocalRegistry beyond the shared contract: layout, listeners, limits, tampering, properties.

Invariant numbers refer to the docstring of :mod:`capevo.registry.local`.
"""

from __future__ import annotations

import contextlib
import getpass
import hashlib
import logging
import math
import random
import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from procs import run_in_threads

from capevo.errors import CapevoError, Corrupt, ErrorCode, Invalid, NotFound, TooLarge, Unavailable
from capevo.records import (
    COMPARISON_OPS,
    Action,
    AuditEvent,
    Condition,
    Descriptor,
    EcmVersion,
    Interface,
    IOSpec,
    Kind,
    Origin,
    Predicate,
    Provenance,
    PublishSpec,
    State,
)
from capevo.records.names import MAX_NAME_LENGTH, RESERVED, validate_name
from capevo.registry.descriptor import dump_publish_spec, parse_publish_spec
from capevo.registry.local import (
    BLOB_DIRNAME,
    DB_FILENAME,
    EventListener,
    LocalRegistry,
    default_actor,
)

SPEC = parse_publish_spec("kind: code\ndescription: test skill\n")


class RecordingListener:
    """In-memory :class:`EventListener` that keeps every ``(event, record)`` it is given."""

    def __init__(self) -> None:
        self.calls: list[tuple[AuditEvent, EcmVersion]] = []
        self._lock = threading.Lock()

    def on_event(self, event: AuditEvent, record: EcmVersion) -> None:
        with self._lock:
            self.calls.append((event, record))

    @property
    def events(self) -> list[AuditEvent]:
        with self._lock:
            return [e for e, _ in self.calls]


@pytest.fixture
def reg(tmp_path: Path) -> Iterator[LocalRegistry]:
    with LocalRegistry(tmp_path / "reg", actor="tester") as r:
        yield r


def _blob_path(reg: LocalRegistry, sha: str) -> Path:
    return reg.root / BLOB_DIRNAME / sha[:2] / sha[2:]


# --- layout and lifetime ----------------------------------------------------------------------
def test_layout_on_disk(tmp_path: Path) -> None:
    root = tmp_path / "a" / "b"
    with LocalRegistry(root) as reg:
        rec = reg.publish("reach", b"payload", SPEC)
        sha = hashlib.sha256(b"payload").hexdigest()
        assert rec.artifact.sha256 == sha
        assert (root / DB_FILENAME).is_file()
        assert _blob_path(reg, sha).read_bytes() == b"payload"
        assert reg.store.pragma("journal_mode") == "wal"
        assert reg.store.pragma("synchronous") == 2  # FULL
        assert reg.store.schema_version() == 1


def test_state_survives_reopen(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path) as reg:
        reg.publish("reach", b"0", SPEC)
        reg.promote("reach", 0)
    with LocalRegistry(tmp_path) as again:
        assert again.get_version("reach").version == 0
        assert again.get_artifact("reach") == b"0"
        assert again.verify().ok


def test_two_registries_on_one_root_see_each_other(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path) as a, LocalRegistry(tmp_path) as b:
        a.publish("reach", b"0", SPEC)
        assert b.publish("reach", b"1", SPEC).version == 1
        b.promote("reach", 1)
        assert a.get_version("reach").version == 1
        assert [e.seq for e in a.history("reach")] == [1, 2, 3]


def test_close_is_idempotent_and_later_calls_are_unavailable(tmp_path: Path) -> None:
    reg = LocalRegistry(tmp_path)
    reg.publish("reach", b"0", SPEC)
    reg.close()
    reg.close()
    for fn, args in [(reg.list_ecms, ()), (reg.get_artifact, ("reach",)), (reg.publish, ("reach", b"1", SPEC))]:
        with pytest.raises(Unavailable) as info:
            fn(*args)
        assert info.value.code is ErrorCode.UNAVAILABLE
        assert info.value.message == f"the registry at {tmp_path} is closed"


def test_actor_default_constructor_and_per_call(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path) as reg:
        reg.publish("reach", b"0", SPEC)
        reg.promote("reach", 0, actor="gate-bot")
        first, second = reg.history("reach")
        assert first.actor == default_actor() == getpass.getuser()
        assert second.actor == "gate-bot"
        assert reg.get_version("reach", 0).created_by == getpass.getuser()
    with LocalRegistry(tmp_path, actor="learner-7") as reg:
        assert reg.publish("reach", b"1", SPEC).created_by == "learner-7"
        with pytest.raises(Invalid, match="actor must not be empty"):
            reg.deprecate("reach", 1, actor="")
    with pytest.raises(Invalid, match="actor must be a string"):
        LocalRegistry(tmp_path, actor=3)  # type: ignore[arg-type]


# --- invariant 1: blob first, metadata second -------------------------------------------------
def test_inv1_blob_is_written_before_metadata(reg: LocalRegistry) -> None:
    # The metadata transaction fails (unknown parent) after the blob was stored: what is
    # left is an orphan blob, never a version row without bytes.
    bad = PublishSpec.from_dict({**SPEC.to_dict(), "parent": 5})
    with pytest.raises(NotFound):
        reg.publish("reach", b"orphan bytes", bad)
    assert _blob_path(reg, hashlib.sha256(b"orphan bytes").hexdigest()).is_file()
    assert reg.list_ecms() == []
    report = reg.verify()
    assert report.ok and report.blobs_checked == 0


# --- invariant 2: validation before writing ---------------------------------------------------
def test_inv2_too_large_artifact_stores_nothing(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path, max_artifact_bytes=10) as reg:
        with pytest.raises(TooLarge) as info:
            reg.publish("reach", b"x" * 11, SPEC)
        assert info.value.code is ErrorCode.TOO_LARGE
        assert info.value.message == "artifact is 11 bytes; the limit is 10"
        assert reg.publish("reach", b"x" * 10, SPEC).version == 0
        assert list(reg.blobs) == [hashlib.sha256(b"x" * 10).hexdigest()]


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (
            PublishSpec(
                kind=Kind.CODE,
                descriptor=Descriptor(
                    description="d", termination=Predicate(all=(Condition(signal="s", op="<", value=math.nan),))
                ),
            ),
            "termination.all[0].value: must be a finite number, got nan",
        ),
        (
            PublishSpec(kind=Kind.CODE, descriptor=Descriptor(description="")),
            "description: '' should be non-empty",
        ),
        (
            PublishSpec(
                kind=Kind.CODE,
                descriptor=Descriptor(description="d"),
                interface=Interface(inputs=(IOSpec(name="x", shape=(0,)),)),
            ),
            "interface.inputs[0].shape[0]: 0 is less than the minimum of 1",
        ),
        (
            PublishSpec(kind="code", descriptor=Descriptor(description="d")),  # type: ignore[arg-type]
            "spec: cannot be written as a descriptor",
        ),
    ],
    ids=["nan", "empty-description", "zero-shape", "kind-not-enum"],
)
def test_inv2_specs_built_in_code_meet_the_schema(reg: LocalRegistry, spec: PublishSpec, message: str) -> None:
    with pytest.raises(Invalid) as info:
        reg.publish("reach", b"x", spec)
    assert info.value.message.startswith(message), info.value.message
    assert reg.list_ecms() == [] and list(reg.blobs) == []


@pytest.mark.parametrize("limit", [-1, 1.5, True])
def test_inv2_bad_max_artifact_bytes(tmp_path: Path, limit: Any) -> None:
    with pytest.raises(Invalid, match="max_artifact_bytes must be a non-negative integer"):
        LocalRegistry(tmp_path, max_artifact_bytes=limit)


def test_inv2_reason_is_checked(reg: LocalRegistry) -> None:
    reg.publish("reach", b"x", SPEC)
    with pytest.raises(Invalid, match="reason is 5000 characters; the limit is 4096"):
        reg.reject("reach", 0, reason="r" * 5000)
    with pytest.raises(Invalid, match="reason must be a string"):
        reg.reject("reach", 0, reason=None)  # type: ignore[arg-type]
    assert reg.get_version("reach", 0).state is State.CANDIDATE


# --- invariant 3: listeners -------------------------------------------------------------------
class _SeesCommitted:
    """Checks from a second connection that the mutation is already durable when told."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.seen: list[int] = []

    def on_event(self, event: Any, record: Any) -> None:
        with LocalRegistry(self.root) as other:
            self.seen.append(other.history(event.name)[-1].seq)


class _Broken:
    def on_event(self, event: Any, record: Any) -> None:
        raise RuntimeError("listener bug")


def test_inv3_listeners_get_every_committed_mutation_in_order(tmp_path: Path) -> None:
    rec = RecordingListener()
    sees = _SeesCommitted(tmp_path)
    assert isinstance(rec, EventListener)
    with LocalRegistry(tmp_path, listeners=[rec, sees]) as reg:
        reg.publish("reach", b"0", SPEC)
        reg.record_gate("reach", 0, {"ok": 1})
        reg.promote("reach", 0)
        reg.publish("reach", b"1", SPEC)
        reg.reject("reach", 1)
        reg.deprecate("reach", 1)
        with pytest.raises(CapevoError):
            reg.promote("reach", 1)  # refused: no event
        assert [e.action for e in rec.events] == [
            Action.PUBLISH,
            Action.GATE,
            Action.PROMOTE,
            Action.PUBLISH,
            Action.REJECT,
            Action.DEPRECATE,
        ]
        assert [e.seq for e in rec.events] == sees.seen == [1, 2, 3, 4, 5, 6]
        assert rec.calls[2][1] == reg.get_version("reach", 0)
        reg.remove_listener(rec)
        reg.publish("reach", b"2", SPEC)
        assert len(rec.calls) == 6 and sees.seen[-1] == 7


class _Jitter:
    """Sleeps a random moment, widening the gap between commit and the next listener."""

    def __init__(self) -> None:
        self.rng = random.Random(7)

    def on_event(self, event: Any, record: Any) -> None:
        time.sleep(self.rng.uniform(0, 0.001))


def test_inv3_listeners_see_commit_order_under_threads(tmp_path: Path) -> None:
    rec = RecordingListener()
    with LocalRegistry(tmp_path, listeners=[_Jitter(), rec]) as reg:

        def work(i: int) -> None:
            for j in range(15):
                reg.publish(f"ecm-{i % 2}", f"{i}-{j}".encode(), SPEC)

        run_in_threads(work, 6)
        assert [e.seq for e in rec.events] == list(range(1, 91))
        for name in ("ecm-0", "ecm-1"):
            assert [e.version for e in rec.events if e.name == name] == list(range(45))


def test_inv3_a_failing_listener_cannot_fail_the_mutation(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    after = RecordingListener()
    with LocalRegistry(tmp_path, listeners=[_Broken()]) as reg:
        reg.add_listener(after)
        with caplog.at_level(logging.ERROR, logger="capevo.registry.local"):
            rec = reg.publish("reach", b"0", SPEC)
        assert rec.version == 0 and reg.get_version("reach", 0) == rec
        assert len(after.calls) == 1
        assert "failed on audit event seq 1 (publish reach)" in caplog.text
        assert "listener bug" in caplog.text
    with LocalRegistry(tmp_path) as reg, pytest.raises(Invalid, match="listener must have on_event"):
        reg.add_listener(object())  # type: ignore[arg-type]


# --- invariant 4: artifacts are checked -------------------------------------------------------
def test_inv4_tampered_blob_is_never_served(reg: LocalRegistry) -> None:
    rec = reg.publish("reach", b"good bytes", SPEC)
    path = _blob_path(reg, rec.artifact.sha256)
    path.write_bytes(b"evil bytes")
    with pytest.raises(Corrupt) as info:
        reg.get_artifact("reach", 0)
    assert info.value.code is ErrorCode.CORRUPT
    assert info.value.message == (
        f"reach v0: blob {rec.artifact.sha256} is corrupt: its content hashes to "
        f"{hashlib.sha256(b'evil bytes').hexdigest()}"
    )
    path.unlink()
    with pytest.raises(Corrupt, match=f"reach v0: its artifact blob {rec.artifact.sha256} is missing"):
        reg.get_artifact("reach", 0)
    # Publishing the same bytes again repairs the store.
    reg.publish("reach", b"good bytes", SPEC)
    assert reg.get_artifact("reach", 0) == b"good bytes"


def test_inv4_64mb_artifact_round_trip(reg: LocalRegistry) -> None:
    payload = hashlib.sha256(b"seed").digest() * (2 * 2**20)  # 64 MiB, not all zeros
    rec = reg.publish("policy", payload, parse_publish_spec("kind: neural\ndescription: big\n"))
    assert rec.artifact.size == 64 * 2**20
    assert reg.get_artifact("policy", 0) == payload
    assert reg.verify().ok


# --- invariant 5: verify finds what is wrong --------------------------------------------------
def _lifecycle(reg: LocalRegistry) -> None:
    reg.publish("reach", b"v0", SPEC)
    reg.publish("reach", b"v1", SPEC)
    reg.record_gate("reach", 1, {"success": 0.8})
    reg.promote("reach", 0)
    reg.promote("reach", 1)
    reg.publish("grasp", b"g0", SPEC)


def _sql(reg: LocalRegistry, statement: str, *args: Any) -> None:
    # A separate, plain connection: what someone editing the file by hand would do.
    with contextlib.closing(sqlite3.connect(reg.root / DB_FILENAME)) as conn, conn:
        conn.execute(statement, args)


def test_inv5_verify_reports_blob_tamper_and_loss(reg: LocalRegistry) -> None:
    _lifecycle(reg)
    v0 = reg.get_version("reach", 0).artifact.sha256
    g0 = reg.get_version("grasp", 0).artifact.sha256
    _blob_path(reg, v0).write_bytes(b"v0 but changed")
    _blob_path(reg, g0).unlink()
    report = reg.verify()
    assert not report.ok
    assert sorted(report.problems) == sorted(
        [
            f"blob {v0}: content hashes to {hashlib.sha256(b'v0 but changed').hexdigest()} (corrupt or tampered); "
            "used by reach v0",
            f"blob {g0}: missing (expected at {_blob_path(reg, g0)}); used by grasp v0",
        ]
    )


@pytest.mark.parametrize(
    ("statement", "args", "problem"),
    [
        (
            "UPDATE events SET reason = 'nothing to see' WHERE seq = 4",
            (),
            "audit event seq 4: hash does not match its contents (tampered)",
        ),
        ("DELETE FROM events WHERE seq = 2", (), "audit event seq 3: expected seq 2 (gap or reorder)"),
        (
            "UPDATE versions SET state = 'active' WHERE name = 'grasp'",
            (),
            "grasp v0: stored state active, audit history says candidate",
        ),
        (
            "UPDATE versions SET sha256 = ? WHERE name = 'reach' AND version = 1",
            ("f" * 64,),
            "reach v1: stored artifact ('" + "f" * 64,
        ),
        (
            "UPDATE versions SET gate_evidence = '{\"success\": 1.0}' WHERE version = 1",
            (),
            "reach v1: stored gate evidence differs from the audit history",
        ),
        ("UPDATE ecms SET active_version = 0 WHERE name = 'reach'", (), "reach: active pointer is v0"),
        ("DELETE FROM pointer_moves WHERE revision = 2", (), "capability set at revision 1 is {'reach': 0}"),
    ],
    ids=["event-reason", "event-deleted", "state", "artifact", "evidence", "pointer", "pointer-log"],
)
def test_inv5_verify_reports_database_tamper(
    reg: LocalRegistry, statement: str, args: tuple[Any, ...], problem: str
) -> None:
    _lifecycle(reg)
    assert reg.verify().ok
    _sql(reg, statement, *args)
    report = reg.verify()
    assert any(p.startswith(problem) for p in report.problems), report.problems


# --- thread safety ----------------------------------------------------------------------------
def test_threads_share_one_registry(reg: LocalRegistry) -> None:
    def work(i: int) -> None:
        for j in range(10):
            reg.publish("reach", f"{i}-{j}".encode(), SPEC)
            reg.get_version("reach", 0)

    run_in_threads(work, 6)
    versions = [v.version for v in reg.get_ecm("reach").versions]
    assert versions == list(range(60))
    assert sorted(reg.get_artifact("reach", v) for v in versions) == sorted(
        f"{i}-{j}".encode() for i in range(6) for j in range(10)
    )
    assert reg.verify().ok


# --- properties: names and descriptors as publish sees them -----------------------------------
valid_names = st.from_regex(r"[a-z0-9][a-z0-9._-]{0,63}", fullmatch=True).filter(
    lambda n: ".." not in n and n not in RESERVED
)
finite = st.floats(allow_nan=False, allow_infinity=False)
signals = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,63}", fullmatch=True)
io_names = st.from_regex(r"[A-Za-z_][A-Za-z0-9_.]{0,63}", fullmatch=True)
short_text = st.text(max_size=40)


@st.composite
def io_specs(draw: st.DrawFn) -> IOSpec:
    bounds = draw(st.one_of(st.none(), st.tuples(finite, finite).map(sorted)))
    low, high = (None, None) if bounds is None else (bounds[0], bounds[1])
    if draw(st.booleans()):
        low, high = (low, None) if draw(st.booleans()) else (None, high)
    return IOSpec(
        name=draw(io_names),
        shape=tuple(draw(st.lists(st.integers(1, 1_000_000), max_size=8))),
        dtype=draw(st.sampled_from(["float32", "float64", "int32", "int64", "bool", "uint8"])),
        low=low,
        high=high,
        units=draw(st.one_of(st.none(), st.text(max_size=32))),
    )


def _unique(specs: list[IOSpec]) -> tuple[IOSpec, ...]:
    seen: dict[str, IOSpec] = {}
    for s in specs:
        seen.setdefault(s.name, s)
    return tuple(seen.values())


predicates = st.builds(
    Predicate,
    text=short_text,
    all=st.lists(
        st.builds(Condition, signal=signals, op=st.sampled_from(COMPARISON_OPS), value=finite), max_size=4
    ).map(tuple),
)
publish_specs = st.builds(
    PublishSpec,
    kind=st.sampled_from(Kind),
    descriptor=st.builds(
        Descriptor, description=st.text(min_size=1, max_size=200), applicability=predicates, termination=predicates
    ),
    interface=st.builds(
        Interface,
        inputs=st.lists(io_specs(), max_size=4).map(_unique),
        outputs=st.lists(io_specs(), max_size=4).map(_unique),
    ),
    media_type=st.one_of(st.none(), st.from_regex(r"[a-z0-9.+-]{1,20}/[a-z0-9.+-]{1,20}", fullmatch=True)),
    parent=st.none(),
    origin=st.sampled_from(Origin),
    provenance=st.builds(
        Provenance,
        learner_id=st.one_of(st.none(), short_text),
        config_hash=st.one_of(st.none(), st.from_regex(r"[0-9a-f]{8,64}", fullmatch=True)),
        traces=st.lists(short_text, max_size=3).map(tuple),
    ),
)


@settings(max_examples=100, deadline=None)
@given(publish_specs)
def test_property_descriptor_round_trip(spec: PublishSpec) -> None:
    assert parse_publish_spec(dump_publish_spec(spec)) == spec


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=300), st.binary(max_size=300)))
def test_property_arbitrary_text_is_a_spec_or_invalid(text: str | bytes) -> None:
    try:
        parse_publish_spec(text)
    except Invalid as exc:
        assert exc.code is ErrorCode.INVALID


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=12), inner, max_size=4)),
    max_leaves=20,
)
schema_keys = st.sampled_from(
    ["kind", "description", "applicability", "termination", "interface", "media_type", "parent", "origin",
     "provenance", "inputs", "outputs", "name", "shape", "all", "signal", "op", "value", "low", "high", "traces"]
)  # fmt: skip
near_miss_docs = st.dictionaries(
    schema_keys,
    st.one_of(
        json_values,
        st.sampled_from(["code", "neural", "<", "float32", "manual"]),
        st.dictionaries(schema_keys, json_values),
    ),
    max_size=8,
)


@settings(max_examples=150, deadline=None)
@given(near_miss_docs)
def test_property_structured_near_misses_are_specs_or_invalid(doc: dict[str, Any]) -> None:
    try:
        parse_publish_spec(yaml.safe_dump(doc))
    except Invalid as exc:
        field = exc.details.get("field")
        assert field is None or exc.message.startswith(f"{field}:"), exc.message


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=80), valid_names))
def test_property_names_are_slugs_or_invalid(name: str) -> None:
    try:
        out = validate_name(name)
    except Invalid as exc:
        assert exc.code is ErrorCode.INVALID and exc.details == {"field": "name"}
        return
    assert out == name and len(name) <= MAX_NAME_LENGTH
    assert not set(name) & set("/*$?#\\ ") and name not in (".", "..") and ".." not in name
    assert name == name.lower() and name.isascii()


@pytest.fixture(scope="module")
def shared_reg(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalRegistry]:
    with LocalRegistry(tmp_path_factory.mktemp("prop"), actor="prop") as r:
        yield r


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=valid_names, spec=publish_specs, artifact=st.binary(max_size=64))
def test_property_publish_stores_what_it_was_given(
    shared_reg: LocalRegistry, name: str, spec: PublishSpec, artifact: bytes
) -> None:
    rec = shared_reg.publish(name, artifact, spec)
    assert (rec.kind, rec.descriptor, rec.interface, rec.origin, rec.provenance) == (
        spec.kind,
        spec.descriptor,
        spec.interface,
        spec.origin,
        spec.provenance,
    )
    assert rec.artifact.media_type == spec.resolved_media_type
    assert shared_reg.get_version(name, rec.version) == rec
    assert shared_reg.get_artifact(name, rec.version) == artifact


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.text(max_size=70), version=st.one_of(st.none(), st.integers(-5, 5)))
def test_property_lookups_raise_only_invalid_or_not_found(shared_reg: LocalRegistry, name: str, version: Any) -> None:
    try:
        rec = shared_reg.get_version(name, version)
    except (Invalid, NotFound) as exc:
        assert exc.code in (ErrorCode.INVALID, ErrorCode.NOT_FOUND)
    else:
        assert rec.name == validate_name(name) and (version is None or rec.version == version)


@pytest.mark.parametrize("parent", [2**63, 9.223372036854776e18, 10**30])
def test_a_parent_beyond_int64_is_invalid_not_an_internal_error(parent: object) -> None:
    # Found by the Zenoh fuzz test: a parent SQLite cannot hold reached the store and failed there.
    with pytest.raises(Invalid) as exc:
        parse_publish_spec(f"kind: code\ndescription: d\nparent: {parent}\n")
    assert exc.value.details.get("field") == "parent"
