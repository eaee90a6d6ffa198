"""SIGKILL the registry server in the middle of concurrent publishes and promotes, restart it on
the same root: every acknowledged write survives intact and nothing half-written shows."""

from __future__ import annotations

import hashlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from procs import ServerProcess, start_server

from capevo.errors import CapevoError, Conflict
from capevo.records import Action
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry

pytestmark = pytest.mark.zenoh

SPEC = parse_publish_spec("kind: neural\ndescription: crash test policy\n")
WRITERS = 3
ACKS_BEFORE_KILL = 24


@dataclass
class Acks:
    """What the server acknowledged before it died, per writer thread."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    published: list[tuple[str, int, str]] = field(default_factory=list)  # (name, version, sha256)
    promoted: list[tuple[str, int]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def count(self) -> int:
        with self.lock:
            return len(self.published) + len(self.promoted)


def _artifact(writer: int, i: int) -> bytes:
    # 64 KiB .. 1 MiB, so the kill often lands while a blob is being written.
    seed = hashlib.sha256(f"{writer}:{i}".encode()).digest()
    return seed * (2048 * (1 + (i * 7 + writer) % 16))


def _writer(server: ServerProcess, writer: int, acks: Acks, stop: threading.Event) -> None:
    name = f"crash-{writer}"
    try:
        client = server.client(actor=f"writer-{writer}", timeout=5.0)
    except CapevoError as exc:
        acks.errors.append(f"connect: {exc}")
        return
    try:
        active: int | None = None
        i = 0
        while not stop.is_set():
            data = _artifact(writer, i)
            record = client.publish(name, data, SPEC)
            with acks.lock:
                acks.published.append((name, record.version, hashlib.sha256(data).hexdigest()))
            if i % 2 == 1:
                try:
                    client.promote(name, record.version, expected_active=active)
                except Conflict:
                    pass  # a promote whose reply was lost earlier may have moved the pointer
                else:
                    active = record.version
                    with acks.lock:
                        acks.promoted.append((name, record.version))
            i += 1
    except CapevoError:
        pass  # the server died mid-request: the outcome of that one request is unknown
    finally:
        client.close()


def _check_recovered(root: Path, server: ServerProcess, acks: Acks) -> None:
    with server.client(timeout=30.0) as client:
        report = client.verify()
        assert report.ok, report.problems
        for name, version, sha in acks.published:
            record = client.get_version(name, version)
            assert record.artifact.sha256 == sha
            assert hashlib.sha256(client.get_artifact(name, version)).hexdigest() == sha
        for name, version in acks.promoted:
            moves = [e.to_version for e in client.history(name) if e.action is Action.PROMOTE]
            assert version in moves
        for summary in client.list_ecms():
            detail = client.get_ecm(summary.name)
            # Gap-free, and every visible version has its whole blob.
            assert [v.version for v in detail.versions] == list(range(summary.n_versions))
            for v in detail.versions:
                data = client.get_artifact(v.name, v.version)
                assert len(data) == v.artifact.size and hashlib.sha256(data).hexdigest() == v.artifact.sha256
    with LocalRegistry(root) as local:  # and the same from a fresh process-local open of the files
        assert local.verify().ok


def test_sigkill_during_concurrent_writes_loses_nothing_acknowledged(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    acks = Acks()
    for round_ in range(2):
        server = start_server(root)
        stop = threading.Event()
        threads = [threading.Thread(target=_writer, args=(server, w, acks, stop), daemon=True) for w in range(WRITERS)]
        target = acks.count() + ACKS_BEFORE_KILL
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        while acks.count() < target and time.monotonic() < deadline:
            time.sleep(0.005)
        assert acks.count() >= target, f"round {round_}: only {acks.count()} acks; errors {acks.errors}"
        server.kill()  # SIGKILL mid-stream: the writers are still going
        stop.set()
        for t in threads:
            t.join(timeout=30)
            assert not t.is_alive()
        assert acks.errors == []
        restarted = start_server(root)
        try:
            _check_recovered(root, restarted, acks)
        finally:
            assert restarted.stop() == 0, restarted.log_text()
    assert len(acks.published) >= 2 * ACKS_BEFORE_KILL // 2
