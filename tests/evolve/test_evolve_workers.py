"""``capevo evolve --connect`` with two runtime workers: one path for every episode (issue 19).

Separate processes over loopback Zenoh (scouting off): the registry server, two idle runtime
workers of T1, and ``capevo evolve --connect ... --modality code`` with its learner in process.
The live (and gate) episodes run on the workers, and CEM's candidate samples, never
published, reach the workers inline and run there too. Their traces come back into the
report directory, where CEM reads them; no process reads another's files.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from evolve_support import Child, evolve_command, registry_server, wait_for

from capevo.registry.client import Client

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

WORKERS = ("w-evo-a", "w-evo-b")


def test_live_gate_and_cem_episodes_all_run_on_the_workers(tmp_path: Path, free_port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port}"
    report = tmp_path / "report"
    children: list[Child] = []
    try:
        children.append(registry_server(tmp_path, endpoint))
        evolve = Child(
            evolve_command(
                "--task",
                "T1",
                "--modality",
                "code",
                "--preset",
                "tiny",
                "--iterations",
                "1",
                "--connect",
                endpoint,
                "--worker-wait",
                "200",
                "--report-dir",
                str(report),
                "--json",
            ),
            tmp_path,
            "evolve",
        )
        children.append(evolve)
        with Client([endpoint], actor="test") as client:
            assert wait_for(lambda: len(client.capability_set().active) == 3, timeout=120, proc=evolve.proc), (
                evolve.log()
            )
        workers = {}
        for worker_id in WORKERS:
            # no --trace-dir: whatever the learner reads must come back over Zenoh
            workers[worker_id] = Child(
                [
                    sys.executable,
                    "-m",
                    "capevo.cli.runtime",
                    "serve",
                    "--connect",
                    endpoint,
                    "--task",
                    "T1",
                    "--idle",
                    "--horizon",
                    "40",
                    "--worker-id",
                    worker_id,
                    "--json",
                ],
                tmp_path,
                worker_id,
            )
            children.append(workers[worker_id])
        for child in workers.values():
            child.wait_event("ready", timeout=180)

        assert wait_for(lambda: evolve.proc.poll() is not None, timeout=600), evolve.log()
        assert evolve.proc.returncode == 0, evolve.log() + "".join(c.log() for c in workers.values())
        summary = json.loads(evolve.out_path.read_text())
        # at `tiny` CEM may find nothing better (then nothing is gated): the episodes' path is the point
        assert summary["iterations"] == 1, summary
    finally:
        for child in reversed(children):
            child.stop()

    evaluated = {w: [e for e in c.lines() if e.get("event") == "evaluated"] for w, c in workers.items()}
    # the live episodes ran on the workers (split across those up at the time: evolve starts as
    # soon as one is ready, so which ones is a race; test_fanout checks the split itself)
    assert any(not e["overrides"] for events in evaluated.values() for e in events), evaluated
    # CEM's samples ran on the workers, as inline overrides of the ECM being learned
    inline = [e for events in evaluated.values() for e in events if e["overrides"]]
    assert inline, evaluated
    assert {tuple(e["overrides"]) for e in inline} <= {("pick.reach",), ("pick.grasp",), ("pick.lift",)}
    # and their traces came back into the report, named after the worker that ran them
    learner_traces = sorted(p.name for p in (report / "traces" / "learner").glob("*.mcap"))
    assert learner_traces and all(name.startswith(WORKERS) for name in learner_traces), learner_traces
    # so did the live episodes' traces, and the loop read them to choose what to learn
    live_traces = sorted(p.name for p in (report / "traces" / "live").glob("*.mcap"))
    assert live_traces and all(name.startswith(WORKERS) for name in live_traces), live_traces
    assert "no readable traces" not in evolve.log()
