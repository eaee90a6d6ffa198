"""``run_evolution`` runs two ``tiny`` iterations on T4 nut_assembly, T5 pick_place_multi and T6
peg_in_hole: real robosuite, real registry, governance on, the paper's perturbations (issue 19).

What this shows: the loop works end to end on the three tasks that had never been run (v0 seeded,
live episodes governed and traced, a CEM candidate of the ECM the traces blame, the gate's decision in
the registry, the final evaluation, the report), and that every candidate's PARAMS stay inside the
skill's declared PARAM_RANGES. What it cannot show: any learning. ``tiny`` cuts episodes at 40 steps,
far short of the tasks' horizons (T4 and T6 300, T5 900), so no episode can succeed; figures come
from ``cpu-small`` runs, not from here.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from capevo.errors import Invalid
from capevo.evolve.run import EvolveOptions, run_evolution
from capevo.learner.search import read_ranges
from capevo.records import State
from capevo.registry.local import LocalRegistry
from capevo.runtime.ecm.code import read_params
from capevo.runtime.tasks import task_spec
from capevo.runtime.traces import TraceReader

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("task", ["T4", "T5", "T6"])
def test_two_tiny_iterations(task: str, tmp_path: Path) -> None:
    root, report = tmp_path / "data", tmp_path / "report"
    result = run_evolution(EvolveOptions(task=task, preset="tiny", root=root, report_dir=report, seed=0))
    rows = result.rows
    names = task_spec(task).ecm_names
    assert [r.iteration for r in rows] == [0, 1]
    assert sorted(f"{r.name}@{r.version}" for r in result.created) == sorted(f"{n}@0" for n in names)

    for r in rows:
        # every live episode ran under governance, was graded by the monitor and traced
        assert r.live.episodes == 3 and r.env_steps_live > 0
        assert r.live.unsafe_steps >= 0
        seeds = [s.seed for path in r.traces for s in TraceReader(path).episode_summaries()]
        assert sorted(seeds) == sorted(r.live_seeds)
        assert r.delta_pi == 0.0

    registry = LocalRegistry(root, actor="test")
    try:
        learned = [r for r in rows if r.candidate_version is not None]
        assert learned, [r.update_note for r in rows]
        for r in learned:
            assert r.learner_steps > 0  # the learner's episodes are counted
            record = registry.get_version(r.ecm_updated, r.candidate_version)
            assert record.state in (State.ACTIVE, State.REJECTED, State.CANDIDATE)
            source = registry.get_artifact(r.ecm_updated, r.candidate_version).decode()
            params, ranges = read_params(source), read_ranges(source)
            assert set(ranges) == set(params)
            for key, value in params.items():
                assert ranges[key].low <= value <= ranges[key].high, (r.ecm_updated, key, value)
        gated = [r for r in rows if r.gate is not None]
        assert gated, [r.update_note for r in rows]
        for r in gated:
            record = registry.get_version(r.gate.ecm, r.gate.candidate_version)
            assert record.gate_evidence is not None and record.gate_evidence["decision"] == r.gate.decision
        assert registry.verify().ok
    finally:
        registry.close()

    assert (report / "report.md").is_file()
    assert result.final is not None and [o.seed for o in result.final.final] == list(rows[0].live_seeds)


def test_t5_with_tied_siblings_publishes_and_gates_each_steps_params_for_all_three_objects(tmp_path: Path) -> None:
    from capevo.learner.skills import siblings

    root = tmp_path / "data"
    options = EvolveOptions(task="T5", preset="tiny", root=root, report_dir=tmp_path / "report", tie_siblings=True)
    assert options.resolved_config().cem.tie_siblings
    with pytest.raises(Invalid, match="--modality code"):
        EvolveOptions(task="T5", modality="il", tie_siblings=True)
    rows = run_evolution(options).rows
    learned = [r for r in rows if r.candidate_version is not None]
    assert learned, [r.update_note for r in rows]
    registry = LocalRegistry(root, actor="test")
    try:
        for r in learned:
            members = {r.ecm_updated: r.candidate_version, **{u.ecm: u.version for u in r.further}}
            params = {e: read_params(registry.get_artifact(e, v).decode()) for e, v in members.items()}
            for ecm, theta in params.items():
                # every member came with its two siblings, all three at one θ, gated as one change
                assert all(params[s] == theta for s in siblings("T5", ecm)), (ecm, members)
            ev = registry.get_version(r.ecm_updated, r.candidate_version).gate_evidence
            assert ev is not None and ev["chain"] == members
    finally:
        registry.close()
    assert "| tied siblings | on" in (tmp_path / "report" / "report.md").read_text()
