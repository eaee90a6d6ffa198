"""End to end on real robosuite: ``run_evolution`` on T1 pick with the ``tiny`` preset, embedded.

Two iterations: live episodes (governed, traced, remembered), a CEM candidate of the ECM the
traces blame, the gate on paired held-out seeds, the decision in the registry, the final
evaluation and the report. Budget: ~40-step episodes; about 30 episodes in all.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from evolve_support import NAMES

from capevo.agent import DecompositionPolicy, IdentityMemory, PersistentAgent, read_episodes
from capevo.agent.episodic import EpisodicMemory
from capevo.evolve.metrics import read_metrics
from capevo.evolve.progress import RecordingProgress
from capevo.evolve.run import EvolveOptions, run_evolution
from capevo.records import Action, State
from capevo.registry.local import LocalRegistry
from capevo.runtime.traces import TraceReader

pytestmark = pytest.mark.slow


def test_two_tiny_iterations_on_t1(tmp_path: Path) -> None:
    root, report = tmp_path / "data", tmp_path / "report"
    progress = RecordingProgress()
    result = run_evolution(
        EvolveOptions(task="T1", preset="tiny", root=root, report_dir=report, seed=0), progress=progress
    )
    rows = result.rows
    assert [r.iteration for r in rows] == [0, 1]

    # versions were created at 0 (manual) and candidates published, gated and decided
    assert sorted(f"{r.name}@{r.version}" for r in result.created) == sorted(f"{n}@0" for n in NAMES)
    registry = LocalRegistry(root, actor="test")
    try:
        gated = [r for r in rows if r.gate is not None]
        assert gated, [r.update_note for r in rows]
        for r in gated:
            assert r.gate is not None
            name, version = r.gate.ecm, r.gate.candidate_version
            record = registry.get_version(name, version)
            assert record.state in (State.ACTIVE, State.REJECTED)
            assert record.gate_evidence is not None and record.gate_evidence["decision"] == r.gate.decision
            assert record.gate_evidence["n"] == 4 and record.parent is not None
            assert record.provenance.learner_id and record.provenance.config_hash
            actions = [e.action for e in registry.history(name) if e.version == version]
            assert actions[:2] == [Action.PUBLISH, Action.GATE]
            assert actions[2] in (Action.PROMOTE, Action.REJECT)
        assert registry.verify().ok
    finally:
        registry.close()

    # the persistent agent did not change
    fresh = PersistentAgent(
        DecompositionPolicy(identity=IdentityMemory.default()),
        IdentityMemory.default(),
        EpisodicMemory(tmp_path / "scratch-memory.jsonl"),
    )
    assert result.identity_hash == fresh.identity_hash
    assert {r.identity_hash for r in rows} == {fresh.identity_hash}
    assert result.delta_pi == 0.0 and all(r.delta_pi == 0.0 for r in rows)

    # traces exist and read back: one episode summary per live episode, with the identity hash
    for r in rows:
        assert r.traces
        summaries = []
        for path in r.traces:
            reader = TraceReader(path)
            assert reader.metadata().agent_identity_hash == result.identity_hash
            summaries += [s.seed for s in reader.episode_summaries()]
        assert sorted(summaries) == sorted(r.live_seeds)
    gate_traces = list((report / "traces" / "gate").glob("*.mcap"))
    assert gate_traces and all(sum(1 for _ in TraceReader(p).episode_summaries()) == 4 for p in gate_traces)

    # episodic memory: every live episode once
    memory = read_episodes(report / "agent" / "episodic.jsonl")
    assert sorted((m.iteration, m.seed) for m in memory.records) == sorted(
        (r.iteration, s) for r in rows for s in r.live_seeds
    )

    # metrics on disk equal the result; the report's files exist
    assert read_metrics(report) == list(rows)
    for name in ("report.md", "metrics.csv", "metrics.jsonl", "progress.png", "timeline.png"):
        assert (report / name).is_file(), name
    for png in ("progress.png", "timeline.png"):
        assert (report / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = (report / "report.md").read_text()
    assert "## What version 0 is" in text and "manual creation" in text
    assert result.identity_hash in text
    assert "| 0 |" in text and "| 1 |" in text
    assert result.final is not None and [o.seed for o in result.final.final] == list(rows[0].live_seeds)
    assert "iteration_finished" in progress.names()
