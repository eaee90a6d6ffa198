"""``capevo experiment run --address ray://...`` on a real Ray cluster that the test starts with
``ray start --head``, the way a user with more machines would (issue 20): the driver is a separate
process that joins through the Ray Client port, the cell runs on the cluster's worker, and its
files come back to the driver's run directory.

Ray >= 2.59 turns token authentication on for clusters it starts; the test sets the token mode and
a token of its own on both sides (``RAY_AUTH_MODE``, ``RAY_AUTH_TOKEN``), as docs/multi-host.md
tells a user to, so it never reads or writes the user's ``~/.ray``.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
GRID = """
name: cluster
tasks: [T1]
seeds: [1]
iterations: 1
budget: {env_steps_per_iteration: 100, eval_episodes: 2, horizon: 30}
methods: [s-ecm]
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for_port(port: int, head: subprocess.Popen[bytes], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert head.poll() is None, "ray start --head exited"
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=1.0):
            return
        time.sleep(0.5)
    raise AssertionError(f"the Ray Client port {port} did not open within {timeout} s")


def _client_server_logs(temp: Path) -> str:
    """The tails of the head's Ray Client server logs, where Ray says why a join failed."""
    return "".join(
        f"\n== {log.name}\n{log.read_text(errors='replace')[-1500:]}"
        for log in sorted(temp.glob("session_latest/logs/ray_client_server*"))
    )


@pytest.fixture
def cluster() -> Iterator[tuple[str, dict[str, str], Path]]:
    """A one-node Ray cluster with token auth; yields its ``ray://`` address, the client's env and
    the head's temp dir (its logs explain a failed join)."""
    # a short temp dir: Ray's socket paths must fit in 107 bytes
    temp = Path(tempfile.mkdtemp(prefix="rt", dir="/tmp"))
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    gcs, client = _free_port(), _free_port()
    ray = str(Path(sys.executable).with_name("ray"))
    head = subprocess.Popen(
        [
            *(ray, "start", "--head", "--block", "--num-cpus", "1", "--port", str(gcs)),
            *("--ray-client-server-port", str(client), "--include-dashboard=false", "--disable-usage-stats"),
            *("--temp-dir", str(temp)),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: the head's raylet and workers are ours to end
    )
    try:
        _wait_for_port(client, head)
        yield f"ray://127.0.0.1:{client}", env, temp
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            head.wait(timeout=30)  # ray start --block stops what it started on SIGTERM
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGKILL)
        head.wait(timeout=30)
        shutil.rmtree(temp, ignore_errors=True)


def test_a_grid_runs_on_an_existing_cluster_joined_through_its_client_address(
    cluster: tuple[str, dict[str, str], Path], tmp_path: Path
) -> None:
    address, env, temp = cluster
    grid = tmp_path / "grid.yaml"
    grid.write_text(GRID, encoding="utf-8")
    run_dir = tmp_path / "run"
    done = subprocess.run(
        [
            *(sys.executable, "-m", "capevo", "experiment", "run", str(grid), "--out", str(run_dir)),
            *("--address", address, "--no-report"),
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:] + _client_server_logs(temp)
    cell = run_dir / "cells" / "T1-s-ecm-s1"
    record = json.loads((cell / "metrics.jsonl").read_text(encoding="utf-8").splitlines()[0])
    assert record["iteration"] == 1 and len(record["episodes"]) == 2
    assert json.loads((cell / "done.json").read_text())["env_steps_eval"] > 0
    assert list(cell.glob("traces/**/*.mcap")) and (cell / "registry").is_dir()
    provenance = json.loads((run_dir / "provenance.json").read_text())
    assert provenance["ray"]["address"] == address and provenance["cells"]["run"] == 1
