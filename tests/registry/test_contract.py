"""One behavioural contract for every implementation of :class:`capevo.registry.api.Registry`.

To run the suite over another implementation, add a factory to ``REGISTRY_FACTORIES``: a
function taking the pytest ``request`` (use ``request.getfixturevalue("tmp_path")`` or
``"free_port"`` for what it needs) and returning a context manager that yields a fresh,
empty registry and cleans up on exit.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from zenoh_fixtures import make_zenoh_registry  # tests/registry is on sys.path (rootdir-relative)

from capevo.errors import CapevoError, Conflict, ErrorCode, IllegalTransition, Invalid, NotFound
from capevo.records import Action, PublishSpec, State
from capevo.records.audit import GENESIS, chain_problems, event_hash
from capevo.registry.api import Registry
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry

SPEC_YAML = """
kind: code
description: Move the open gripper above the object.
applicability: {text: object on table, all: [{signal: object_height, op: "<", value: 0.05}]}
termination: {text: above object, all: [{signal: eef_object_xy_dist, op: "<", value: 0.01}]}
interface:
  inputs: [{name: eef_pos, shape: [3], dtype: float32, units: m}]
  outputs: [{name: action, shape: [7], dtype: float32, low: -1, high: 1}]
"""
SPEC: PublishSpec = parse_publish_spec(SPEC_YAML)


@contextlib.contextmanager
def make_local(request: pytest.FixtureRequest) -> Iterator[Registry]:
    root = request.getfixturevalue("tmp_path") / "registry"
    with LocalRegistry(root, actor="contract-tester") as reg:
        yield reg


RegistryFactory = Callable[[pytest.FixtureRequest], contextlib.AbstractContextManager[Registry]]
REGISTRY_FACTORIES: dict[str, RegistryFactory] = {"local": make_local, "zenoh": make_zenoh_registry}


@pytest.fixture(params=sorted(REGISTRY_FACTORIES))
def registry(request: pytest.FixtureRequest) -> Iterator[Registry]:
    with REGISTRY_FACTORIES[request.param](request) as reg:
        assert isinstance(reg, Registry)
        yield reg


def _art(tag: str) -> bytes:
    return f"def act(obs):  # {tag}\n    return [0.0] * 7\n".encode()


def _raises(exc_type: type[CapevoError], code: ErrorCode, fn: Callable[..., Any], *args: Any, **kw: Any) -> str:
    """Call ``fn`` expecting exactly ``exc_type`` with ``code``; return the message."""
    with pytest.raises(CapevoError) as info:
        fn(*args, **kw)
    assert type(info.value) is exc_type, f"{type(info.value).__name__}: {info.value}"
    assert info.value.code is code
    return info.value.message


# --- lifecycle ------------------------------------------------------------------------------
def test_full_lifecycle(registry: Registry) -> None:
    v0 = registry.publish("reach", _art("v0"), SPEC)
    assert (v0.name, v0.version, v0.state, v0.kind) == ("reach", 0, State.CANDIDATE, SPEC.kind)
    assert v0.descriptor == SPEC.descriptor and v0.interface == SPEC.interface
    assert v0.artifact.media_type == "text/x-python" and v0.artifact.size == len(_art("v0"))
    assert registry.capability_set().active == {}

    gated = registry.record_gate("reach", 0, {"success_rate": 0.9, "episodes": 20}, reason="gate run 1")
    assert gated.gate_evidence == {"success_rate": 0.9, "episodes": 20}
    assert gated.state is State.CANDIDATE

    active0 = registry.promote("reach", 0, reason="first")
    assert active0.state is State.ACTIVE
    assert registry.get_version("reach").version == 0
    assert registry.capability_set().active == {"reach": 0}

    v1 = registry.publish("reach", _art("v1"), SPEC)
    assert v1.version == 1 and v1.state is State.CANDIDATE
    registry.record_gate("reach", 1, {"success_rate": 0.95})
    assert registry.promote("reach", 1, expected_active=0).state is State.ACTIVE
    assert registry.get_version("reach", 0).state is State.SUPERSEDED
    assert registry.get_artifact("reach") == _art("v1")

    back = registry.rollback("reach", reason="regression")  # default: what was active before v1
    assert (back.version, back.state) == (0, State.ACTIVE)
    assert registry.get_version("reach", 1).state is State.SUPERSEDED
    assert registry.get_artifact("reach") == _art("v0")

    forward = registry.rollback("reach", to=1, expected_active=0)
    assert (forward.version, forward.state) == (1, State.ACTIVE)
    assert registry.get_version("reach", 0).state is State.SUPERSEDED

    assert registry.deprecate("reach", 0, reason="old").state is State.DEPRECATED
    registry.publish("reach", _art("v2"), SPEC)
    assert registry.reject("reach", 2, reason="failed gate").state is State.REJECTED
    assert registry.deprecate("reach", 2).state is State.DEPRECATED

    detail = registry.get_ecm("reach")
    assert detail.active_version == 1
    assert [(v.version, v.state) for v in detail.versions] == [
        (0, State.DEPRECATED),
        (1, State.ACTIVE),
        (2, State.DEPRECATED),
    ]
    [summary] = registry.list_ecms()
    assert (summary.name, summary.active_version, summary.latest_version, summary.n_versions) == ("reach", 1, 2, 3)

    actions = [e.action for e in registry.history("reach")]
    assert actions == [
        Action.PUBLISH,
        Action.GATE,
        Action.PROMOTE,
        Action.PUBLISH,
        Action.GATE,
        Action.PROMOTE,
        Action.ROLLBACK,
        Action.ROLLBACK,
        Action.DEPRECATE,
        Action.PUBLISH,
        Action.REJECT,
        Action.DEPRECATE,
    ]
    moves = [e for e in registry.history("reach") if e.action in (Action.PROMOTE, Action.ROLLBACK)]
    assert [(e.from_version, e.to_version, e.revision) for e in moves] == [
        (None, 0, 1),
        (0, 1, 2),
        (1, 0, 3),
        (0, 1, 4),
    ]
    assert registry.history("reach")[-4].reason == "old"
    report = registry.verify()
    assert report.ok, report.problems
    assert report.events_checked == 12 and report.blobs_checked == 3


def test_versions_are_numbered_from_zero_without_gaps(registry: Registry) -> None:
    versions = [registry.publish("grasp", _art(str(i)), SPEC).version for i in range(5)]
    assert versions == [0, 1, 2, 3, 4]
    assert registry.publish("other", _art("x"), SPEC).version == 0  # numbering is per ECM


def test_publish_with_parent(registry: Registry) -> None:
    registry.publish("grasp", _art("0"), SPEC)
    child = registry.publish("grasp", _art("1"), PublishSpec.from_dict({**SPEC.to_dict(), "parent": 0}))
    assert child.parent == 0
    msg = _raises(
        NotFound,
        ErrorCode.NOT_FOUND,
        registry.publish,
        "grasp",
        _art("2"),
        PublishSpec.from_dict({**SPEC.to_dict(), "parent": 7}),
    )
    assert msg == "parent: grasp has no version 7 to derive from"
    assert [v.version for v in registry.get_ecm("grasp").versions] == [0, 1]


def test_same_bytes_in_two_versions_share_one_blob(registry: Registry) -> None:
    a = registry.publish("grasp", b"same", SPEC)
    b = registry.publish("grasp", b"same", SPEC)
    assert a.artifact == b.artifact
    assert registry.get_artifact("grasp", 1) == b"same"
    assert registry.verify().blobs_checked == 1


# --- illegal moves ----------------------------------------------------------------------------
def _three_states(registry: Registry) -> None:
    """reach: v0 superseded, v1 active, v2 candidate, v3 rejected."""
    for i in range(4):
        registry.publish("reach", _art(str(i)), SPEC)
    registry.promote("reach", 0)
    registry.promote("reach", 1)
    registry.reject("reach", 3)


ILLEGAL = [
    ("promote", (1,), {}, "cannot promote reach v1: it is active (no action is allowed)"),
    ("promote", (0,), {}, "cannot promote reach v0: it is superseded (allowed: deprecate, rollback)"),
    ("promote", (3,), {}, "cannot promote reach v3: it is rejected (allowed: deprecate)"),
    ("deprecate", (1,), {}, "cannot deprecate reach v1: it is active (no action is allowed)"),
    ("reject", (1,), {}, "cannot reject reach v1: it is active (no action is allowed)"),
    ("reject", (0,), {}, "cannot reject reach v0: it is superseded (allowed: deprecate, rollback)"),
    ("reject", (3,), {}, "cannot reject reach v3: it is rejected (allowed: deprecate)"),
    ("rollback", (), {"to": 2}, "cannot rollback reach v2: it is candidate (allowed: deprecate, promote, reject)"),
    ("rollback", (), {"to": 1}, "cannot rollback reach v1: it is active (no action is allowed)"),
    (
        "record_gate",
        (1, {"x": 1}),
        {},
        "cannot gate reach v1: it is active (gate evidence is recorded on candidates only)",
    ),
    (
        "record_gate",
        (0, {"x": 1}),
        {},
        "cannot gate reach v0: it is superseded (gate evidence is recorded on candidates only)",
    ),
]


@pytest.mark.parametrize(
    ("method", "args", "kwargs", "message"), ILLEGAL, ids=[f"{m}{a[:1]}{k}" for m, a, k, _ in ILLEGAL]
)
def test_illegal_transitions_are_refused_and_change_nothing(
    registry: Registry, method: str, args: tuple[Any, ...], kwargs: dict[str, Any], message: str
) -> None:
    _three_states(registry)
    before = (registry.get_ecm("reach"), registry.history("reach"), registry.capability_set())
    msg = _raises(IllegalTransition, ErrorCode.ILLEGAL_TRANSITION, getattr(registry, method), "reach", *args, **kwargs)
    assert msg == message
    assert (registry.get_ecm("reach"), registry.history("reach"), registry.capability_set()) == before


def test_deprecated_is_terminal(registry: Registry) -> None:
    registry.publish("reach", _art("0"), SPEC)
    registry.deprecate("reach", 0)
    for method, args, kwargs in [
        ("deprecate", (0,), {}),
        ("promote", (0,), {}),
        ("reject", (0,), {}),
        ("rollback", (), {"to": 0}),
    ]:
        msg = _raises(
            IllegalTransition, ErrorCode.ILLEGAL_TRANSITION, getattr(registry, method), "reach", *args, **kwargs
        )
        assert msg == f"cannot {method} reach v0: it is deprecated (no action is allowed)"
    assert registry.get_version("reach", 0).state is State.DEPRECATED


def test_rollback_to_superseded_is_refused_when_deprecated(registry: Registry) -> None:
    for i in range(2):
        registry.publish("reach", _art(str(i)), SPEC)
    registry.promote("reach", 0)
    registry.promote("reach", 1)
    registry.deprecate("reach", 0)
    msg = _raises(IllegalTransition, ErrorCode.ILLEGAL_TRANSITION, registry.rollback, "reach")
    assert msg == "cannot rollback reach v0: it is deprecated (no action is allowed)"


def test_rollback_with_nothing_before_is_not_found(registry: Registry) -> None:
    registry.publish("reach", _art("0"), SPEC)
    msg = _raises(NotFound, ErrorCode.NOT_FOUND, registry.rollback, "reach")
    assert msg == "cannot roll back reach: it has no active version"
    registry.promote("reach", 0)
    msg = _raises(NotFound, ErrorCode.NOT_FOUND, registry.rollback, "reach")
    assert msg == "cannot roll back reach: v0 is the first version ever active, nothing was active before it"


def test_default_rollback_follows_the_pointer_log_not_version_order(registry: Registry) -> None:
    for i in range(3):
        registry.publish("reach", _art(str(i)), SPEC)
    registry.promote("reach", 2)
    registry.promote("reach", 0)
    assert registry.rollback("reach").version == 2  # not v1, which was never active


# --- compare-and-swap -------------------------------------------------------------------------
def test_stale_expected_active_is_a_conflict_and_changes_nothing(registry: Registry) -> None:
    for i in range(3):
        registry.publish("reach", _art(str(i)), SPEC)
    registry.promote("reach", 0)
    registry.promote("reach", 1, expected_active=0)
    before = (registry.get_ecm("reach"), registry.history("reach"), registry.capability_set())

    msg = _raises(Conflict, ErrorCode.CONFLICT, registry.promote, "reach", 2, expected_active=0)
    assert msg == "cannot promote reach: expected active v0, but the active version is v1"
    msg = _raises(Conflict, ErrorCode.CONFLICT, registry.rollback, "reach", expected_active=2)
    assert msg == "cannot rollback reach: expected active v2, but the active version is v1"
    assert (registry.get_ecm("reach"), registry.history("reach"), registry.capability_set()) == before

    assert registry.promote("reach", 2, expected_active=1).state is State.ACTIVE


def test_expected_active_when_nothing_is_active(registry: Registry) -> None:
    registry.publish("reach", _art("0"), SPEC)
    msg = _raises(Conflict, ErrorCode.CONFLICT, registry.promote, "reach", 0, expected_active=3)
    assert msg == "cannot promote reach: expected active v3, but the active version is none"


# --- capability set ---------------------------------------------------------------------------
def test_capability_set_at_every_past_revision(registry: Registry) -> None:
    assert registry.capability_set().to_dict() == {"revision": 0, "active": {}}
    for name in ("reach", "grasp"):
        for i in range(3):
            registry.publish(name, _art(f"{name}{i}"), SPEC)
    registry.promote("reach", 0)  # r1
    registry.promote("grasp", 1)  # r2
    registry.promote("reach", 2)  # r3
    registry.record_gate("grasp", 0, {"ok": True})  # no pointer move, no revision
    registry.rollback("reach")  # r4 -> reach 0
    registry.promote("grasp", 2, expected_active=1)  # r5
    expected = {
        0: {},
        1: {"reach": 0},
        2: {"reach": 0, "grasp": 1},
        3: {"reach": 2, "grasp": 1},
        4: {"reach": 0, "grasp": 1},
        5: {"reach": 0, "grasp": 2},
    }
    for rev, active in expected.items():
        cap = registry.capability_set(rev)
        assert (cap.revision, dict(cap.active)) == (rev, active)
    assert registry.capability_set() == registry.capability_set(5)
    msg = _raises(NotFound, ErrorCode.NOT_FOUND, registry.capability_set, 6)
    assert msg == "revision 6 has not been reached; the registry is at revision 5"
    _raises(Invalid, ErrorCode.INVALID, registry.capability_set, -1)


# --- history ----------------------------------------------------------------------------------
def test_history_is_one_hash_chain(registry: Registry) -> None:
    registry.publish("reach", _art("0"), SPEC)
    registry.publish("grasp", _art("0"), SPEC)
    registry.promote("reach", 0, reason="why not")
    registry.record_gate("grasp", 0, {"success_rate": 0.5, "curve": [0.1, 0.2]})
    registry.reject("grasp", 0)
    reach, grasp = registry.history("reach"), registry.history("grasp")
    assert [e.seq for e in reach] == [1, 3] and [e.seq for e in grasp] == [2, 4, 5]
    merged = sorted(reach + grasp, key=lambda e: e.seq)
    assert merged[0].prev_hash == GENESIS
    assert chain_problems(merged) == []
    for ev in merged:
        assert ev.hash == event_hash(ev.to_dict())
    promote = reach[1]
    assert (promote.action, promote.version, promote.from_state, promote.to_state) == (
        Action.PROMOTE,
        0,
        State.CANDIDATE,
        State.ACTIVE,
    )
    assert (promote.reason, promote.revision, promote.from_version, promote.to_version) == ("why not", 1, None, 0)
    # Over Zenoh the event also says how the actor is known ("auth"); see test_zenoh_hardening.
    assert {k: v for k, v in grasp[1].data.items() if k != "auth"} == {
        "evidence": {"success_rate": 0.5, "curve": [0.1, 0.2]}
    }
    assert reach[0].data["sha256"] == registry.get_version("reach", 0).artifact.sha256


# --- artifacts --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "payload", [b"", bytes(range(256)) * 4, b"\x00" * (3 << 20) + b"tail"], ids=["empty", "all-bytes", "3MB"]
)
def test_artifact_round_trip(registry: Registry, payload: bytes) -> None:
    rec = registry.publish("policy", payload, parse_publish_spec("kind: neural\ndescription: a policy\n"))
    assert rec.artifact.size == len(payload) and rec.artifact.media_type == "application/zip"
    assert registry.get_artifact("policy", 0) == payload
    registry.promote("policy", 0)
    assert registry.get_artifact("policy") == payload


# --- validation and lookups -------------------------------------------------------------------
BAD_NAMES = ["../x", "a/b", "*", "**", "$*", "A", "", "a" * 65, "..", ".", "a..b", "-a", "a b", "active", "ü"]


@pytest.mark.parametrize("name", BAD_NAMES)
def test_bad_names_are_invalid(registry: Registry, name: str) -> None:
    calls: list[tuple[Callable[..., Any], tuple[Any, ...]]] = [
        (registry.publish, (name, b"x", SPEC)),
        (registry.get_ecm, (name,)),
        (registry.get_version, (name, 0)),
        (registry.get_version, (name,)),
        (registry.get_artifact, (name,)),
        (registry.history, (name,)),
        (registry.promote, (name, 0)),
        (registry.rollback, (name,)),
        (registry.deprecate, (name, 0)),
        (registry.reject, (name, 0)),
        (registry.record_gate, (name, 0, {})),
    ]
    for fn, args in calls:
        msg = _raises(Invalid, ErrorCode.INVALID, fn, *args)
        assert "ECM name" in msg, msg
    assert registry.list_ecms() == []


@pytest.mark.parametrize("name", [*BAD_NAMES[:4], 7, None, b"reach"])
def test_resolving_a_good_name_lets_no_bad_name_through(registry: Registry, name: Any) -> None:
    """The client keeps the active-version key of each name it resolved (issue 21); a bad name,
    or one that is not a str, must still be refused, before and after a good one is resolved."""
    registry.publish("reach", b"x", SPEC)
    registry.promote("reach", 0)
    for _ in range(2):
        assert registry.get_version("reach").version == 0
        _raises(Invalid, ErrorCode.INVALID, registry.get_version, name)


@pytest.mark.parametrize("version", [-1, True, 1.5, "0"])
def test_bad_versions_are_invalid(registry: Registry, version: Any) -> None:
    registry.publish("reach", b"x", SPEC)
    msg = _raises(Invalid, ErrorCode.INVALID, registry.get_version, "reach", version)
    assert msg == f"version must be a non-negative integer, got {version!r}"
    _raises(Invalid, ErrorCode.INVALID, registry.promote, "reach", version)


def test_unknown_things_are_not_found(registry: Registry) -> None:
    for fn, args in [
        (registry.get_ecm, ("ghost",)),
        (registry.get_version, ("ghost",)),
        (registry.get_version, ("ghost", 0)),
        (registry.get_artifact, ("ghost",)),
        (registry.history, ("ghost",)),
        (registry.promote, ("ghost", 0)),
        (registry.rollback, ("ghost",)),
        (registry.deprecate, ("ghost", 0)),
        (registry.reject, ("ghost", 0)),
        (registry.record_gate, ("ghost", 0, {})),
    ]:
        assert _raises(NotFound, ErrorCode.NOT_FOUND, fn, *args) == "no ECM named 'ghost'"
    registry.publish("reach", b"x", SPEC)
    assert _raises(NotFound, ErrorCode.NOT_FOUND, registry.get_version, "reach", 9) == (
        "reach has no version 9 (latest is v0)"
    )
    assert _raises(NotFound, ErrorCode.NOT_FOUND, registry.get_version, "reach") == (
        "reach has no active version (promote one first)"
    )
    _raises(NotFound, ErrorCode.NOT_FOUND, registry.get_artifact, "reach")
    _raises(NotFound, ErrorCode.NOT_FOUND, registry.promote, "reach", 1)


@pytest.mark.parametrize(
    ("evidence", "field"),
    [
        ({"loss": math.nan}, "evidence.loss"),
        ({"curve": [1.0, math.inf]}, "evidence.curve[1]"),
        ({"obj": object()}, "evidence.obj"),
        ({1: "int key"}, "evidence"),
    ],
    ids=["nan", "inf", "object", "int-key"],
)
def test_bad_gate_evidence_is_invalid(registry: Registry, evidence: Any, field: str) -> None:
    registry.publish("reach", b"x", SPEC)
    msg = _raises(Invalid, ErrorCode.INVALID, registry.record_gate, "reach", 0, evidence)
    assert msg.startswith(field), msg
    assert registry.get_version("reach", 0).gate_evidence is None


def test_bad_artifact_and_spec_are_invalid(registry: Registry) -> None:
    assert "artifact must be bytes" in _raises(Invalid, ErrorCode.INVALID, registry.publish, "reach", "text", SPEC)
    assert "spec must be a PublishSpec" in _raises(
        Invalid, ErrorCode.INVALID, registry.publish, "reach", b"x", SPEC.to_dict()
    )
    assert registry.list_ecms() == []


def test_verify_of_fresh_and_used_registry(registry: Registry) -> None:
    empty = registry.verify()
    assert (empty.ok, empty.events_checked, empty.blobs_checked) == (True, 0, 0)
    registry.publish("reach", b"a", SPEC)
    registry.publish("reach", b"b", SPEC)
    registry.promote("reach", 1)
    report = registry.verify()
    assert report.ok and report.problems == ()
    assert (report.events_checked, report.blobs_checked) == (3, 2)
