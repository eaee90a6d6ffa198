"""Crash and resume for real: SIGKILL a running ``python -m capevo evolve`` process mid-iteration,
rerun the same command, and check that it continues where the files on disk say.

The kill lands right after the journal records the first candidate a learner published (before
its gate ran), or, if iteration 0 publishes none, as iteration 1 starts.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from evolve_support import NAMES, evolve_command, kill, run_cli, wait_for

from capevo.agent import read_episodes
from capevo.evolve.audit import learner_step_checks
from capevo.evolve.metrics import read_metrics
from capevo.records import Action, State
from capevo.registry.local import LocalRegistry

pytestmark = pytest.mark.slow


def _events(report: Path) -> list[dict]:
    path = report / "journal.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


def test_sigkill_mid_iteration_then_resume(tmp_path: Path) -> None:
    root, report = tmp_path / "data", tmp_path / "report"
    args = evolve_command(
        "--task", "T1", "--preset", "tiny", "--root", str(root), "--report-dir", str(report), "--json"
    )
    log = open(tmp_path / "first.log", "w")  # noqa: SIM115 - the child writes it
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT)
    try:

        def mid_iteration() -> bool:
            # right after a candidate is published (before its gate), or as iteration 1 starts
            return any(
                e["event"] == "candidate" or (e["event"] == "start" and e["iteration"] == 1) for e in _events(report)
            )

        reached = wait_for(mid_iteration, timeout=400, proc=proc)
        assert reached, (tmp_path / "first.log").read_text()[-3000:]
    finally:
        kill(proc)
        log.close()
    assert proc.returncode == -9
    killed_at = _events(report)[-1]
    k = killed_at["iteration"]
    rows_before = read_metrics(report)
    assert [r.iteration for r in rows_before] == list(range(k))  # no row for the interrupted iteration
    row_lines = (report / "metrics.jsonl").read_text().splitlines() if rows_before else []
    registry = LocalRegistry(root, actor="test")
    versions_before = {n: [v.version for v in registry.get_ecm(n).versions] for n in NAMES}
    registry.close()

    done = run_cli(args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout)
    assert summary["resumed_from"] == k and summary["iterations"] == 2
    if k:
        assert f"resuming pick: {k} iteration(s) already done" in done.stderr

    rows = read_metrics(report)
    assert [r.iteration for r in rows] == [0, 1]
    assert (report / "metrics.jsonl").read_text().splitlines()[:k] == row_lines  # finished rows untouched
    assert len((report / "metrics.csv").read_text().splitlines()) == 3
    # one start per iteration: the interrupted one was continued, not started afresh
    assert [e["event"] for e in _events(report) if e["iteration"] == k].count("start") == 1

    registry = LocalRegistry(root, actor="test")
    try:
        assert registry.verify().ok
        for name in NAMES:
            versions = registry.get_ecm(name).versions
            assert all(v.state is not State.CANDIDATE for v in versions), name
            for v in versions:
                gates = [e for e in registry.history(name) if e.version == v.version and e.action is Action.GATE]
                assert len(gates) <= 1, (name, v.version)
        if killed_at["event"] == "candidate":
            # the rerun gated the candidate published before the kill instead of learning another
            name, version = killed_at["ecm"], killed_at["version"]
            assert version in versions_before[name]
            assert registry.get_version(name, version).gate_evidence is not None
            assert rows[k].candidate_version == version and rows[k].gate is not None
            assert "resumed" in rows[k].update_note
            if k == 1:
                assert [v.version for v in registry.get_ecm(name).versions] == versions_before[name]
    finally:
        registry.close()

    # M_ep: the redone live episodes were not appended twice
    memory = read_episodes(report / "agent" / "episodic.jsonl")
    pairs = [(m.iteration, m.seed) for m in memory.records]
    assert len(pairs) == len(set(pairs))
    assert sorted(pairs) == sorted((r.iteration, s) for r in rows for s in r.live_seeds)
    assert (report / "report.md").is_file() and (report / "timeline.png").is_file()

    # the learners' traces still account for every recorded learner step: the interrupted
    # attempt's traces are counted apart, and the redo's row records them only if it gated what
    # that attempt learned
    checks = learner_step_checks(report)
    assert [c.iteration for c in checks] == [0, 1]
    assert all(c.ok for c in checks), checks
    if killed_at["event"] == "candidate":
        assert checks[k].interrupted > 0 and checks[k].recorded == checks[k].traced + checks[k].interrupted
        assert checks[k].discarded == 0

    # a third run has nothing left to do
    again = run_cli(args, cwd=tmp_path)
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads(again.stdout)["resumed_from"] == 2
    assert [r.iteration for r in read_metrics(report)] == [0, 1]
