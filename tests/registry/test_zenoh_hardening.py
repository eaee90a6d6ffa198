"""Issue 22: what a legitimate but low-privilege user must not be able to do, over real Zenoh.

A secured server (rita=reader, lena=learner, olga=operator) runs in its own process with
Zenoh usrpwd and access control on; open servers run where the test needs one.

* forged actor: the audit actor is the authenticated user, whatever the body or the key says;
* self-declared trust: a learner cannot publish ``origin: manual`` (what the runtime runs
  outside its sandbox);
* verify flood: 70 concurrent ``verify`` loops do not make an ordinary resolve fail;
* lone surrogates are ``invalid`` at every boundary and leave no blob behind;
* temporary blob files of a SIGKILLed server are removed when it starts again;
* non-canonical numbers (``parent: 1.0``) are invalid, as the key space's are.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from procs import ServerProcess, start_server
from zenoh_fixtures import raw_query, raw_session, unique_name

from capevo.errors import CapevoError, ErrorCode, Forbidden, Invalid
from capevo.records import Action, Attribution, Auth, Descriptor, Kind, Origin, PublishSpec
from capevo.registry.client import Client
from capevo.registry.descriptor import parse_publish_spec, spec_from_document
from capevo.registry.keys import COMMANDS, CommandRoute, Keys
from capevo.registry.local import LocalRegistry
from capevo.registry.server_config import access_control_for, parse_server_config
from capevo.registry.wire import loads

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"

pytestmark = pytest.mark.zenoh

LEARNED = parse_publish_spec("kind: code\ndescription: learned skill\norigin: llm\n")
MANUAL = parse_publish_spec("kind: code\ndescription: hand-written skill\norigin: manual\n")
CONFIG = """
users:
  rita: {password: rita-pw, roles: [reader]}
  lena: {password: lena-pw, roles: [learner]}
  olga: {password: olga-pw, roles: [operator]}
"""
PASSWORDS = {"rita": "rita-pw", "lena": "lena-pw", "olga": "olga-pw"}
CLIENT_TIMEOUT = 8.0
# A trojan a learner would like the runtime to run in-process: it opens a file.
TROJAN = b'PARAMS = {}\n\ndef act(obs, params):\n    open("/etc/hostname").read()\n    return [0.0] * 7\n'


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    base = tmp_path_factory.mktemp("hardening")
    (base / "registry.yaml").write_text(CONFIG)
    server = start_server(base / "registry", config=base / "registry.yaml")
    assert server.info["secured"] is True
    yield server
    assert server.stop() == 0, server.log_text()


@pytest.fixture(scope="module")
def users(secured: ServerProcess) -> Iterator[dict[str, Client]]:
    opened = {u: secured.client(user=u, password=p, timeout=CLIENT_TIMEOUT) for u, p in PASSWORDS.items()}
    yield opened
    for client in opened.values():
        client.close()


def _blob_files(root: Path) -> list[Path]:
    return sorted(p for p in (root / "blobs").rglob("*") if p.is_file())


# --- forged actors -------------------------------------------------------------------------------


def test_learner_claiming_another_actor_is_recorded_as_itself(users: dict[str, Client]) -> None:
    name = unique_name("forge")
    record = users["lena"].publish(name, b"v0", LEARNED, actor="olga")
    assert record.created_by == "lena"
    users["lena"].record_gate(name, 0, {"success_rate": 0.9}, actor="olga")
    events = users["rita"].history(name)
    assert [(e.action, e.actor) for e in events] == [(Action.PUBLISH, "lena"), (Action.GATE, "lena")]
    for event in events:
        assert event.data["auth"] == Auth.USER.value
        assert "on_behalf_of" not in event.data  # only an operator may name one
    assert users["rita"].verify().ok


def test_operator_on_behalf_of_is_kept_beside_the_authenticated_actor(users: dict[str, Client]) -> None:
    name = unique_name("vouch")
    users["olga"].publish(name, b"v0", LEARNED)
    record = users["olga"].promote(name, 0, actor="evolve-gate", reason="gate passed")
    assert record.created_by == "olga"
    publish, promote = users["rita"].history(name)
    assert (publish.actor, publish.data["auth"], "on_behalf_of" in publish.data) == ("olga", "user", False)
    assert (promote.actor, promote.data["auth"], promote.data["on_behalf_of"]) == ("olga", "user", "evolve-gate")
    assert users["rita"].verify().ok


def test_a_raw_query_on_another_users_command_key_is_dropped(secured: ServerProcess, users: dict[str, Client]) -> None:
    """The actor comes from the key, and Zenoh's access control grants lena only her own keys."""
    name = unique_name("rawforge")
    users["lena"].publish(name, b"v0", LEARNED)
    before = users["rita"].history(name)
    keys = Keys()
    header = json.dumps({"name": name, "spec": LEARNED.to_dict(), "actor": "olga"}).encode()
    session = raw_session(secured.endpoint, user="lena", password=PASSWORDS["lena"])
    try:
        body = json.dumps({"name": name, "version": 0, "actor": "olga"}).encode()
        for key in (keys.cmd("promote", "olga"), keys.cmd("promote", "lena"), "capevo/cmd/promote", "capevo/cmd/**"):
            assert raw_query(session, key, payload=body, timeout=3) == [], key
        for key in (keys.cmd("publish", "olga"), "capevo/cmd/publish/*", "capevo/cmd/publish"):
            assert raw_query(session, key, payload=b"v1", attachment=header, timeout=3) == [], key
        # Her own key works, and the body's actor does not change who is recorded.
        replies = raw_query(session, keys.cmd("publish", "lena"), payload=b"v1", attachment=header, timeout=5)
        assert len(replies) == 1 and replies[0].ok is not None
        assert json.loads(replies[0].ok.payload.to_bytes())["created_by"] == "lena"
    finally:
        session.close()
    after = users["rita"].history(name)
    assert after[: len(before)] == before and [(e.action, e.actor) for e in after[len(before) :]] == [
        (Action.PUBLISH, "lena")
    ]


def test_open_registry_records_the_claim_as_unauthenticated(tmp_path: Path, free_port: int) -> None:
    server = start_server(tmp_path / "open", port=free_port)
    try:
        assert server.info["secured"] is False
        with server.client(actor="claimer") as client:
            client.publish("reach", b"v0", MANUAL)
            (event,) = client.history("reach")
        assert (event.actor, event.data["auth"]) == ("claimer", Auth.OPEN.value)
        assert "OPEN" in server.log_text()
    finally:
        assert server.stop() == 0, server.log_text()


def test_access_control_grants_each_user_only_its_own_command_keys() -> None:
    acl = access_control_for(parse_server_config(CONFIG))
    assert acl is not None
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    granted: dict[str, set[str]] = {}
    for policy in acl["policies"]:
        who = {u for sid in policy["subjects"] for u in subjects[sid].get("usernames", [])}
        for rule_id in policy["rules"]:
            rule = rules[rule_id]
            if "query" in rule["messages"] and "ingress" in rule["flows"]:
                for key in rule["key_exprs"]:
                    if "/cmd/" in key:
                        for user in who:
                            granted.setdefault(user, set()).add(key)
    keys = Keys()
    assert granted == {
        "lena": {keys.cmd("publish", "lena"), keys.cmd("gate", "lena")},
        "olga": {keys.cmd(op, "olga") for op in ("publish", "promote", "rollback", "deprecate", "reject", "gate")},
    }


def test_trusted_nodes_may_not_hold_command_roles() -> None:
    with pytest.raises(Invalid) as info:
        parse_server_config(CONFIG + "trusted_nodes:\n  - {zid: abcdef, roles: [reader, learner]}\n")
    assert info.value.details["field"] == "trusted_nodes[0].roles[1]"
    assert "relays other people's traffic" in info.value.message


# --- trust is granted, never declared -------------------------------------------------------------


def test_learner_cannot_publish_trusted_code(secured: ServerProcess, users: dict[str, Client]) -> None:
    name = unique_name("trojan")
    blobs_before = _blob_files(secured.root)
    with pytest.raises(CapevoError) as info:
        users["lena"].publish(name, TROJAN, MANUAL)
    assert type(info.value) is Forbidden and info.value.code is ErrorCode.FORBIDDEN
    assert "origin 'manual'" in info.value.message and "user 'lena' is not one" in info.value.message
    assert info.value.details["field"] == "spec.origin"
    assert name not in [s.name for s in users["rita"].list_ecms()]
    assert _blob_files(secured.root) == blobs_before  # refused before the bytes were stored
    # The same code as a learned origin is accepted, and the runtime's trust policy sandboxes it.
    assert users["lena"].publish(name, TROJAN, LEARNED).origin is Origin.LLM
    # An operator vouches for manual code.
    assert users["olga"].publish(name, TROJAN, MANUAL).origin is Origin.MANUAL


# --- one client cannot starve the others -------------------------------------------------------


def test_verify_flood_does_not_starve_resolves() -> None:
    """70 concurrent verify loops (two processes, user ``flood``) against a secured server while
    user ``probe`` resolves: no resolve may fail. The figures are in bench_verify_flood."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import bench_verify_flood
    finally:
        sys.path.remove(str(BENCHMARKS))
    result = bench_verify_flood.measure(loops=70, flooders=2, n_resolve=150, blobs=4, blob_mib=2.0)
    assert result["quiet"]["failures"] == 0 and result["flooded"]["failures"] == 0, result["failure_samples"]
    outcomes = result["flood_outcomes"]
    assert outcomes.get("ok", 0) > 0, outcomes  # the flood ran verifies ...
    assert outcomes.get("busy", 0) > 0, outcomes  # ... and more than their lane takes
    assert set(outcomes) <= {"ok", "busy"}, outcomes
    # Generous enough for any machine; the benchmark gives the real figure.
    assert result["flooded"]["max_ms"] < 5000, result


# --- lone surrogates ------------------------------------------------------------------------------

SURROGATE = "\ud800"


def _raw_reply_error(session: Any, key: str, **kwargs: Any) -> dict[str, Any]:
    (reply,) = raw_query(session, key, timeout=5, **kwargs)
    assert reply.err is not None, reply.ok.payload.to_bytes()
    return dict(json.loads(reply.err.payload.to_bytes())["error"])


def test_surrogates_over_zenoh_are_invalid_and_leave_no_blob(tmp_path: Path, free_port: int) -> None:
    server = start_server(tmp_path / "reg", port=free_port)
    try:
        with server.client(actor="t") as client:
            client.publish("reach", b"v0", LEARNED)
            with pytest.raises(Invalid) as info:  # the client runs the server's checks first
                client.record_gate("reach", 0, {SURROGATE: 1})
            assert info.value.details["field"] == "evidence.<key>"
        blobs = _blob_files(server.root)
        session = raw_session(server.endpoint)
        try:
            spec = LEARNED.to_dict()
            spec["descriptor"]["description"] = "caf\\ud800"
            header = json.dumps({"name": "reach", "spec": spec}).replace("\\\\ud800", "\\ud800").encode()
            assert b"\\ud800" in header
            err = _raw_reply_error(session, "capevo/cmd/publish", payload=b"new bytes", attachment=header)
            assert (err["code"], err["details"]["field"]) == ("invalid", "spec.descriptor.description")
            for body, field in (
                (b'{"name": "reach", "version": 0, "reason": "\\ud800"}', "reason"),
                (b'{"name": "reach", "version": 0, "actor": "x\\udfff"}', "actor"),
                (b'{"name": "reach", "version": 0, "evidence": {"\\ud800": 1}}', "evidence.<key>"),
            ):
                op = "gate" if b"evidence" in body else "reject"
                err = _raw_reply_error(session, f"capevo/cmd/{op}", payload=body)
                assert (err["code"], err["details"]["field"]) == ("invalid", field), err
                assert "lone UTF-16 surrogate" in err["message"]
        finally:
            session.close()
        assert _blob_files(server.root) == blobs
        with server.client() as client:
            assert [e.action for e in client.history("reach")] == [Action.PUBLISH]
            assert client.verify().ok
    finally:
        assert server.stop() == 0, server.log_text()


def test_surrogates_in_process_are_invalid_and_leave_no_blob(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path / "reg", actor="t") as reg:
        reg.publish("reach", b"v0", LEARNED)
        blobs = _blob_files(reg.root)
        doc = {"kind": "code", "description": "ok", "origin": "llm"}
        with pytest.raises(Invalid) as info:
            spec_from_document({**doc, "description": "caf" + SURROGATE})
        assert info.value.details["field"] == "description"
        bad_spec = PublishSpec(kind=Kind.CODE, descriptor=Descriptor(description="caf" + SURROGATE))
        for call, field in (
            (lambda: reg.publish("reach", b"v1", bad_spec), "description"),
            (lambda: reg.publish("reach", b"v1", LEARNED, actor=SURROGATE), "actor"),
            (lambda: reg.reject("reach", 0, reason=SURROGATE), "reason"),
            (lambda: reg.record_gate("reach", 0, {"k": [SURROGATE]}), "evidence.k[0]"),
        ):
            with pytest.raises(Invalid) as info:
                call()
            assert info.value.details["field"] == field
        assert _blob_files(reg.root) == blobs
        assert reg.verify().ok and len(reg.history()) == 1


@settings(max_examples=200, deadline=None)
@given(text=st.text(max_size=20), at=st.integers(min_value=0, max_value=20), code=st.integers(0xD800, 0xDFFF))
def test_any_lone_surrogate_in_a_request_is_invalid(text: str, at: int, code: int) -> None:
    bad = text[:at] + chr(code) + text[at:]
    escaped = json.dumps(bad)  # ensure_ascii: the surrogate travels as a \\uXXXX escape
    with pytest.raises(Invalid) as info:
        loads(f'{{"name": "reach", "reason": {escaped}}}'.encode(), what="request")
    assert info.value.details["field"] == "reason"
    with pytest.raises(Invalid) as info:
        spec_from_document({"kind": "code", "description": bad})
    assert info.value.details["field"] == "description"


# --- temporary blob files after SIGKILL --------------------------------------------------------------


def test_temp_blob_files_of_a_killed_server_are_swept_at_start(tmp_path: Path) -> None:
    root = tmp_path / "reg"
    big = os.urandom(48 << 20)
    left: list[Path] = []
    for attempt in range(5):
        server = start_server(root)
        stop = threading.Event()
        publisher = threading.Thread(target=_publish_until_stopped, args=(server, big, attempt, stop), daemon=True)
        publisher.start()
        deadline = time.monotonic() + 30
        while not left and time.monotonic() < deadline:
            left = list((root / "blobs").glob("*/.tmp-*"))
            time.sleep(0.001)
        server.kill()  # SIGKILL while the blob's temp file is being written
        stop.set()
        publisher.join(timeout=30)
        left = [p for p in left if p.exists()]
        if left:
            break
    assert left, "never caught the server between creating a temp blob file and renaming it"
    # A live writer's temp file (this test process's pid) is kept.
    live = root / "blobs" / "incoming" / f".tmp-{os.getpid()}-live"
    live.parent.mkdir(exist_ok=True)
    live.write_bytes(b"a writer still at work")
    server = start_server(root)
    try:
        assert not any(p.exists() for p in left)
        assert live.exists()
        assert "temporary blob file(s) left by killed writers" in server.log_text()
        with server.client() as client:
            assert client.verify().ok
    finally:
        assert server.stop() == 0, server.log_text()


def _publish_until_stopped(server: ServerProcess, data: bytes, salt: int, stop: threading.Event) -> None:
    try:
        with server.client(timeout=30.0) as client:
            i = 0
            while not stop.is_set():
                client.publish("big", bytes([salt, i % 256]) + data, LEARNED)
                i += 1
    except CapevoError:
        pass  # the server was killed under us: that is the point


# --- canonical numbers ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("kind: code\ndescription: x\nparent: 1.0\n", "parent"),
        ("kind: code\ndescription: x\nparent: true\n", "parent"),
        (
            "kind: code\ndescription: x\ninterface: {inputs: [{name: a, shape: [3.0]}]}\n",
            "interface.inputs[0].shape[0]",
        ),
    ],
)
def test_non_canonical_integers_are_invalid(text: str, field: str) -> None:
    with pytest.raises(Invalid) as info:
        parse_publish_spec(text)
    assert info.value.details["field"] == field
    assert "is not of type 'integer'" in info.value.message


def test_float_parent_over_zenoh_is_invalid(tmp_path: Path, free_port: int) -> None:
    server = start_server(tmp_path / "reg", port=free_port)
    session = raw_session(server.endpoint)
    try:
        with server.client() as client:
            client.publish("reach", b"v0", LEARNED)
        spec = LEARNED.to_dict()
        spec["parent"] = 0.0
        header = json.dumps({"name": "reach", "spec": spec}).encode()
        err = _raw_reply_error(session, "capevo/cmd/publish", payload=b"v1", attachment=header)
        assert (err["code"], err["details"]["field"]) == ("invalid", "spec.parent")
    finally:
        session.close()
        assert server.stop() == 0, server.log_text()


# --- the per-user command key and what an attribution records ---------------------------------------

USERS = st.from_regex(r"[A-Za-z0-9._@-]{1,64}", fullmatch=True)


@settings(max_examples=300)
@given(op=st.sampled_from(COMMANDS), user=st.none() | USERS)
def test_command_keys_round_trip_with_their_user(op: str, user: str | None) -> None:  # keys invariant 4
    keys = Keys("lab/robot-1")
    key = keys.cmd(op, user)
    assert keys.parse_cmd(key) == CommandRoute(op=op, user=user)
    assert zenoh.KeyExpr(key) == zenoh.KeyExpr(key)  # a valid key expression
    if user is not None:
        assert not zenoh.KeyExpr(f"lab/robot-1/cmd/{op}/*").intersects(zenoh.KeyExpr(key))
        assert not zenoh.KeyExpr("lab/robot-1/**").intersects(zenoh.KeyExpr(key))


@pytest.mark.parametrize(
    "key",
    ["capevo/cmd/publish/alice", "capevo/cmd/publish/@", "capevo/cmd/publish/@a b", "capevo/cmd/publish/@a/b"],
)
def test_bad_user_chunks_are_invalid(key: str) -> None:
    with pytest.raises(Invalid):
        Keys().parse_cmd(key)


def test_attribution_extras_go_into_the_event_data_and_the_chain_verifies(tmp_path: Path) -> None:
    # storage invariant 8, local invariant 7
    with LocalRegistry(tmp_path / "reg", actor="local") as reg:
        reg.publish("reach", b"v0", LEARNED)
        reg.promote("reach", 0, actor=Attribution(actor="olga", auth=Auth.USER, on_behalf_of="evolve-gate"))
        reg.publish("reach", b"v1", LEARNED, actor=Attribution(actor="claimer", auth=Auth.OPEN))
        plain, vouched, claimed = reg.history("reach")
        assert (plain.actor, "auth" in plain.data, "on_behalf_of" in plain.data) == ("local", False, False)
        assert (vouched.actor, vouched.data) == ("olga", {"auth": "user", "on_behalf_of": "evolve-gate"})
        assert (claimed.actor, claimed.data["auth"]) == ("claimer", "open")
        assert reg.get_version("reach", 1).created_by == "claimer"
        assert reg.verify().ok
