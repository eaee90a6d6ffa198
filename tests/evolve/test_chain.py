"""Chains: one iteration learning several ECMs in sequence, each behind the previous candidates,
then gating them as one change (the current set against the set with every member).

Fakes of the evaluator and learner (no simulator); the registry, gate, journal, metrics and the
experience traces (MCAP files) are real.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from evolve_support import (
    NAMES,
    PLAN,
    TASK,
    ChainUpdater,
    Crash,
    ParamUpdater,
    ScriptedEvaluator,
    fake_config,
    make_loop,
    seeded_registry,
)

from capevo.evolve.config import EvolveConfig, make_config
from capevo.evolve.learners import UpdateRequest
from capevo.evolve.loop import UPSTREAM_BELOW, ensure_v0
from capevo.evolve.metrics import read_metrics
from capevo.evolve.progress import RecordingProgress
from capevo.evolve.state import Journal
from capevo.records import State
from capevo.registry.local import LocalRegistry
from capevo.runtime.ecm.code import read_params, with_params

REACH, GRASP, LIFT = NAMES


def _needs(*names: str):
    return lambda versions, seed: all(versions[n] >= 1 for n in names)


def one_iteration(tmp_path: Path, registry: Any, evaluator: Any, updater: Any, *, updates: int = 0) -> Any:
    """Run one evolve iteration with chains of up to ``updates`` ECMs (0: one per step); its metrics row."""
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=updater,
        config=fake_config(iterations=1, updates_per_iteration=updates),
    )
    return loop.run().rows[0]


def test_a_chain_learns_the_next_stalled_step_behind_the_first_and_gates_both(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, GRASP))
    # reach's candidate hands over but its episodes stall in grasp; grasp's candidate succeeds
    updater = ChainUpdater(registry, tmp_path, {REACH: [REACH, GRASP], GRASP: None})
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=updater,
        config=fake_config(iterations=1, updates_per_iteration=0),
    )
    result = loop.run()
    row = result.rows[0]
    assert [r.ecm for r in updater.requests] == [REACH, GRASP]
    # grasp was learned behind reach's (unpublished) candidate, on its own seed slot
    assert set(updater.requests[1].companions) == {REACH}
    assert updater.requests[0].seed_slot != updater.requests[1].seed_slot
    assert row.ecm_updated == REACH and [u.ecm for u in row.further] == [GRASP]
    assert [g.decision for g in row.gates] == ["promote", "promote"]
    # one gate for the chain: the current set against the set with both candidates
    reach_ev = registry.get_version(REACH, 1).gate_evidence
    assert reach_ev["capability_set"] == {
        "candidate": {REACH: 1, GRASP: 1, LIFT: 0},
        "active": {REACH: 0, GRASP: 0, LIFT: 0},
    }
    assert reach_ev["chain"] == {REACH: 1, GRASP: 1} and reach_ev["chain_active"] == {REACH: 0, GRASP: 0}
    assert reach_ev["candidate"]["successes"] == 8 and reach_ev["active"]["successes"] == 0
    grasp_ev = registry.get_version(GRASP, 1).gate_evidence
    assert (grasp_ev["name"], grasp_ev["candidate_version"], grasp_ev["active_version"]) == (GRASP, 1, 0)
    assert grasp_ev["outcomes"] == reach_ev["outcomes"]
    gate_calls = [ran for ran, seeds in evaluator.calls if set(seeds) <= set(PLAN.gate(8, round=0))]
    assert gate_calls == [{REACH: 0, GRASP: 0, LIFT: 0}, {REACH: 1, GRASP: 1, LIFT: 0}]
    assert row.active_after == {REACH: 1, GRASP: 1, LIFT: 0}
    assert "succeeded on all its training episodes" in row.update_note
    assert result.final is not None and all(o.success for o in result.final.final)
    # the metrics row keeps the chain across a round trip
    assert [u.ecm for u in read_metrics(tmp_path / "report")[0].further] == [GRASP]
    assert Journal(tmp_path / "report").last(0, "chain")["members"][1]["ecm"] == GRASP


def test_tied_candidates_join_the_chain_are_gated_with_it_and_cost_nothing_twice(tmp_path: Path) -> None:
    # (--tie-siblings: a search's θ written into the ECMs of the same skill; pick's steps stand in)
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, LIFT))
    updater = ChainUpdater(registry, tmp_path, {REACH: None}, tied={REACH: [LIFT]}, steps=500)
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=0)
    assert [r.ecm for r in updater.requests] == [REACH]
    assert row.ecm_updated == REACH and [u.ecm for u in row.further] == [LIFT]
    assert row.further[0].learner == "param-fake (tied to pick.reach)"
    members = Journal(tmp_path / "report").last(0, "chain")["members"]
    assert [(m["ecm"], m["episodes"], m["steps"]) for m in members] == [(REACH, 4, 500), (LIFT, 0, 0)]
    assert (row.learner_episodes, row.learner_steps) == (4, 500)
    # gated as one change, and only together do they succeed
    assert [(g.ecm, g.decision, g.candidate_successes) for g in row.gates] == [
        (REACH, "promote", 8),
        (LIFT, "promote", 8),
    ]
    assert registry.get_version(REACH, 1).gate_evidence["chain"] == {REACH: 1, LIFT: 1}
    assert row.active_after == {REACH: 1, GRASP: 0, LIFT: 1}


def test_a_tied_member_learned_later_starts_from_its_tied_candidate_and_replaces_its_ties(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, LIFT))
    # reach's episodes end in lift; lift (already a tied member) is learned next, tied back to reach
    updater = ChainUpdater(
        registry, tmp_path, {REACH: [REACH, GRASP, LIFT], LIFT: None}, tied={REACH: [LIFT], LIFT: [REACH]}
    )
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=0)
    assert [r.ecm for r in updater.requests] == [REACH, LIFT]
    lift_request = updater.requests[1]
    assert lift_request.source is not None and lift_request.source != registry.get_artifact(LIFT, 0).decode()
    assert set(lift_request.companions) == {REACH}
    # the chain gates lift's own candidate and reach's copy tied to it (reach's first candidate is replaced)
    chain = Journal(tmp_path / "report").last(0, "chain")["members"]
    assert [(m["ecm"], m["learner"]) for m in chain] == [
        (REACH, "param-fake (tied to pick.lift)"),
        (LIFT, "param-fake"),
    ]
    assert row.active_after == {REACH: 1, GRASP: 0, LIFT: 1}


def test_members_that_only_work_together_are_promoted_together(tmp_path: Path) -> None:
    # grasp's candidate alone succeeds on half the gate seeds, reach's alone on none, both
    # together on all (T6 at 6 pairs, results/h2-t6-4x). Judged one at a time (reach with grasp's
    # candidate on both sides: 8 vs 4; then grasp behind reach v0: 4 vs 0), each gain is too small
    # for 8 pairs (McNemar p 0.0625) and both were rejected; as one change it is 8 vs 0.
    half = set(PLAN.gate(8, round=0)[:4])
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, lambda v, seed: v[GRASP] >= 1 and (v[REACH] >= 1 or seed in half))
    updater = ChainUpdater(registry, tmp_path, {REACH: [REACH, GRASP], GRASP: None})
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=0)
    assert [r.ecm for r in updater.requests] == [REACH, GRASP]
    assert [(g.ecm, g.decision, g.candidate_successes, g.active_successes) for g in row.gates] == [
        (REACH, "promote", 8, 0),
        (GRASP, "promote", 8, 0),
    ]
    assert row.active_after == {REACH: 1, GRASP: 1, LIFT: 0}
    assert registry.get_version(GRASP, 1).state is State.ACTIVE


def test_a_chain_that_is_no_better_is_rejected_whole(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, lambda v, seed: False)
    updater = ChainUpdater(registry, tmp_path, {REACH: [REACH, GRASP], GRASP: None})
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=0)
    assert [(g.ecm, g.decision) for g in row.gates] == [(REACH, "reject"), (GRASP, "reject")]
    assert registry.get_version(REACH, 1).state is State.REJECTED
    assert registry.get_version(GRASP, 1).state is State.REJECTED
    assert row.active_after == {REACH: 0, GRASP: 0, LIFT: 0}


def test_a_step_that_still_fails_to_hand_over_sends_the_chain_upstream(tmp_path: Path) -> None:
    assert 0.0 < UPSTREAM_BELOW <= 1.0
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, GRASP))
    # reach's episodes stall in lift; lift's candidate stalls in lift too (it never hands
    # over): the chain learns lift's predecessor, grasp, next
    updater = ChainUpdater(registry, tmp_path, {REACH: [REACH, GRASP, LIFT], LIFT: [REACH, GRASP, LIFT], GRASP: None})
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=0)
    assert [r.ecm for r in updater.requests] == [REACH, LIFT, GRASP]
    assert set(updater.requests[2].companions) == {REACH, LIFT}
    # gated in plan order
    assert [g.ecm for g in row.gates] == [REACH, GRASP, LIFT]
    assert row.active_after[REACH] == 1 and row.active_after[GRASP] == 1


def test_a_step_graded_unsafe_is_learned_next_even_after_success(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH))
    # reach's candidate succeeds, but the safety monitor graded lift's steps unsafe in its
    # episodes: the chain goes on to lift (once), whose candidate is clean
    updater = ChainUpdater(registry, tmp_path, {REACH: None, LIFT: None}, unsafe={REACH: LIFT})
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=0)
    assert [r.ecm for r in updater.requests] == [REACH, LIFT]
    assert [g.ecm for g in row.gates] == [REACH, LIFT]
    assert "succeeded on all its training episodes" in row.update_note


@pytest.mark.parametrize("limit", [1, 2])
def test_the_chain_respects_its_limit_and_stops_without_improvement(tmp_path: Path, limit: int) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, GRASP, LIFT))
    stalls = {REACH: [REACH, GRASP], GRASP: [REACH, GRASP, LIFT], LIFT: None}
    updater = ChainUpdater(registry, tmp_path, stalls)
    row = one_iteration(tmp_path, registry, evaluator, updater, updates=limit)
    assert [r.ecm for r in updater.requests] == [REACH, GRASP][:limit]
    assert len(row.gates) == limit
    # a learner that brings nothing better ends the chain after the first update
    registry2 = seeded_registry(tmp_path / "b")
    updater2 = ChainUpdater(registry2, tmp_path / "b", stalls, improved=False)
    row2 = (
        make_loop(
            tmp_path / "b",
            registry=registry2,
            evaluator=ScriptedEvaluator(registry2, _needs(REACH)),
            updater=updater2,
            config=fake_config(iterations=1, updates_per_iteration=0),
        )
        .run()
        .rows[0]
    )
    # (after nothing better for grasp, its predecessor is tried once more)
    assert [r.ecm for r in updater2.requests] == [REACH, GRASP, REACH] and row2.further == ()
    assert "found nothing better" in row2.update_note


def test_an_ecm_learned_again_in_a_chain_counts_every_update_and_gates_its_latest(tmp_path: Path) -> None:
    # reach's candidate still stalls in reach: the chain learns reach again from that candidate
    # (improved), then once more (nothing better). The budget must count all three updates,
    # and the gate must judge the second one, not the first it replaced.
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, GRASP))
    spent_each = 1000
    updater = ChainUpdater(registry, tmp_path, {REACH: [REACH]}, improved=[True, True, False], steps=spent_each)
    config = fake_config(iterations=1, updates_per_iteration=0, env_steps_per_iteration=40_000)
    loop = make_loop(tmp_path, registry=registry, evaluator=evaluator, updater=updater, config=config)
    row = loop.run().rows[0]
    assert [r.ecm for r in updater.requests] == [REACH, REACH, REACH]
    caps = [r.max_env_steps for r in updater.requests]
    assert caps[0] is not None and caps[1:] == [caps[0] - spent_each, caps[0] - 2 * spent_each]
    assert row.learner_steps == 3 * spent_each and row.learner_episodes == 3 * 4
    assert row.further == () and row.candidate_version == 1
    # ParamUpdater's k-th proposal scales v0's first parameter by 1.5 k: v1 is the second
    v0 = registry.get_artifact(REACH, 0).decode()
    key = next(iter(read_params(v0)))
    second = with_params(v0, {key: read_params(v0)[key] * 1.5 * 2})
    assert registry.get_artifact(REACH, 1).decode() == second
    assert "found nothing better for " + REACH in row.update_note


def test_resume_gates_a_chain_an_interrupted_attempt_published(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    stalls = {REACH: [REACH, GRASP], GRASP: None}
    # calls: 1 live, 2 the chain gate's active side, 3 its candidate side -> the process "dies"
    crashing = ScriptedEvaluator(registry, _needs(REACH, GRASP), crash_on_call=3)
    config = fake_config(iterations=1, updates_per_iteration=0)
    loop = make_loop(
        tmp_path, registry=registry, evaluator=crashing, updater=ChainUpdater(registry, tmp_path, stalls), config=config
    )
    with pytest.raises(Crash):
        loop.run()
    loop.agent.episodic_memory.close()
    assert registry.get_version(REACH, 1).state is State.CANDIDATE
    assert registry.get_version(GRASP, 1).state is State.CANDIDATE

    updater = ChainUpdater(registry, tmp_path, stalls)
    row = (
        make_loop(
            tmp_path,
            registry=registry,
            evaluator=ScriptedEvaluator(registry, _needs(REACH, GRASP)),
            updater=updater,
            config=config,
        )
        .run()
        .rows[0]
    )
    assert updater.requests == []  # nothing learned again
    assert [(g.ecm, g.decision) for g in row.gates] == [(REACH, "promote"), (GRASP, "promote")]
    assert "resumed" in row.update_note
    assert [v.version for v in registry.get_ecm(GRASP).versions] == [0, 1]


class _DiesOnPromote(LocalRegistry):
    """A registry whose process "dies" at the ``die_at``-th promotion after it is armed."""

    die_at: int | None = None
    promotions = 0

    def promote(self, name: str, version: int, **kwargs: Any) -> Any:
        if self.die_at is not None:
            self.promotions += 1
            if self.promotions == self.die_at:
                raise Crash(f"died promoting {name} v{version}")
        return super().promote(name, version, **kwargs)


def test_resume_finishes_a_chain_decision_from_its_recorded_evidence(tmp_path: Path) -> None:
    registry = _DiesOnPromote(tmp_path / "registry", actor="tester")
    ensure_v0(registry, TASK, modality="code")
    registry.die_at = 2  # the decision is recorded on both, reach promoted, then the crash
    stalls = {REACH: [REACH, GRASP], GRASP: None}
    config = fake_config(iterations=1, updates_per_iteration=0)
    evaluator = ScriptedEvaluator(registry, _needs(REACH, GRASP))
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=ChainUpdater(registry, tmp_path, stalls),
        config=config,
    )
    with pytest.raises(Crash):
        loop.run()
    loop.agent.episodic_memory.close()
    assert registry.get_version(REACH, 1).state is State.ACTIVE
    assert registry.get_version(GRASP, 1).state is State.CANDIDATE
    assert registry.get_version(GRASP, 1).gate_evidence["decision"] == "promote"
    calls = len(evaluator.calls)

    registry.die_at = None
    evaluator2 = ScriptedEvaluator(registry, _needs(REACH, GRASP))
    row = (
        make_loop(
            tmp_path,
            registry=registry,
            evaluator=evaluator2,
            updater=ChainUpdater(registry, tmp_path, stalls),
            config=config,
        )
        .run()
        .rows[0]
    )
    # finished from the evidence: grasp promoted without gating again (only the redone live
    # episodes and the final evaluation ran)
    assert registry.get_version(GRASP, 1).state is State.ACTIVE
    assert [(g.ecm, g.decision) for g in row.gates] == [(REACH, "promote"), (GRASP, "promote")]
    gate_seeds = set(PLAN.gate(8, round=0))
    assert not [c for c in evaluator2.calls if set(c[1]) <= gate_seeds]
    assert calls == 3
    history = [e.action.value for e in registry.history(GRASP) if e.version == 1]
    assert history == ["publish", "gate", "promote"]


def test_presets_chain_code_updates_and_round_trip() -> None:
    assert make_config("cpu-small").updates_per_iteration == 0
    assert make_config("tiny").updates_per_iteration == 2
    c = make_config("cpu-small", updates_per_iteration=3, live_episodes=10)
    assert EvolveConfig.from_dict(c.to_dict()) == c
    assert c.cem.train_seeds_per_update == c.cem.iterations * c.cem.episodes_per_candidate + 4
    # an old config without the field resumes as one update per iteration
    old = {k: v for k, v in c.to_dict().items() if k != "updates_per_iteration"}
    assert EvolveConfig.from_dict(old).updates_per_iteration == 1


def test_the_gate_refuses_a_chain_it_cannot_judge(tmp_path: Path) -> None:
    from capevo.errors import IllegalTransition, Invalid
    from capevo.runtime.gate import Gate

    registry = seeded_registry(tmp_path)
    updater = ParamUpdater(registry)
    for ecm in (REACH, GRASP):
        request = UpdateRequest(task=TASK, ecm=ecm, iteration=0, outcomes=(), plan=PLAN, seed=0)
        proposal = updater.propose(request, RecordingProgress())
        assert proposal is not None and proposal.candidate is not None
        registry.publish(ecm, proposal.candidate.artifact, proposal.candidate.spec)
    gate = Gate(registry, ScriptedEvaluator(registry, _needs(REACH, GRASP)), fake_config().gate, seed_plan=PLAN)
    seeds = PLAN.gate(8, round=0)
    with pytest.raises(Invalid, match="names the gated ECM"):
        gate.run(REACH, 1, task=TASK, seeds=seeds, with_candidates={REACH: 1})
    with pytest.raises(IllegalTransition):  # v0 is active, not a candidate
        gate.run(REACH, 1, task=TASK, seeds=seeds, with_candidates={GRASP: 0})
    with pytest.raises(Invalid, match="chain"):
        gate.settle({"decision": "promote"})
    # nothing was recorded or moved by the refusals
    assert registry.get_version(REACH, 1).state is State.CANDIDATE
    assert registry.get_version(REACH, 1).gate_evidence is None
    decision = gate.run(REACH, 1, task=TASK, seeds=seeds, with_candidates={GRASP: 1})
    assert decision.promoted and [m.name for m in decision.members] == [GRASP]
    assert decision.to_dict()["members"][0]["state"] == "active"
