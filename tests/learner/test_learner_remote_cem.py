"""``capevo learner serve --modality code --evaluate-on-workers``: CEM's samples run on the runtime
workers, the same path as the gate's and the live episodes (issue 19, "Rollouts across runtime
workers").

Separate processes over loopback Zenoh (scouting off): the registry server, one idle runtime
worker of T1 with no trace directory of the learner's, and a learner doing one update. Every
sample reaches the worker inline (never published), and the samples' traces come back into the
learner's work directory, named after the worker.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from neural_support import REPO, learner_args, start_registry, subprocess_env
from procs import free_tcp_port

from capevo.learner.skills import seed_registry
from capevo.registry.client import Client

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

ECM = "pick.reach"
WORKER = "w-cem"


def test_cem_samples_run_on_the_runtime_worker_and_their_traces_come_back(tmp_path: Path) -> None:
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    registry = start_registry(tmp_path / "registry", port)
    worker_log = tmp_path / "worker.log"
    worker = None
    try:
        with Client([endpoint], actor="tests") as client:
            seed_registry(client, "T1")
        with open(worker_log, "w") as log:
            worker = subprocess.Popen(
                [
                    *(sys.executable, "-m", "capevo.cli.runtime", "serve", "--connect", endpoint, "--task", "T1"),
                    *("--idle", "--horizon", "40", "--worker-id", WORKER, "--json"),
                ],
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
                env=subprocess_env(),
                cwd=REPO,
            )
        assert worker.stdout is not None
        line = worker.stdout.readline()
        assert json.loads(line)["event"] == "ready", line + worker_log.read_text()

        work = tmp_path / "learner"
        done = subprocess.run(
            learner_args(
                endpoint,
                "--ecm",
                ECM,
                "--modality",
                "code",
                "--preset",
                "tiny",
                "--once",
                "--evaluate-on-workers",
                "--work-dir",
                work,
            ),
            capture_output=True,
            text=True,
            env=subprocess_env(),
            cwd=REPO,
            timeout=600,
        )
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
        events = [json.loads(x)["event"] for x in done.stdout.splitlines() if x.strip()]
        assert events[0] == "ready" and events[-1] == "stopped" and ("published" in events or "unchanged" in events)
    finally:
        if worker is not None:
            worker.terminate()
            out, _ = worker.communicate(timeout=60)
        assert registry.stop() == 0, registry.log_text()

    evaluated = [json.loads(x) for x in out.splitlines() if x.strip()]
    evaluated = [e for e in evaluated if e.get("event") == "evaluated"]
    # every sample ran on the worker, as an inline override of the ECM being learned
    assert evaluated and all(e["overrides"] == [ECM] for e in evaluated), evaluated
    traces = sorted(p.name for p in (work / "candidate-traces").glob("*.mcap"))
    assert traces and all(name.startswith(WORKER) for name in traces), traces
    assert not (work / "scratch").exists()  # no in-process scratch registry was built
