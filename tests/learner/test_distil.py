"""``capevo learner distil``: a set's successful traces cloned into neural ECMs and gated as one
change (issue 19's hybrid path, :mod:`capevo.evolve.distil`), as a real process on a real registry
directory, real MCAP traces and real robosuite episodes at the ``tiny`` preset."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from neural_support import subprocess_env, write_scripted_trace

from capevo.learner.skills import seed_registry
from capevo.records import Kind, Origin, State
from capevo.registry.local import LocalRegistry

PICK = ("pick.reach", "pick.grasp", "pick.lift")


@pytest.fixture(scope="module")
def pick_traces(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One real T1 trace: seed 0 runs to success, seed 1 is cut after 10 steps (a failure)."""
    d = tmp_path_factory.mktemp("traces")
    write_scripted_trace(
        d / "pick-run.mcap", seeds=[0, 1], horizons=[80, 10], versions=dict.fromkeys(PICK, 0), inputs={}
    )
    return d


def _distil(root: Path, task: str, traces: Path, *, as_json: bool = True) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "capevo", "learner", "distil", "--root", str(root), "--task", task]
    cmd += ["--traces", str(traces), "--preset", "tiny", "--round", "0", *(["--json"] if as_json else [])]
    return subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(), timeout=900, check=False)


@pytest.mark.slow
def test_every_ecm_with_demonstrations_is_cloned_and_all_are_decided_together(
    tmp_path: Path, pick_traces: Path
) -> None:
    root = tmp_path / "reg"
    with LocalRegistry(root, actor="test") as reg:
        seed_registry(reg, "pick")
    done = _distil(root, "T1", pick_traces)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout)  # one JSON document on stdout; the learners' events on stderr
    assert result["task"] == "pick" and result["skipped"] == {}
    assert result["candidates"] == dict.fromkeys(PICK, 1)
    decision = result["decision"]
    assert (decision["name"], decision["candidate_version"]) == ("pick.reach", 1)
    assert {(m["name"], m["version"]) for m in decision["members"]} == {("pick.grasp", 1), ("pick.lift", 1)}
    trace_file = str((pick_traces / "pick-run.mcap").resolve())
    with LocalRegistry(root, actor="reader") as reg:
        records = [reg.get_version(name, 1) for name in PICK]
        active = reg.capability_set().active
    for record in records:
        assert (record.kind, record.origin, record.parent) == (Kind.NEURAL, Origin.IL, 0)
        assert trace_file in record.provenance.traces
    # one decision for all: every clone is active, or none is and v0 stays
    want = State.ACTIVE if result["promoted"] else State.REJECTED
    assert {r.state for r in records} == {want}
    assert active == dict.fromkeys(PICK, 1 if result["promoted"] else 0)


@pytest.mark.slow
def test_without_json_it_names_the_clones_and_the_decision_for_people(tmp_path: Path, pick_traces: Path) -> None:
    root = tmp_path / "reg"
    with LocalRegistry(root, actor="test") as reg:
        seed_registry(reg, "pick")
    done = _distil(root, "T1", pick_traces, as_json=False)
    assert done.returncode == 0, done.stderr[-3000:]
    first, second = done.stdout.splitlines()
    assert first == "cloned: pick.reach v1, pick.grasp v1, pick.lift v1"
    with LocalRegistry(root, actor="reader") as reg:
        promoted = reg.get_version("pick.reach", 1).state is State.ACTIVE
    verdict, action = ("promoted", "promote") if promoted else ("rejected", "reject")
    assert second.startswith(f"{verdict} as one change: gate: {action} pick.reach v1 ")
    assert second.endswith("decided together with pick.grasp v1, pick.lift v1, as one change")


@pytest.mark.slow
def test_with_no_demonstrations_for_any_ecm_nothing_is_published_or_gated(tmp_path: Path, pick_traces: Path) -> None:
    # T6 has no scripted reference, and a trace of T1 holds none of its steps
    root = tmp_path / "reg"
    with LocalRegistry(root, actor="test") as reg:
        seed_registry(reg, "peg_in_hole")
        before = reg.capability_set()
    done = _distil(root, "T6", pick_traces)
    assert done.returncode == 3, done.stderr[-3000:]
    assert done.stdout == ""
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("error [invalid]: nothing to distil: no ECM of peg_in_hole has demonstration rows")
    assert done.stderr.count("kept as it is") == 8
    with LocalRegistry(root, actor="reader") as reg:
        assert reg.capability_set() == before
        assert all(len(reg.get_ecm(name).versions) == 1 for name in before.active)
