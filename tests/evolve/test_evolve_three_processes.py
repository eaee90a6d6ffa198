"""One full iteration across separate processes over Zenoh (loopback TCP, multicast scouting off):

* the registry server: ``python -m capevo.registry.service``;
* a runtime worker: ``python -m capevo.cli.runtime serve --idle`` (serves evaluations only);
* a learner worker: ``python -m capevo.cli.learner serve --once`` (SAC, tiny budget);
* the loop: ``capevo evolve --connect ... --learner remote --iterations 1`` which seeds v0
  through the registry, runs the live episodes on the runtime worker (RemoteEvaluator), waits
  for the learner's candidate, gates it with the worker's paired evaluations, and records
  the decision in the registry.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from evolve_support import Child, evolve_command, registry_server, wait_for

from capevo.records import Action, Origin, State
from capevo.registry.client import Client
from capevo.runtime.traces import TraceReader

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]


def test_registry_runtime_and_learner_processes_complete_an_iteration(tmp_path: Path, free_port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port}"
    worker_traces = tmp_path / "worker-traces"
    report = tmp_path / "report"
    children: list[Child] = []
    try:
        children.append(registry_server(tmp_path, endpoint))

        evolve = Child(
            evolve_command(
                "--task",
                "T1",
                "--preset",
                "tiny",
                "--iterations",
                "1",
                "--connect",
                endpoint,
                "--learner",
                "remote",
                "--learner-timeout",
                "400",
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

        # v0 exists once evolve seeded it through the registry server
        with Client([endpoint], actor="test") as client:
            assert wait_for(lambda: len(client.capability_set().active) == 3, timeout=120, proc=evolve.proc), (
                evolve.log()
            )

        runtime = Child(
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
                "--step-budget",
                "40",
                "--trace-dir",
                str(worker_traces),
                "--json",
            ],
            tmp_path,
            "runtime",
        )
        children.append(runtime)
        runtime.wait_event("ready", timeout=180)
        learner = Child(
            [
                sys.executable,
                "-m",
                "capevo.cli.learner",
                "serve",
                "--connect",
                endpoint,
                "--ecm",
                "pick.reach",
                "--modality",
                "rl",
                "--preset",
                "tiny",
                "--once",
                "--traces",
                str(worker_traces / "evaluations"),
                "--learner-id",
                "rl-three-proc",
                "--json",
            ],
            tmp_path,
            "learner",
        )
        children.append(learner)

        assert wait_for(lambda: evolve.proc.poll() is not None, timeout=600), evolve.log()
        assert evolve.proc.returncode == 0, evolve.log() + learner.log() + runtime.log()
        assert learner.proc.wait(timeout=120) == 0, learner.log()
        summary = json.loads(evolve.out_path.read_text())

        # the learner process published one candidate; evolve gated it with the worker's episodes
        published = [e for e in learner.lines() if e.get("event") == "published"]
        assert len(published) == 1, learner.log()
        assert summary["iterations"] == 1 and len(summary["gate"]) == 1, summary
        gate = summary["gate"][0]
        assert (gate["ecm"], gate["n"]) == ("pick.reach", 4)
        with Client([endpoint], actor="test") as client:
            record = client.get_version("pick.reach", gate["candidate_version"])
            assert record.origin is Origin.RL and record.provenance.learner_id == "rl-three-proc"
            assert record.created_by == "rl-three-proc" and record.parent == 0
            assert record.state is (State.ACTIVE if gate["decision"] == "promote" else State.REJECTED)
            assert record.gate_evidence is not None and record.gate_evidence["decision"] == gate["decision"]
            actions = [(e.action, e.actor) for e in client.history("pick.reach") if e.version == record.version]
            assert actions[0] == (Action.PUBLISH, "rl-three-proc")
            assert actions[1] == (Action.GATE, "evolve-gate")
            assert actions[2][0] in (Action.PROMOTE, Action.REJECT)
            assert client.verify().ok

        # the episodes ran on the runtime worker: live (3) and both sides of the gate (4 + 4)
        evaluated = [e for e in runtime.lines() if e.get("event") == "evaluated"]
        assert sum(e["seeds"] for e in evaluated) >= 3 + 4 + 4, runtime.log()
        traces = sorted((worker_traces / "evaluations").glob("*.mcap"))
        assert traces
        assert {TraceReader(t).metadata().agent_identity_hash for t in traces} == {summary["identity_hash"]}
        assert summary["delta_pi"] == 0.0
        assert (report / "report.md").is_file() and (report / "metrics.csv").is_file()
    finally:
        for child in reversed(children):
            child.stop()
