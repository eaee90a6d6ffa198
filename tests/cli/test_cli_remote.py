"""The CLI against a running registry: ``capevo registry serve`` in a real process, every
command a real ``python -m capevo`` process talking Zenoh over loopback."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cli_support import REPO, artifact_bytes, assert_clean_error, run_capevo, subprocess_env

pytestmark = pytest.mark.zenoh


class Server:
    def __init__(self, proc: subprocess.Popen[str], endpoint: str, info: dict) -> None:
        self.proc = proc
        self.endpoint = endpoint
        self.info = info

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.proc.wait(timeout=timeout)


def start_server(root: Path, port: int, *extra: str) -> Server:
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "capevo",
            "registry",
            "serve",
            "--root",
            str(root),
            "--listen",
            endpoint,
            "--no-multicast",
            "--json",
            "--log-level",
            "WARNING",
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=subprocess_env(),
        cwd=REPO,
    )
    assert proc.stdout is not None
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            line = proc.stdout.readline()
            if line:
                return Server(proc, endpoint, json.loads(line))
        if proc.poll() is not None:
            break
    proc.kill()
    _, err = proc.communicate(timeout=10)
    raise AssertionError(f"registry serve did not become ready: {err}")


@pytest.fixture
def server(tmp_path: Path, free_port: int) -> Iterator[Server]:
    srv = start_server(tmp_path / "served", free_port)
    yield srv
    if srv.proc.poll() is None:
        srv.proc.kill()
        srv.proc.wait(timeout=10)


def test_rollback_from_the_cli_against_a_running_registry(
    server: Server, tmp_path: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    conn = ["--connect", server.endpoint]
    assert server.info["listen"] == [server.endpoint] and server.info["secured"] is False

    def ok(*args: object) -> subprocess.CompletedProcess[str]:
        proc = run_capevo([*args, *conn])
        assert proc.returncode == 0, proc.stderr
        return proc

    for tag in ("v0", "v1"):
        pub = json.loads(
            ok("ecm", "publish", "reach", "--artifact", make_artifact(tag), "--descriptor", descriptor, "--json").stdout
        )
        assert pub["state"] == "candidate"
        ok("ecm", "promote", "reach", pub["version"], "--reason", f"ship {tag}")
    assert json.loads(ok("ecm", "show", "reach", "--json").stdout)["active_version"] == 1

    proc = ok("ecm", "rollback", "reach", "--expected-active", "1", "--reason", "regressed in the field")
    assert proc.stdout.strip() == "rolled back reach v0: now active"

    detail = json.loads(ok("ecm", "show", "reach", "--json").stdout)
    assert detail["active_version"] == 0
    assert [(v["version"], v["state"]) for v in detail["versions"]] == [(0, "active"), (1, "superseded")]
    history = json.loads(ok("ecm", "history", "reach", "--json").stdout)
    assert [e["action"] for e in history] == ["publish", "promote", "publish", "promote", "rollback"]
    last = history[-1]
    assert (last["version"], last["from_version"], last["to_version"]) == (0, 1, 0)
    assert (last["from_state"], last["to_state"], last["reason"]) == ("superseded", "active", "regressed in the field")
    table = ok("ecm", "history", "reach").stdout.splitlines()
    assert table[-1].split()[:5] == ["5", *table[-1].split()[1:3], "rollback", "v0"]
    assert "v1->v0" in table[-1]

    # The active pointer moved for every reader: pull gets v0's bytes, the set says v0.
    out = tmp_path / "pulled.py"
    ok("ecm", "pull", "reach", "-o", out)
    assert out.read_bytes() == artifact_bytes("v0")
    assert json.loads(ok("ecm", "set", "--json").stdout)["active"] == {"reach": 0}
    assert json.loads(ok("ecm", "list", "--json").stdout)[0]["active_version"] == 0
    assert json.loads(ok("registry", "verify", "--json").stdout)["ok"] is True

    # A stale compare-and-swap is refused over the wire with the same code as locally.
    proc = run_capevo(["ecm", "rollback", "reach", "--expected-active", "1", *conn])
    assert proc.returncode == 5
    assert_clean_error(proc.stderr, "conflict")
    proc = run_capevo(["ecm", "show", "ghost", *conn])
    assert proc.returncode == 4
    assert assert_clean_error(proc.stderr, "not_found") == "no ECM named 'ghost'"

    # SIGTERM stops the server cleanly.
    assert server.stop(signal.SIGTERM) == 0
    proc = run_capevo(["ecm", "list", *conn, "--timeout", "2"])
    assert proc.returncode == 10
    assert_clean_error(proc.stderr, "unavailable")


def test_serve_exits_0_on_sigint(tmp_path: Path, free_port: int) -> None:
    srv = start_server(tmp_path / "r", free_port)
    assert srv.stop(signal.SIGINT) == 0


def test_unreachable_registry_and_password_never_echoed(free_port: int) -> None:
    secret = "s3cret-Pa55word"
    proc = run_capevo(
        ["ecm", "list", "--connect", f"tcp/127.0.0.1:{free_port}", "--user", "alice", "--timeout", "2"],
        env={"CAPEVO_PASSWORD": secret},
    )
    assert proc.returncode == 10
    assert_clean_error(proc.stderr, "unavailable")
    assert secret not in proc.stderr + proc.stdout
    proc = run_capevo(
        [
            "ecm",
            "list",
            "--connect",
            f"tcp/127.0.0.1:{free_port}",
            "--user",
            "alice",
            "--password",
            secret,
            "--timeout",
            "2",
        ]
    )
    assert proc.returncode == 10 and secret not in proc.stderr + proc.stdout


def test_access_control_codes(
    tmp_path: Path, free_port: int, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    config = tmp_path / "registry.yaml"
    config.write_text(
        "users:\n  alice: {password: alice-pw, roles: [operator]}\n  bob: {password: bob-pw, roles: [reader]}\n"
    )
    srv = start_server(tmp_path / "secured", free_port, "--config", str(config))
    try:
        assert srv.info["secured"] is True
        conn = ["--connect", srv.endpoint, "--timeout", "3"]
        publish = ["ecm", "publish", "reach", "--artifact", make_artifact("v0"), "--descriptor", descriptor]
        proc = run_capevo([*publish, *conn], env={"CAPEVO_USER": "alice", "CAPEVO_PASSWORD": "alice-pw"})
        assert proc.returncode == 0, proc.stderr
        proc = run_capevo([*publish, *conn, "--user", "bob", "--password", "bob-pw"])
        assert proc.returncode == 7, proc.stderr
        assert_clean_error(proc.stderr, "forbidden")
        proc = run_capevo(["ecm", "list", *conn, "--json", "--user", "bob", "--password", "bob-pw"])
        assert proc.returncode == 0 and json.loads(proc.stdout)[0]["name"] == "reach"
        proc = run_capevo(["ecm", "list", *conn, "--user", "bob", "--password", "wrong-pw"])
        assert proc.returncode == 10
        assert "wrong-pw" not in proc.stderr
        history = json.loads(
            run_capevo(["ecm", "history", "reach", *conn, "--json", "--user", "bob", "--password", "bob-pw"]).stdout
        )
        assert [e["actor"] for e in history] == ["alice"]
    finally:
        assert srv.stop() == 0


def test_publish_and_pull_a_large_artifact(server: Server, tmp_path: Path, descriptor: Path) -> None:
    big = tmp_path / "big.bin"
    payload = os.urandom(8 * 1024 * 1024)
    big.write_bytes(payload)
    conn = ["--connect", server.endpoint]
    proc = run_capevo(["ecm", "publish", "big", "--artifact", big, "--descriptor", descriptor, "--json", *conn])
    assert proc.returncode == 0, proc.stderr
    version = json.loads(proc.stdout)["version"]
    out = tmp_path / "out.bin"
    proc = run_capevo(["ecm", "pull", "big", "--version", version, "-o", out, *conn])
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() == payload


def test_serve_bad_config_and_taken_port(server: Server, tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("users:\n  alice: {password: pw, roles: [wizard]}\n")
    proc = run_capevo(["registry", "serve", "--root", tmp_path / "r", "--config", bad, "--listen", server.endpoint])
    assert proc.returncode == 3
    assert assert_clean_error(proc.stderr, "invalid").startswith("users.alice.roles[0]")
    # The fixture's server holds the port: a second server cannot open its session.
    proc = run_capevo(
        ["registry", "serve", "--root", tmp_path / "r2", "--listen", server.endpoint, "--log-level", "ERROR"]
    )
    assert proc.returncode == 10
    assert server.endpoint in assert_clean_error(proc.stderr, "unavailable")
