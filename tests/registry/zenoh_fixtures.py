"""Registry servers in separate processes, for the Zenoh tests.

``shared_server`` keeps one server (:func:`procs.start_server`) per key for the whole session;
``make_zenoh_registry`` is the contract suite's factory (a fresh server and root per test, so
the suite's "empty registry" assumptions hold); ``hub_router`` is a plain Zenoh router.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from procs import LOOPBACK, ServerProcess, free_tcp_port, start_server

from capevo.registry.client import Client


def unique_name(prefix: str = "ecm") -> str:
    """A fresh valid ECM name, so tests sharing a server never collide."""
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


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
