"""Registry servers in separate processes, for the Zenoh tests.

``start_server`` runs ``python -m capevo.registry.service`` as a subprocess on a loopback
port and waits for its ``READY`` line; ``shared_server`` keeps one per key for the whole
session; ``make_zenoh_registry`` is the contract suite's factory (a fresh server and root
per test, so the suite's "empty registry" assumptions hold).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from procs import kill, terminate

from capevo.registry.client import Client
from capevo.registry.service import READY_PREFIX

LOOPBACK = "127.0.0.1"


def free_tcp_port() -> int:
    """A loopback TCP port that was free a moment ago (session fixtures cannot use ``free_port``)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def unique_name(prefix: str = "ecm") -> str:
    """A fresh valid ECM name, so tests sharing a server never collide."""
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


@dataclass
class ServerProcess:
    """A running registry server subprocess."""

    proc: subprocess.Popen[str]
    root: Path
    port: int
    namespace: str
    info: dict[str, Any]
    log_path: Path

    @property
    def endpoint(self) -> str:
        return f"tcp/{LOOPBACK}:{self.port}"

    def client(self, **kwargs: Any) -> Client:
        kwargs.setdefault("namespace", self.namespace)
        return Client([self.endpoint], **kwargs)

    def running(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 20.0) -> int:
        """SIGTERM and wait; returns the exit code (SIGKILL if it does not exit in time)."""
        code = terminate(self.proc, timeout)
        self._close_pipes()
        return code

    def kill(self) -> None:
        """SIGKILL: no handler runs, nothing is flushed or closed."""
        kill(self.proc)
        self._close_pipes()

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def _close_pipes(self) -> None:
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def start_server(
    root: Path,
    *,
    port: int | None = None,
    namespace: str = "capevo",
    config: Path | None = None,
    max_artifact_bytes: int | None = None,
    connect: list[str] | None = None,
    env: dict[str, str] | None = None,
    ready_timeout: float = 60.0,
) -> ServerProcess:
    """Start ``python -m capevo.registry.service`` and wait until it serves.

    Raises:
        RuntimeError: the server exited or stayed silent; the message holds its log.
    """
    attempts = 1 if port is not None else 3
    last_error = ""
    for _ in range(attempts):
        p = port if port is not None else free_tcp_port()
        root.mkdir(parents=True, exist_ok=True)
        log_path = root.parent / f"{root.name}-server-{p}-{uuid.uuid4().hex[:6]}.log"
        cmd = [
            sys.executable,
            "-m",
            "capevo.registry.service",
            "--root",
            str(root),
            "--listen",
            f"tcp/{LOOPBACK}:{p}",
            "--namespace",
            namespace,
            "--log-level",
            "INFO",
        ]
        if config is not None:
            cmd += ["--config", str(config)]
        if max_artifact_bytes is not None:
            cmd += ["--max-artifact-bytes", str(max_artifact_bytes)]
        for endpoint in connect or ():
            cmd += ["--connect", endpoint]
        with open(log_path, "w") as log_file:
            proc = subprocess.Popen(
                cmd,
                stdout=subprocess.PIPE,
                stderr=log_file,
                text=True,
                env={**os.environ, **(env or {})},
            )
        info = _wait_ready(proc, ready_timeout)
        if info is not None:
            return ServerProcess(proc=proc, root=root, port=p, namespace=namespace, info=info, log_path=log_path)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        last_error = log_path.read_text(errors="replace")
    raise RuntimeError(f"registry server did not start:\n{last_error}")


def _wait_ready(proc: subprocess.Popen[str], timeout: float) -> dict[str, Any] | None:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        readable, _, _ = select.select([proc.stdout], [], [], 0.2)
        if readable:
            line = proc.stdout.readline()
            if line.startswith(READY_PREFIX):
                return dict(json.loads(line[len(READY_PREFIX) :]))
            if not line and proc.poll() is not None:
                return None
        elif proc.poll() is not None:
            return None
    return None


_HUB_SCRIPT = """
import json, sys, time, zenoh
port, zid, dictionary = int(sys.argv[1]), sys.argv[2], sys.argv[3]
c = zenoh.Config()
c.insert_json5("mode", '"router"')
c.insert_json5("id", json.dumps(zid))
c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
c.insert_json5("scouting/multicast/enabled", "false")
if dictionary:
    c.insert_json5("transport/auth/usrpwd", json.dumps({"dictionary_file": dictionary}))
s = zenoh.open(c)
print("HUB", s.zid(), flush=True)
sys.stdin.read()  # serve until the test closes our stdin
s.close()
"""


@contextlib.contextmanager
def hub_router(zid: str, *, dictionary: Path | None = None) -> Iterator[str]:
    """A plain Zenoh router (standing in for zenohd) in another process; yields its endpoint."""
    port = free_tcp_port()
    proc = subprocess.Popen(
        [sys.executable, "-c", _HUB_SCRIPT, str(port), zid, str(dictionary or "")],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("HUB"), "hub router did not start"
        yield f"tcp/{LOOPBACK}:{port}"
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


_SHARED: dict[str, ServerProcess] = {}


def shared_server(pytestconfig: pytest.Config, key: str, root: Path, **kwargs: Any) -> ServerProcess:
    """One server per ``key`` for the whole test session, stopped when pytest finishes."""
    server = _SHARED.get(key)
    if server is None or not server.running():
        server = start_server(root, **kwargs)
        _SHARED[key] = server
        pytestconfig.add_cleanup(server.stop)
    return server


@contextlib.contextmanager
def make_zenoh_registry(request: pytest.FixtureRequest) -> Iterator[Client]:
    """Contract-suite factory: a Zenoh client of a fresh server process on a fresh root."""
    root = request.getfixturevalue("tmp_path") / "registry"
    server = start_server(root, port=request.getfixturevalue("free_port"))
    try:
        with server.client(actor="contract-tester") as client:
            yield client
    finally:
        assert server.stop() == 0, server.log_text()


def raw_session(endpoint: str, *, user: str | None = None, password: str | None = None) -> zenoh.Session:
    """A bare client-mode Zenoh session, for sending requests the Client would never build."""
    from capevo.registry.zconfig import client_config

    return zenoh.open(client_config(connect=[endpoint], user=user, password=password))


def raw_query(
    session: zenoh.Session,
    selector: str,
    *,
    payload: bytes | None = None,
    attachment: bytes | None = None,
    timeout: float = 10.0,
) -> list[zenoh.Reply]:
    """Every reply to one raw query."""
    return list(
        session.get(
            selector,
            payload=payload,
            attachment=attachment,
            timeout=timeout,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
    )


# --- workers for spawned client processes (importable by multiprocessing 'spawn') -------------


def learner_publish_worker(
    endpoint: str, namespace: str, name: str, count: int, tag: str, ready: Any, go: Any, results: Any
) -> None:
    """Publish ``count`` versions of ``name`` once ``go`` is set; put ``(tag, [(version, sha256)])``."""
    from capevo.registry.descriptor import parse_publish_spec

    spec = parse_publish_spec("kind: code\ndescription: concurrent learner output\n")
    out: list[tuple[int, str]] = []
    try:
        with Client([endpoint], namespace=namespace, actor=tag) as client:
            ready.put(tag)
            go.wait(30)
            for i in range(count):
                record = client.publish(name, f"{tag}-{i}".encode() * 100, spec)
                out.append((record.version, record.artifact.sha256))
        results.put((tag, out, None))
    except Exception as exc:  # reported to the parent test, which fails on it
        results.put((tag, out, f"{type(exc).__name__}: {exc}"))


def promote_worker(
    endpoint: str, namespace: str, name: str, version: int, expected: int, ready: Any, go: Any, results: Any
) -> None:
    """Try ``promote(name, version, expected_active=expected)`` once ``go`` is set; put the outcome."""
    from capevo.errors import CapevoError

    try:
        with Client([endpoint], namespace=namespace, actor=f"promoter-{version}") as client:
            ready.put(version)
            go.wait(30)
            try:
                record = client.promote(name, version, expected_active=expected)
                results.put((version, "ok", record.state.value, ""))
            except CapevoError as exc:
                results.put((version, "error", exc.code.value, exc.message))
    except Exception as exc:
        results.put((version, "crash", type(exc).__name__, str(exc)))
