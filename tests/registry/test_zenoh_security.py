"""Zenoh's own usrpwd authentication and access control, as the registry configures them.

A secured server (users rita=reader, lena=learner, olga=operator) runs in its own process.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from procs import ServerProcess, start_server
from zenoh_fixtures import hub_router, raw_query, raw_session, unique_name

from capevo.errors import CapevoError, ErrorCode, Forbidden, Unavailable
from capevo.records import Action, State
from capevo.registry.client import Client
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.uploads import PART_BYTES

pytestmark = pytest.mark.zenoh

# A learner may not publish origin manual (see test_zenoh_hardening), so these specs are learned.
SPEC = parse_publish_spec("kind: code\ndescription: secured test skill\norigin: llm\n")
CONFIG = """
users:
  rita: {password: "rita pass:1", roles: [reader]}
  lena: {password_file: lena.pw, roles: [learner]}
  olga: {password_env: CAPEVO_TEST_OLGA_PW, roles: [operator]}
  wendy: {password: "wendy-secret", roles: [runtime]}
"""
PASSWORDS = {"rita": "rita pass:1", "lena": "lena-secret", "olga": "olga-secret", "wendy": "wendy-secret"}
# A refused query must fail fast, not after the client's timeout.
CLIENT_TIMEOUT = 8.0


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    base = tmp_path_factory.mktemp("secured")
    (base / "lena.pw").write_text(PASSWORDS["lena"] + "\n")
    (base / "registry.yaml").write_text(CONFIG)
    server = start_server(
        base / "registry", config=base / "registry.yaml", env={"CAPEVO_TEST_OLGA_PW": PASSWORDS["olga"]}
    )
    assert server.info["secured"] is True
    yield server
    assert server.stop() == 0, server.log_text()


@pytest.fixture(scope="module")
def clients(secured: ServerProcess) -> Iterator[dict[str, Client]]:
    opened = {
        role: secured.client(user=user, password=PASSWORDS[user], timeout=CLIENT_TIMEOUT)
        for role, user in (("reader", "rita"), ("learner", "lena"), ("operator", "olga"))
    }
    yield opened
    for client in opened.values():
        client.close()


def _forbidden(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Forbidden:
    started = time.monotonic()
    with pytest.raises(CapevoError) as info:
        fn(*args, **kwargs)
    elapsed = time.monotonic() - started
    assert type(info.value) is Forbidden, f"{type(info.value).__name__}: {info.value}"
    assert info.value.code is ErrorCode.FORBIDDEN
    assert "access control" in info.value.message
    assert elapsed < CLIENT_TIMEOUT / 2, f"refusal took {elapsed:.1f}s; it must not wait for the timeout"
    return info.value


def test_server_logs_access_control_on(secured: ServerProcess) -> None:
    log = secured.log_text()
    assert "access control on: 4 users, roles learner, operator, reader, runtime" in log
    assert "OPEN" not in log


@pytest.mark.parametrize(
    ("user", "password"),
    [(None, None), ("rita", "wrong"), ("mallory", "rita pass:1"), ("rita", "rita pass")],
    ids=["no-credentials", "wrong-password", "unknown-user", "password-prefix"],
)
def test_bad_credentials_cannot_even_connect(secured: ServerProcess, user: str | None, password: str | None) -> None:
    with pytest.raises(CapevoError) as info:
        secured.client(user=user, password=password)
    assert type(info.value) is Unavailable and info.value.code is ErrorCode.UNAVAILABLE
    assert f"cannot reach the registry at {secured.endpoint}" in info.value.message
    expected = "needs a user and password" if user is None else "user/password was refused"
    assert expected in info.value.message


def test_reader_reads_everything(clients: dict[str, Client]) -> None:
    name = unique_name("read")
    clients["learner"].publish(name, b"artifact", SPEC)
    clients["operator"].promote(name, 0)
    reader = clients["reader"]
    assert reader.is_registry_alive()
    assert name in [s.name for s in reader.list_ecms()]
    assert reader.get_ecm(name).active_version == 0
    assert reader.get_version(name).state is State.ACTIVE
    assert reader.get_artifact(name) == b"artifact"
    assert [e.action for e in reader.history(name)] == [Action.PUBLISH, Action.PROMOTE]
    assert reader.capability_set().active[name] == 0
    assert reader.verify().ok
    assert reader.info()["secured"] is True


def test_reader_is_refused_every_mutation_and_nothing_changes(clients: dict[str, Client]) -> None:
    name = unique_name("ro")
    clients["learner"].publish(name, b"v0", SPEC)
    reader = clients["reader"]
    before = (reader.get_ecm(name), reader.history(name), reader.capability_set())
    err = _forbidden(reader.promote, name, 0)
    assert err.message.startswith("capevo/cmd/promote/@rita: the registry is up but did not answer")
    assert "user 'rita'" in err.message
    _forbidden(reader.publish, name, b"v1", SPEC)
    _forbidden(reader.record_gate, name, 0, {"ok": True})
    _forbidden(reader.reject, name, 0)
    _forbidden(reader.deprecate, name, 0)
    _forbidden(reader.rollback, name)
    assert (reader.get_ecm(name), reader.history(name), reader.capability_set()) == before


def test_learner_publishes_and_gates_but_cannot_move_pointers(clients: dict[str, Client]) -> None:
    name = unique_name("learn")
    learner = clients["learner"]
    # The audit actor is the authenticated user; a learner's claimed actor is not recorded.
    assert learner.publish(name, b"v0", SPEC, actor="sac-1").created_by == "lena"
    assert learner.record_gate(name, 0, {"success_rate": 0.9}).gate_evidence == {"success_rate": 0.9}
    _forbidden(learner.promote, name, 0)
    _forbidden(learner.reject, name, 0)
    _forbidden(learner.deprecate, name, 0)
    _forbidden(learner.rollback, name, to=0)
    assert learner.get_version(name, 0).state is State.CANDIDATE


def test_operator_can_mutate(clients: dict[str, Client]) -> None:
    name = unique_name("op")
    op = clients["operator"]
    op.publish(name, b"v0", SPEC)
    op.publish(name, b"v1", SPEC)
    op.record_gate(name, 1, {"ok": True})
    assert op.promote(name, 0).state is State.ACTIVE
    assert op.promote(name, 1, expected_active=0).state is State.ACTIVE
    assert op.rollback(name, reason="regression").version == 0
    op.publish(name, b"v2", SPEC)
    assert op.reject(name, 2).state is State.REJECTED
    assert op.deprecate(name, 1).state is State.DEPRECATED
    assert op.history(name)[-1].actor == "olga"  # the client's default actor is its user


def test_reader_receives_events(clients: dict[str, Client]) -> None:
    name = unique_name("ev")
    seen: list[tuple[int, Action]] = []
    with clients["reader"].subscribe_events(name, lambda e, r: seen.append((e.seq, e.action))):
        time.sleep(0.3)  # let the subscription propagate to the router
        clients["learner"].publish(name, b"v0", SPEC)
        clients["operator"].promote(name, 0)
        deadline = time.monotonic() + 5
        while len(seen) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
    assert [a for _, a in seen] == [Action.PUBLISH, Action.PROMOTE]


def test_refused_raw_query_gets_no_reply_at_all(secured: ServerProcess) -> None:
    """What Zenoh's ACL does to a refused query: it vanishes; the querier sees zero replies, at once."""
    session = raw_session(secured.endpoint, user="rita", password=PASSWORDS["rita"])
    try:
        started = time.monotonic()
        replies = raw_query(session, "capevo/cmd/promote", payload=b'{"name": "x", "version": 0}', timeout=5)
        assert replies == []
        assert time.monotonic() - started < 2.5
        allowed = raw_query(session, "capevo/cmd/promote_typo", payload=b"{}", timeout=5)
        assert allowed == []  # not a read key either: refused the same way
        read = raw_query(session, "capevo/ecm", timeout=5)
        assert len(read) == 1 and read[0].ok is not None
    finally:
        session.close()


def test_refusal_is_unavailable_when_no_registry_is_alive(tmp_path: Path, free_port: int) -> None:
    server = start_server(tmp_path / "reg", port=free_port)
    client = server.client(timeout=CLIENT_TIMEOUT)
    try:
        assert server.stop() == 0
        time.sleep(0.2)
        with pytest.raises(CapevoError) as info:
            client.promote("reach", 0)
        assert info.value.code is ErrorCode.UNAVAILABLE, info.value
        assert "capevo/cmd/promote: no registry serves namespace 'capevo'" in info.value.message
        assert not client.is_registry_alive()
    finally:
        client.close()


def test_joining_a_router_with_own_credentials_and_trusted_node_roles(tmp_path: Path) -> None:
    """The registry logs in to another router (zenohd's stand-in) with ``credentials``; traffic
    from that router is allowed by its Zenoh id (``trusted_nodes``): reading yes, promoting no."""
    hub_zid = "abcdef0123"
    (tmp_path / "hub-users.txt").write_text("registry:join-secret\nvisitor:visitor-secret\n")
    (tmp_path / "registry.yaml").write_text(
        "users:\n  olga: {password: o-pw, roles: [operator]}\n"
        f"trusted_nodes:\n  - {{zid: {hub_zid}, roles: [reader]}}\n"
        "credentials: {user: registry, password: join-secret}\n"
    )
    with hub_router(hub_zid, dictionary=tmp_path / "hub-users.txt") as hub:
        server = start_server(tmp_path / "reg", config=tmp_path / "registry.yaml", connect=[hub])
        try:
            with server.client(user="olga", password="o-pw") as olga:
                olga.publish("reach", b"v0", SPEC)
            with Client([hub], user="visitor", password="visitor-secret", timeout=CLIENT_TIMEOUT) as visitor:
                _wait_for_alive(visitor)
                assert [s.name for s in visitor.list_ecms()] == ["reach"]
                assert visitor.get_artifact("reach", 0) == b"v0"
                _forbidden(visitor.promote, "reach", 0)
        finally:
            assert server.stop() == 0, server.log_text()


def _wait_for_alive(client: Client, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not client.is_registry_alive(timeout=0.5):
        assert time.monotonic() < deadline, "the registry never became visible through the hub"


def _serve_runtime_key(session: Any, key: str, body: bytes) -> Any:
    return session.declare_queryable(key, lambda query: query.reply(key, body))


def test_runtime_role_serves_worker_keys_and_readers_query_them(secured: ServerProcess) -> None:
    key = "capevo/runtime/w-acl/adopted"
    worker = raw_session(secured.endpoint, user="wendy", password=PASSWORDS["wendy"])
    reader = raw_session(secured.endpoint, user="rita", password=PASSWORDS["rita"])
    try:
        queryable = _serve_runtime_key(worker, key, b'{"worker_id": "w-acl"}')
        deadline = time.monotonic() + 10
        replies: list[Any] = []
        while not replies and time.monotonic() < deadline:  # declarations propagate asynchronously
            replies = [r for r in raw_query(reader, key, timeout=2.0) if r.ok is not None]
        assert [r.ok.payload.to_bytes() for r in replies] == [b'{"worker_id": "w-acl"}']
        queryable.undeclare()
    finally:
        worker.close()
        reader.close()


def test_reader_cannot_serve_worker_keys(secured: ServerProcess) -> None:
    key = "capevo/runtime/w-fake/adopted"
    impostor = raw_session(secured.endpoint, user="rita", password=PASSWORDS["rita"])
    operator = raw_session(secured.endpoint, user="olga", password=PASSWORDS["olga"])
    try:
        _serve_runtime_key(impostor, key, b"fake")
        time.sleep(1.0)
        assert [r for r in raw_query(operator, key, timeout=2.0) if r.ok is not None] == []
    finally:
        impostor.close()
        operator.close()


def _part(session: Any, user: str, name: str, upload: str, offset: int, total: int, spec: Any = None) -> Any:
    fields = {"name": name, "part": {"upload": upload, "offset": offset, "total": total}}
    if spec is not None:
        fields["spec"] = spec.to_dict()
    (reply,) = raw_query(session, f"capevo/cmd/publish/@{user}", attachment=json.dumps(fields).encode(), payload=b"x")
    return reply


def test_an_upload_in_parts_is_its_senders_alone(secured: ServerProcess, clients: dict[str, Client]) -> None:
    """Parts are publishes: the same ACL, the same actor, and one user cannot add to another's upload."""
    name = unique_name("parts")
    data = os.urandom(2 * PART_BYTES + 7)
    record = clients["learner"].publish(name, data, SPEC)  # in three parts
    assert record.created_by == "lena" and clients["reader"].get_artifact(name, record.version) == data
    lena = raw_session(secured.endpoint, user="lena", password=PASSWORDS["lena"])
    olga = raw_session(secured.endpoint, user="olga", password=PASSWORDS["olga"])
    rita = raw_session(secured.endpoint, user="rita", password=PASSWORDS["rita"])
    try:
        upload = uuid.uuid4().hex
        assert _part(lena, "lena", name, upload, 0, 3, SPEC).ok is not None
        taken = _part(olga, "olga", name, upload, 1, 3)  # an operator, but not the upload's sender
        assert json.loads(taken.err.payload.to_bytes())["error"]["code"] == "not_found"
        assert _part(lena, "lena", name, upload, 1, 3).ok is not None
        assert raw_query(rita, "capevo/cmd/publish/@rita", attachment=b"{}", payload=b"x", timeout=5) == []
        manual = parse_publish_spec("kind: code\ndescription: hand-written\norigin: manual\n")
        refused = _part(lena, "lena", name, uuid.uuid4().hex, 0, 3, manual)  # refused before a byte is kept
        assert json.loads(refused.err.payload.to_bytes())["error"]["code"] == "forbidden"
        last = _part(lena, "lena", name, upload, 2, 3)
        assert json.loads(last.ok.payload.to_bytes())["created_by"] == "lena"
        assert clients["reader"].get_artifact(name, record.version + 1) == b"xxx"
    finally:
        for session in (lena, olga, rita):
            session.close()
