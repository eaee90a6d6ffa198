"""The server's hot reads come from memory (issue 21): never staler than an acknowledged commit
of any process, byte for byte what SQLite would answer, not queued behind writes, and a
SIGKILL between a commit and the cache update loses nothing."""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from procs import LOOPBACK, ServerProcess, free_tcp_port, start_server
from read_cache_crash_child import KILL_REASON

from capevo.errors import CapevoError, Invalid, NotFound
from capevo.records import Action
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.keys import Keys, Route
from capevo.registry.local import DB_FILENAME, LocalRegistry
from capevo.registry.read_cache import ReadCache, ReadSnapshot
from capevo.registry.server_config import ServerConfig
from capevo.registry.service import READ_HANDLERS, READY_PREFIX, Context
from capevo.registry.uploads import Uploads
from capevo.storage.commit_word import CommitWord

SPEC = parse_publish_spec("kind: neural\ndescription: read cache test policy\n")
MIB = 1 << 20


def _sqlite_reply(reg: LocalRegistry, route: Route, params: dict[str, int]) -> bytes | None:
    """What the server's SQLite read handler replies, or None where it raises (NotFound, ...)."""
    uploads = Uploads(reg.artifact_writer, max_artifact_bytes=MIB)
    ctx = Context(registry=reg, keys=Keys(), max_artifact_bytes=MIB, config=ServerConfig(), uploads=uploads)
    try:
        return READ_HANDLERS[route.endpoint](ctx, route, params).payload
    except CapevoError:
        return None


def _every_route(reg: LocalRegistry, revision: int) -> list[tuple[Route, dict[str, int]]]:
    routes: list[tuple[Route, dict[str, int]]] = [(Route(endpoint="list"), {}), (Route(endpoint="set"), {})]
    routes += [(Route(endpoint="set"), {"revision": r}) for r in range(revision + 2)]
    for name in ("alpha", "beta", "never-published"):
        routes.append((Route(endpoint="version", name=name), {}))
        routes += [(Route(endpoint="version", name=name, version=k), {}) for k in range(6)]
    return routes


def _assert_matches_sqlite(snapshot: ReadSnapshot, reg: LocalRegistry) -> None:
    """Invariants 2 and 3 of read_cache: what the snapshot holds is SQLite's reply; a miss is None."""
    for route, params in _every_route(reg, snapshot.revision):
        held = snapshot.reply(route, params)
        if held is not None:
            assert held == _sqlite_reply(reg, route, params), (route, params)
        elif route.endpoint == "version" and _sqlite_reply(reg, route, params) is not None:
            pytest.fail(f"the snapshot misses {route} that SQLite holds")


def test_cached_replies_are_sqlites_through_every_lifecycle_move(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    with LocalRegistry(root) as ours, LocalRegistry(root) as other:
        cache = ReadCache(root / DB_FILENAME)
        ours.add_listener(cache)
        try:
            # Moves through this registry (listener path) and another connection (data_version path).
            steps = [
                lambda: ours.publish("alpha", b"a0", SPEC),
                lambda: other.publish("alpha", b"a1", SPEC),
                lambda: ours.record_gate("alpha", 1, {"success": 0.9}),
                lambda: other.promote("alpha", 0),
                lambda: ours.promote("alpha", 1, expected_active=0),
                lambda: other.publish("beta", b"b0", SPEC),
                lambda: other.publish("alpha", b"a2", SPEC),
                lambda: ours.reject("alpha", 2, reason="gate said no"),
                lambda: other.rollback("alpha"),
                lambda: ours.deprecate("alpha", 1),
                lambda: other.promote("beta", 0),
            ]
            for step in steps:
                step()
                _assert_matches_sqlite(cache.current(), ours)
            snapshot = cache.current()
            assert snapshot.active == {"alpha": 0, "beta": 0}
            assert snapshot.reply(Route(endpoint="version", name="alpha"), {}) is not None
            # Misses: the SQLite path answers them, with its own errors.
            assert snapshot.reply(Route(endpoint="version", name="never-published"), {}) is None
            assert snapshot.reply(Route(endpoint="version", name="alpha", version=9), {}) is None
            assert snapshot.reply(Route(endpoint="set"), {"revision": 1}) is None
            assert snapshot.reply(Route(endpoint="ecm", name="alpha"), {}) is None
        finally:
            cache.close()


def test_a_cache_opened_on_an_existing_root_holds_its_whole_state(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    with LocalRegistry(root) as reg:
        for i in range(3):
            reg.publish("alpha", f"a{i}".encode(), SPEC)
        reg.promote("alpha", 2)
        reg.publish("beta", b"b0", SPEC)
        cache = ReadCache(root / DB_FILENAME)
        try:
            snapshot = cache.current()
            assert snapshot.seq == len(reg.history())
            assert {n: sorted(v) for n, v in snapshot.versions.items()} == {"alpha": [0, 1, 2], "beta": [0]}
            _assert_matches_sqlite(snapshot, reg)
        finally:
            cache.close()


@pytest.mark.zenoh
def test_a_promote_acknowledged_by_another_process_is_served_at_once(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    server = start_server(root)
    try:
        with server.client() as client, LocalRegistry(root) as direct:
            direct.publish("shared", b"v0", SPEC)
            direct.publish("shared", b"v1", SPEC)
            direct.promote("shared", 0)
            assert client.get_version("shared").version == 0  # the server's cache holds v0 now
            for i in range(10):
                # This test process writes the root directly; the server learns of it only from SQLite.
                expected = 1 if i % 2 == 0 else 0
                if i == 0:
                    direct.promote("shared", 1, expected_active=0)
                else:
                    direct.rollback("shared", expected, expected_active=1 - expected)
                assert client.get_version("shared").version == expected, f"move {i}"
                assert client.capability_set().active == {"shared": expected}
                assert client.capability_set().revision == i + 2
                assert [s.active_version for s in client.list_ecms()] == [expected]
            direct.publish("born-elsewhere", b"x", SPEC)
            direct.promote("born-elsewhere", 0)
            assert client.get_version("born-elsewhere").version == 0
            assert client.get_version("born-elsewhere", 0).state.value == "active"
    finally:
        assert server.stop() == 0, server.log_text()


@pytest.mark.zenoh
def test_a_hot_key_answered_before_still_checks_its_parameters(tmp_path: Path) -> None:
    """The server keeps the parsed route of a hot key; a later query on the same key with
    parameters is still checked (past revisions from SQLite, unknown parameters refused)."""
    root = tmp_path / "registry"
    with LocalRegistry(root) as direct:
        direct.publish("alpha", b"v0", SPEC)
        direct.promote("alpha", 0)
    server = start_server(root)
    try:
        with server.client() as client:
            for _ in range(3):
                assert client.capability_set().revision == 1
                assert client.get_version("alpha").version == 0
            assert client.capability_set(revision=0).active == {}
            assert client.capability_set(revision=1).active == {"alpha": 0}
            with pytest.raises(NotFound):
                client.capability_set(revision=7)
            for key in (client._keys.capability_set(), client._keys.version("alpha", None)):
                with pytest.raises(Invalid, match="unknown parameter"):
                    client._read(key, dict, what="probe", colour="blue")
            assert client.get_version("alpha").version == 0
    finally:
        assert server.stop() == 0, server.log_text()


@pytest.mark.zenoh
def test_a_resolve_returns_while_a_large_publish_waits_to_commit(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    server = start_server(root)
    try:
        with server.client(timeout=60.0) as publisher, server.client(timeout=60.0) as reader:
            publisher.publish("hot", b"v0", SPEC)
            publisher.promote("hot", 0)
            assert reader.get_version("hot").version == 0
            data = hashlib.sha256(b"big").digest() * (16 * MIB // 32)
            blob = root / "blobs" / hashlib.sha256(data).hexdigest()[:2] / hashlib.sha256(data).hexdigest()[2:]
            order: list[str] = []
            published: list[int] = []
            # Another writer holds SQLite's write lock, so the publish, its blob stored, must wait to commit.
            lock = sqlite3.connect(root / DB_FILENAME, isolation_level=None)
            lock.execute("BEGIN IMMEDIATE")
            try:

                def publish() -> None:
                    published.append(publisher.publish("big", data, SPEC).version)
                    order.append("publish")

                thread = threading.Thread(target=publish)
                thread.start()
                while not blob.exists() and thread.is_alive():
                    thread.join(0.01)
                assert blob.exists(), "the publish never stored its blob"
                for _ in range(20):
                    assert reader.get_version("hot").version == 0
                    assert reader.capability_set().active == {"hot": 0}
                order.append("resolves")
            finally:
                lock.execute("ROLLBACK")
                lock.close()
            thread.join(60)
            assert order == ["resolves", "publish"]
            assert published == [0]
            assert reader.get_version("big", 0).artifact.size == len(data)
    finally:
        assert server.stop() == 0, server.log_text()


def _start_crash_child(root: Path) -> ServerProcess:
    port = free_tcp_port()
    root.mkdir(parents=True, exist_ok=True)
    log_path = root.parent / f"crash-child-{port}.log"
    child = Path(__file__).with_name("read_cache_crash_child.py")
    with open(log_path, "w") as log_file:
        proc = subprocess.Popen(
            [sys.executable, str(child), "--root", str(root), "--listen", f"tcp/{LOOPBACK}:{port}"],
            stdout=subprocess.PIPE,
            stderr=log_file,
            text=True,
        )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith(READY_PREFIX), log_path.read_text()
    info = json.loads(line[len(READY_PREFIX) :])
    return ServerProcess(proc=proc, root=root, port=port, namespace="capevo", info=info, log_path=log_path)


@pytest.mark.zenoh
def test_sigkill_between_commit_and_cache_update_serves_the_commit_after_restart(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    child = _start_crash_child(root)
    try:
        with child.client(timeout=5.0) as client:
            client.publish("crashy", b"v0", SPEC)
            client.publish("crashy", b"v1", SPEC)
            client.promote("crashy", 0)
            assert client.get_version("crashy").version == 0
            with pytest.raises(CapevoError):
                client.promote("crashy", 1, expected_active=0, reason=KILL_REASON)
        assert child.proc.wait(timeout=30) == -9, "the child did not die by SIGKILL in the cache update"
    finally:
        child.kill()
    with LocalRegistry(root) as direct:  # the move was durable before the kill
        assert direct.get_version("crashy").version == 1
        assert direct.verify().ok
    restarted = start_server(root)
    try:
        with restarted.client() as client:
            assert client.get_version("crashy").version == 1
            assert client.get_version("crashy", 0).state.value == "superseded"
            assert client.capability_set().active == {"crashy": 1}
            assert [e.action for e in client.history("crashy")][-1] is Action.PROMOTE
            assert client.verify().ok
    finally:
        assert restarted.stop() == 0, restarted.log_text()


def _promote_in_another_process(root: Path, version: int, *, move_word: bool) -> None:
    child = mp.get_context("spawn").Process(target=_promote_child, args=(str(root), version, move_word))
    child.start()
    child.join(120)
    assert child.exitcode == 0


def _promote_child(root: str, version: int, move_word: bool) -> None:
    if not move_word:
        # As a writer that bypasses capevo's store.
        CommitWord.move = lambda self: None  # type: ignore[method-assign]
    with LocalRegistry(root, actor="elsewhere") as reg:
        reg.promote("alpha", version)


def _promote_then_die_before_the_word(root: str) -> None:
    with LocalRegistry(root, actor="elsewhere") as reg:  # opening writes too: die on the promote only
        CommitWord.move = lambda self: os.kill(os.getpid(), signal.SIGKILL)  # type: ignore[method-assign]
        reg.promote("alpha", 1)


def _three_versions(root: Path) -> None:
    with LocalRegistry(root) as reg:
        for i in range(3):
            reg.publish("alpha", f"a{i}".encode(), SPEC)
        reg.promote("alpha", 0)


def test_the_commit_word_alone_tells_the_cache_of_another_process_commit(tmp_path: Path) -> None:
    """With the timer out of reach, the word is what makes the cache check SQLite again."""
    root = tmp_path / "registry"
    _three_versions(root)
    waits = ReadCache(root / DB_FILENAME, recheck_s=1e9)
    eager = ReadCache(root / DB_FILENAME, recheck_s=0.0)
    try:
        assert waits.current().active == {"alpha": 0}
        _promote_in_another_process(root, 1, move_word=True)
        assert waits.current().active == {"alpha": 1}
        _promote_in_another_process(root, 2, move_word=False)
        assert waits.current().active == {"alpha": 1}, "nothing moved the word, so only the timer may tell"
        assert eager.current().active == {"alpha": 2}
    finally:
        waits.close()
        eager.close()


def test_the_timer_finds_a_commit_that_never_moved_the_word(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    _three_versions(root)
    cache = ReadCache(root / DB_FILENAME, recheck_s=0.2)
    try:
        assert cache.current().active == {"alpha": 0}
        _promote_in_another_process(root, 1, move_word=False)
        time.sleep(0.3)  # past recheck_s: the next call must check SQLite in full
        assert cache.current().active == {"alpha": 1}
    finally:
        cache.close()


@pytest.mark.parametrize("recheck_s", [-1.0, float("nan"), float("inf")])
def test_a_bad_recheck_interval_is_invalid(tmp_path: Path, recheck_s: float) -> None:
    with pytest.raises(Invalid, match="recheck_s"):
        ReadCache(tmp_path / DB_FILENAME, recheck_s=recheck_s)


def test_sigkill_between_commit_and_word_is_found_by_the_timer(tmp_path: Path) -> None:
    """A writer SIGKILLed after COMMIT and before it moves the word never acknowledged its commit,
    so the cache may miss it for a while; the commit is durable, and the timer finds it."""
    root = tmp_path / "registry"
    _three_versions(root)
    cache = ReadCache(root / DB_FILENAME, recheck_s=0.2)
    try:
        assert cache.current().active == {"alpha": 0}
        child = mp.get_context("spawn").Process(target=_promote_then_die_before_the_word, args=(str(root),))
        child.start()
        child.join(120)
        assert child.exitcode == -signal.SIGKILL
        with LocalRegistry(root) as direct:
            assert direct.get_version("alpha").version == 1  # durable before the kill
            assert direct.verify().ok
        time.sleep(0.3)  # past recheck_s: the next call must check SQLite in full
        assert cache.current().active == {"alpha": 1}
    finally:
        cache.close()
