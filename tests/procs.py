"""Real child processes and threads in tests: loopback ports, the registry server, stopping
processes, running one function on many threads at once.

``start_server`` runs ``python -m capevo.registry.service`` as a subprocess on a loopback port
and waits for its ``READY`` line; every test that needs a registry server process starts it
here, whichever directory the test lives in.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from capevo.registry.client import Client

LOOPBACK = "127.0.0.1"
T = TypeVar("T")


def free_tcp_port() -> int:
    """A loopback TCP port that was free a moment ago (bind to 0, read, release)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def terminate(proc: subprocess.Popen[str], timeout: float) -> int:
    """SIGTERM and wait up to ``timeout`` s, then SIGKILL; the exit code (negative for a signal)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return int(proc.returncode)


def kill(proc: subprocess.Popen[str]) -> None:
    """SIGKILL: no handler runs, nothing is flushed or closed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def run_in_threads(fn: Callable[[int], T], n: int) -> list[T]:
    """``fn(0)``, ..., ``fn(n - 1)``, each on a thread of its own, all started before any is joined.

    Returns:
        The results, in call order.

    Raises:
        BaseException: the first exception a call raised, once every thread has ended.
    """
    results: list[Any] = [None] * n
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            results[i] = fn(i)
        except BaseException as exc:  # re-raised in the calling thread below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return results


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
        from capevo.registry.client import Client

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
        info = wait_ready(proc, ready_timeout)
        if info is not None:
            return ServerProcess(proc=proc, root=root, port=p, namespace=namespace, info=info, log_path=log_path)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        last_error = log_path.read_text(errors="replace")
    raise RuntimeError(f"registry server did not start:\n{last_error}")


def wait_ready(proc: subprocess.Popen[str], timeout: float) -> dict[str, Any] | None:
    from capevo.registry.service import READY_PREFIX

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
