"""The registry server and client over real Zenoh, server in another process."""

from __future__ import annotations

import hashlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from procs import ServerProcess, free_tcp_port, start_server
from zenoh_fixtures import unique_name

from capevo.errors import CapevoError, Corrupt, ErrorCode, Invalid, TooLarge, Unavailable
from capevo.records import Action, AuditEvent, EcmVersion, State
from capevo.registry.api import Registry
from capevo.registry.client import Client
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry
from capevo.registry.open import open_registry

pytestmark = pytest.mark.zenoh

SPEC = parse_publish_spec("kind: neural\ndescription: a policy\n")
MB = 2**20


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    srv = start_server(tmp_path_factory.mktemp("svc") / "registry")
    yield srv
    assert srv.stop() == 0, srv.log_text()


@pytest.fixture
def client(server: ServerProcess) -> Iterator[Client]:
    with server.client(actor="svc-test") as c:
        yield c


def _wait_for(predicate: object, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:  # type: ignore[operator]
        time.sleep(0.02)


def test_server_says_it_runs_open(server: ServerProcess) -> None:
    assert server.info["secured"] is False
    assert "no users configured: the registry is OPEN" in server.log_text()


def test_client_is_a_registry_and_sees_the_server_alive(client: Client) -> None:
    assert isinstance(client, Registry)
    assert client.is_registry_alive()
    info = client.info()
    assert (info["protocol"], info["namespace"], info["max_artifact_bytes"]) == (2, "capevo", 256 * MB)


def test_every_commit_is_published_as_an_event(client: Client) -> None:
    name = unique_name("events")
    everything: list[tuple[AuditEvent, EcmVersion]] = []
    mine: list[tuple[AuditEvent, EcmVersion]] = []
    lock = threading.Lock()

    def keep(into: list[tuple[AuditEvent, EcmVersion]]) -> object:
        def on_event(event: AuditEvent, record: EcmVersion) -> None:
            with lock:
                into.append((event, record))

        return on_event

    with client.subscribe_events("*", keep(everything)), client.subscribe_events(name, keep(mine)):
        time.sleep(0.3)  # declarations reach the router
        client.publish(name, b"0", SPEC)
        client.record_gate(name, 0, {"ok": True})
        client.promote(name, 0)
        client.publish(name, b"1", SPEC)
        client.promote(name, 1, expected_active=0)
        client.rollback(name)
        client.deprecate(name, 1)
        # Both subscriptions see all seven (under load the wildcard one may lag the other).
        _wait_for(lambda: len(mine) >= 7 and sum(e.name == name for e, _ in everything) >= 7)
    history = client.history(name)
    assert [e for e, _ in sorted(mine, key=lambda p: p[0].seq)] == history
    assert [e.action for e in history] == [
        Action.PUBLISH,
        Action.GATE,
        Action.PROMOTE,
        Action.PUBLISH,
        Action.PROMOTE,
        Action.ROLLBACK,
        Action.DEPRECATE,
    ]
    for event, record in mine:
        assert record.name == name and record.version == event.version
        if event.to_state is not None:
            assert record.state is event.to_state
    assert [e for e, _ in everything if e.name == name] == [e for e, _ in mine]


def test_closing_a_subscription_stops_delivery(client: Client) -> None:
    name = unique_name("unsub")
    seen: list[int] = []
    sub = client.subscribe_events(name, lambda e, r: seen.append(e.seq))
    time.sleep(0.3)
    client.publish(name, b"0", SPEC)
    _wait_for(lambda: len(seen) == 1)
    sub.close()
    sub.close()  # idempotent
    client.publish(name, b"1", SPEC)
    time.sleep(0.5)
    assert len(seen) == 1


def test_64mb_artifact_round_trip(client: Client) -> None:
    name = unique_name("big")
    block = hashlib.sha256(b"seed").digest() * (MB // 32)
    artifact = b"".join(bytes([i]) + block[1:] for i in range(64))
    assert len(artifact) == 64 * MB
    record = client.publish(name, artifact, SPEC)
    assert record.artifact.size == 64 * MB
    assert record.artifact.sha256 == hashlib.sha256(artifact).hexdigest()
    assert client.get_artifact(name, 0) == artifact
    client.promote(name, 0)
    assert client.get_artifact(name) == artifact


def test_corrupt_blob_is_reported_not_served(server: ServerProcess, client: Client) -> None:
    name = unique_name("rot")
    record = client.publish(name, b"pristine bytes", SPEC)
    sha = record.artifact.sha256
    blob = server.root / "blobs" / sha[:2] / sha[2:]
    assert blob.read_bytes() == b"pristine bytes"
    os.chmod(blob, 0o644)
    blob.write_bytes(b"tampered bytes")
    try:
        with pytest.raises(CapevoError) as info:
            client.get_artifact(name, 0)
        assert type(info.value) is Corrupt and info.value.code is ErrorCode.CORRUPT
        assert info.value.message.startswith(f"{name} v0:")
        report = client.verify()
        assert not report.ok and any(sha in p for p in report.problems)
    finally:
        blob.write_bytes(b"pristine bytes")
    assert client.verify().ok


def test_client_refuses_oversize_artifact_before_sending(tmp_path: Path, free_port: int) -> None:
    small = start_server(tmp_path / "reg", port=free_port, max_artifact_bytes=MB)
    try:
        with small.client() as c:
            with pytest.raises(CapevoError) as info:
                c.publish("big", b"\0" * (MB + 1), SPEC)
            assert type(info.value) is TooLarge and info.value.code is ErrorCode.TOO_LARGE
            assert info.value.message == f"artifact is {MB + 1} bytes; the limit is {MB}"
            assert c.publish("big", b"\0" * MB, SPEC).artifact.size == MB
            assert [v.version for v in c.get_ecm("big").versions] == [0]
    finally:
        assert small.stop() == 0


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_shuts_down_cleanly_and_liveliness_goes(tmp_path: Path, free_port: int, sig: signal.Signals) -> None:
    srv = start_server(tmp_path / "reg", port=free_port)
    c = srv.client(timeout=5.0)
    try:
        c.publish("reach", b"x", SPEC)
        assert c.is_registry_alive()
        srv.proc.send_signal(sig)
        assert srv.proc.wait(timeout=20) == 0
        log = srv.log_text()
        assert f"received {sig.name}; shutting down" in log and "Traceback" not in log
        _wait_for(lambda: not c.is_registry_alive(timeout=0.5))
        assert not c.is_registry_alive()
        with pytest.raises(CapevoError) as info:
            c.list_ecms()
        assert type(info.value) is Unavailable
    finally:
        c.close()
        srv.stop()
    with LocalRegistry(tmp_path / "reg") as local:  # everything it acknowledged is on disk
        assert local.get_version("reach", 0).state is State.CANDIDATE and local.verify().ok


def test_unreachable_registry_is_unavailable() -> None:
    started = time.monotonic()
    with pytest.raises(CapevoError) as info:
        Client([f"tcp/127.0.0.1:{free_tcp_port()}"])
    assert type(info.value) is Unavailable
    assert "cannot reach the registry at tcp/127.0.0.1:" in info.value.message
    assert time.monotonic() - started < 10


def test_closed_client_is_unavailable(server: ServerProcess) -> None:
    c = server.client()
    c.close()
    c.close()
    with pytest.raises(Unavailable, match="closed"):
        c.list_ecms()
    assert not c.is_registry_alive()


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"timeout": 0}, "timeout"), ({"artifact_timeout": -1}, "artifact_timeout"), ({"namespace": "a/*"}, "namespace")],
)
def test_bad_client_arguments_are_invalid(server: ServerProcess, kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(Invalid) as info:
        Client([server.endpoint], **kwargs)  # type: ignore[arg-type]
    assert info.value.details["field"] == field


def test_bad_endpoint_is_invalid() -> None:
    with pytest.raises(Invalid) as info:
        Client(["not-an-endpoint"])
    assert info.value.message.startswith("bad connect endpoint ['not-an-endpoint']")


def test_open_registry_picks_local_or_zenoh(server: ServerProcess, tmp_path: Path) -> None:
    with open_registry(root=tmp_path / "local") as reg:
        assert isinstance(reg, LocalRegistry)
    with open_registry(connect=server.endpoint, actor="opener") as reg:
        assert isinstance(reg, Client) and reg.actor == "opener"
        assert isinstance(reg.list_ecms(), list)
    for kwargs in ({}, {"root": tmp_path, "connect": server.endpoint}, {"root": tmp_path, "user": "u"}):
        with pytest.raises(Invalid):
            open_registry(**kwargs)  # type: ignore[arg-type]


def test_serve_in_a_thread_stops_on_the_stop_event(tmp_path: Path, free_port: int) -> None:
    from capevo.registry.service import ServeInfo, serve

    infos: list[ServeInfo] = []
    stop = threading.Event()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            serve(
                tmp_path / "reg",
                listen=[f"tcp/127.0.0.1:{free_port}"],
                ready=infos.append,
                stop=stop,
                handle_signals=False,
            )
        except BaseException as exc:  # surfaced by the assertion below
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    _wait_for(lambda: bool(infos) or bool(errors), timeout=20)
    assert errors == [] and infos[0].listen == (f"tcp/127.0.0.1:{free_port}",) and not infos[0].secured
    with Client([f"tcp/127.0.0.1:{free_port}"], timeout=5.0) as c:
        assert c.publish("reach", b"x", SPEC).version == 0
        stop.set()
        thread.join(timeout=20)
        assert not thread.is_alive() and errors == []
        _wait_for(lambda: not c.is_registry_alive(timeout=0.5))
        assert not c.is_registry_alive()


def test_serve_refuses_a_taken_port_and_bad_endpoints(tmp_path: Path) -> None:
    import socket

    from capevo.registry.service import serve

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(Unavailable, match="cannot open the registry's Zenoh session"):
            serve(tmp_path / "a", listen=[f"tcp/127.0.0.1:{port}"], handle_signals=False)
    with pytest.raises(Invalid, match="bad listen endpoint"):
        serve(tmp_path / "b", listen=["garbage"], handle_signals=False)
    with pytest.raises(Invalid, match="namespace"):
        serve(tmp_path / "c", namespace="a/**", handle_signals=False)
