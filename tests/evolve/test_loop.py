"""The closed loop over fakes of the evaluator and the learner (no simulator; real registry, gate,
monitor, agent, episodic memory and metrics files).

Invariants of :mod:`capevo.evolve.loop` tested here: 1 (identity checked every iteration, Δπ 0),
2 (every published candidate gated in its iteration, evidence before the move), 3 (seed ranges),
4 (metrics rows only for finished iterations), 5 (no episode remembered twice on a redo).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from evolve_support import (
    NAMES,
    PLAN,
    TASK,
    Crash,
    ParamUpdater,
    ScriptedEvaluator,
    fake_config,
    make_agent,
    make_loop,
    reach_at_least,
    seeded_registry,
)

from capevo.agent.episodic import read_episodes
from capevo.agent.policy import PolicyParameters
from capevo.errors import ErrorCode, IdentityViolation, Invalid, Unavailable
from capevo.evolve.learners import waiting_candidates
from capevo.evolve.loop import ensure_v0, task_capability_set
from capevo.evolve.metrics import read_metrics
from capevo.evolve.progress import RecordingProgress
from capevo.evolve.state import Journal, load_manifest
from capevo.records import Action, Origin, State
from capevo.registry.local import LocalRegistry
from capevo.runtime.monitor import MonitorConfig


def _actions(registry: LocalRegistry, name: str) -> list[tuple[str, int | None]]:
    return [(e.action.value, e.version) for e in registry.history(name)]


def test_v0_is_manual_creation_of_every_ecm(tmp_path: Path) -> None:
    registry = LocalRegistry(tmp_path / "r", actor="tester")
    created = ensure_v0(registry, TASK, modality="code")
    assert [(r.name, r.version, r.state, r.origin) for r in created] == [
        (n, 0, State.ACTIVE, Origin.MANUAL) for n in NAMES
    ]
    assert ensure_v0(registry, TASK, modality="code") == []  # idempotent
    # seeding interrupted between publish and promote: the manual candidate is promoted
    registry2 = LocalRegistry(tmp_path / "r2", actor="tester")
    from capevo.learner.skills import seed_registry

    seed_registry(registry2, TASK, promote=False)
    done = ensure_v0(registry2, TASK, modality="code")
    assert sorted(r.name for r in done) == sorted(NAMES)
    assert task_capability_set(registry2, TASK) == dict.fromkeys(NAMES, 0)


def test_two_iterations_learn_gate_promote_and_record(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, reach_at_least(1))
    updater = ParamUpdater(registry)
    progress = RecordingProgress()
    loop = make_loop(tmp_path, registry=registry, evaluator=evaluator, updater=updater, progress=progress)
    result = loop.run()

    rows = result.rows
    assert [r.iteration for r in rows] == [0, 1]
    # iteration 0: v0 fails everything live; the fake learner's reach v1 wins 8/8 at the gate
    assert rows[0].live.successes == 0 and rows[0].ecm_updated == "pick.reach"
    assert rows[0].gate is not None and rows[0].gate.decision == "promote"
    assert rows[0].gate.n == 8 and rows[0].gate.p_success is not None and rows[0].gate.p_success < 0.05
    assert rows[0].active_after["pick.reach"] == 1
    # iteration 1 runs the promoted set live and succeeds: nothing left to improve
    assert rows[1].active_versions["pick.reach"] == 1 and rows[1].live.successes == 3
    assert rows[1].gate is None and "nothing to improve" in rows[1].update_note
    # invariant 1: identity unchanged and Δπ exactly 0 every iteration
    assert {r.identity_hash for r in rows} == {loop.agent.identity_hash}
    assert all(r.delta_pi == 0.0 for r in rows) and result.delta_pi == 0.0
    # invariant 2: publish -> gate (evidence) -> promote, in that order, in the audit history
    assert _actions(registry, "pick.reach") == [
        ("publish", 0),
        ("promote", 0),
        ("publish", 1),
        ("gate", 1),
        ("promote", 1),
    ]
    gate_event = next(e for e in registry.history("pick.reach") if e.action is Action.GATE)
    assert gate_event.actor == "evolve-gate"
    assert registry.get_version("pick.reach", 1).gate_evidence["decision"] == "promote"
    # invariant 3: live seeds from the live range, disjoint across iterations; gate seeds held out
    assert all(PLAN.purpose_of(s) == "live" for r in rows for s in r.live_seeds)
    assert not set(rows[0].live_seeds) & set(rows[1].live_seeds)
    gate_seeds = registry.get_version("pick.reach", 1).gate_evidence["seeds"]
    assert all(PLAN.purpose_of(s) == "gate" for s in gate_seeds)
    # M_ep holds the live episodes, tagged with their iteration
    log = read_episodes(tmp_path / "report" / "agent" / "episodic.jsonl")
    assert [(r.iteration, r.seed) for r in log.records] == [(r.iteration, s) for r in rows for s in r.live_seeds]
    # the final evaluation reran iteration 0's seeds with the final set
    assert result.final is not None and result.final.final_versions["pick.reach"] == 1
    assert [o.seed for o in result.final.final] == list(rows[0].live_seeds)
    assert all(o.success for o in result.final.final)
    assert result.final.comparison is not None and result.final.comparison["table"]["candidate_only"] == 3
    # progress: each iteration started and finished, phases announced
    names = progress.names()
    assert names.count("iteration_started") == 2 and names.count("iteration_finished") == 2
    assert ("phase", {"name": "gate", "episodes": 16}) in progress.calls


def test_rejected_candidate_keeps_the_active_version(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, lambda versions, seed: False)
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=ParamUpdater(registry),
        config=fake_config(iterations=1),
    )
    row = loop.run().rows[0]
    assert row.gate is not None and row.gate.decision == "reject"
    assert "superior" in row.gate.failed_checks
    assert registry.get_version("pick.reach", 1).state is State.REJECTED
    assert row.active_after == dict.fromkeys(NAMES, 0)


def test_monitor_rolls_back_a_version_that_degrades_live(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    second_live = set(PLAN.live(3, offset=3))

    def behaviour(versions: dict, seed: int) -> bool:
        # v1 of reach wins on the held-out gate seeds but fails every live episode, where v0
        # (replayed by the monitor on iteration 1's live seeds) succeeds
        if versions["pick.reach"] == 0:
            return seed in second_live
        return versions["pick.reach"] >= 1 and PLAN.purpose_of(seed) == "gate"

    config = fake_config(
        iterations=2, monitor=MonitorConfig(window=6, min_episodes=3, margin=0.1, reference="gate_rate")
    )
    evaluator = ScriptedEvaluator(registry, behaviour)
    loop = make_loop(tmp_path, registry=registry, evaluator=evaluator, updater=ParamUpdater(registry), config=config)
    rows = loop.run().rows
    assert rows[0].gate is not None and rows[0].gate.decision == "promote"
    assert rows[1].active_versions["pick.reach"] == 1
    assert len(rows[1].rollbacks) == 1
    rb = rows[1].rollbacks[0]
    assert (rb["name"], rb["version"], rb["to_version"]) == ("pick.reach", 1, 0)
    assert rb["replayed"]["successes"] == 3 and rb["replayed"]["confirmed"]
    # the confirmation ran v0 on the live seeds, in its own phase, and its steps are counted
    on_live_seeds = [ran["pick.reach"] for ran, seeds in evaluator.calls if set(seeds) == second_live]
    assert on_live_seeds == [1, 0]  # the live episodes, then the replay
    assert rows[1].env_steps_monitor == 3 * 20 and rows[0].env_steps_monitor == 0
    assert rows[1].env_steps == rows[1].env_steps_live + 60 + rows[1].learner_steps + rows[1].env_steps_gate
    assert registry.get_version("pick.reach").version == 2  # rolled back to 0, then v2 promoted
    rollbacks = [e for e in registry.history("pick.reach") if e.action is Action.ROLLBACK]
    assert len(rollbacks) == 1 and rollbacks[0].actor == "evolve-monitor"
    assert "live success 0/3" in rollbacks[0].reason and "confirmed against v0 replayed" in rollbacks[0].reason


def test_monitor_keeps_a_version_whose_replaced_version_fails_the_same_live_seeds(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)

    def behaviour(versions: dict, seed: int) -> bool:
        # v1 wins on the gate seeds; live seeds are hard for every version (issue 19, T1 il, seed plan 1)
        return versions["pick.reach"] >= 1 and PLAN.purpose_of(seed) == "gate"

    config = fake_config(
        iterations=2,
        monitor=MonitorConfig(window=6, min_episodes=3, margin=0.1, reference="gate_rate"),
        env_steps_per_iteration=100_000,
    )
    progress = RecordingProgress()
    evaluator = ScriptedEvaluator(registry, behaviour)
    updater = ParamUpdater(registry)
    loop = make_loop(
        tmp_path, registry=registry, evaluator=evaluator, updater=updater, config=config, progress=progress
    )
    rows = loop.run().rows
    (action,) = rows[1].rollbacks
    assert not action["rolled_back"] and action["to_version"] is None
    replayed = action["replayed"]
    assert (replayed["version"], replayed["n"], replayed["successes"], replayed["steps"]) == (0, 3, 0, 3 * 40)
    assert not replayed["confirmed"] and replayed["threshold"] == pytest.approx(-0.1)
    assert rows[1].env_steps_monitor == 3 * 40
    # the replay comes out of the learner's share of the iteration's budget
    gates = 2 * config.gate_seeds_max * config.episode_steps_max("T1")
    assert updater.requests[1].max_env_steps == 100_000 - rows[1].env_steps_live - 3 * 40 - gates
    assert not [e for e in registry.history("pick.reach") if e.action is Action.ROLLBACK]
    assert rows[1].csv_row()["rollbacks"] == ""
    assert any(
        call == "iteration_finished" and "kept pick.reach v1 (drop not confirmed" in kw["summary"]
        for call, kw in progress.calls
    )
    assert ("phase", {"name": "monitor", "episodes": 3}) in progress.calls
    assert rows[1].active_versions["pick.reach"] == 1
    assert registry.get_version("pick.reach", 1).state is State.ACTIVE  # v2 ties it at the gate


def test_identity_change_stops_the_run(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    report = tmp_path / "report"
    report.mkdir()
    agent = make_agent(report)

    def rogue(request: object) -> None:
        # a learner that (wrongly) retunes the agent's policy instead of an ECM
        object.__setattr__(agent.policy, "parameters", PolicyParameters(max_attempts_per_ecm=7))

    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=ScriptedEvaluator(registry, reach_at_least(1)),
        updater=ParamUpdater(registry, tamper=rogue),
        agent=agent,
        config=fake_config(iterations=3),
    )
    with pytest.raises(IdentityViolation) as info:
        loop.run()
    assert info.value.code is ErrorCode.IDENTITY_VIOLATION
    assert "policy parameters changed" in info.value.message and "max_attempts_per_ecm" in info.value.message
    # iteration 0 finished and was recorded; iteration 1 never ran
    assert [r.iteration for r in read_metrics(report)] == [0]


def test_learner_failure_and_identical_candidates_are_notes_not_versions(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, lambda versions, seed: False)
    loop = make_loop(
        tmp_path / "a",
        registry=registry,
        evaluator=evaluator,
        updater=ParamUpdater(registry, fail=Unavailable("learner endpoint down")),
        config=fake_config(iterations=1),
    )
    row = loop.run().rows[0]
    assert row.gate is None and "learner failed" in row.update_note and "endpoint down" in row.update_note
    loop = make_loop(
        tmp_path / "b",
        registry=registry,
        evaluator=evaluator,
        updater=ParamUpdater(registry, same=True),
        config=fake_config(iterations=1),
    )
    row = loop.run().rows[0]
    assert row.gate is None and "nothing better than the parent" in row.update_note
    assert [v.version for v in registry.get_ecm("pick.reach").versions] == [0]


def test_resume_skips_finished_iterations(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, lambda versions, seed: False)
    first = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=ParamUpdater(registry),
        config=fake_config(iterations=1),
    )
    first.run()
    first.agent.episodic_memory.close()
    calls = len(evaluator.calls)
    updater = ParamUpdater(registry)
    second = make_loop(
        tmp_path, registry=registry, evaluator=evaluator, updater=updater, config=fake_config(iterations=2)
    )
    result = second.run()
    assert result.resumed_from == 1 and [r.iteration for r in result.rows] == [0, 1]
    assert [r.iteration for r in updater.requests] == [1]
    # iteration 1 only: live + gate (active, candidate) + the final run on iteration 0's seeds
    assert len(evaluator.calls) - calls == 3
    # the manifest (which the report's "n of N iterations" reads) follows the run's new target
    assert load_manifest(second.report_dir).config.iterations == 2


def test_resume_gates_the_candidate_an_interrupted_attempt_published(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    # calls: 1 live, 2 gate active, 3 gate candidate -> the process "dies" mid-gate
    crashing = ScriptedEvaluator(registry, reach_at_least(1), crash_on_call=3)
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=crashing,
        updater=ParamUpdater(registry),
        config=fake_config(iterations=1),
    )
    with pytest.raises(Crash):
        loop.run()
    loop.agent.episodic_memory.close()
    assert read_metrics(tmp_path / "report") == []  # invariant 4
    assert [v.version for v in waiting_candidates(registry, NAMES)] == [1]

    updater = ParamUpdater(registry)
    evaluator = ScriptedEvaluator(registry, reach_at_least(1))
    result = make_loop(
        tmp_path, registry=registry, evaluator=evaluator, updater=updater, config=fake_config(iterations=1)
    ).run()
    row = result.rows[0]
    assert updater.requests == []  # no second candidate learned
    assert row.candidate_version == 1 and row.gate is not None and row.gate.decision == "promote"
    assert "resumed" in row.update_note
    assert [v.version for v in registry.get_ecm("pick.reach").versions] == [0, 1]
    # invariant 5: the redone live episodes were not remembered twice
    log = read_episodes(tmp_path / "report" / "agent" / "episodic.jsonl")
    assert sorted((r.iteration, r.seed) for r in log.records) == sorted((0, s) for s in row.live_seeds)


class _DiesAfterPromote(LocalRegistry):
    """A real registry whose process 'dies' right after a promotion is committed."""

    armed = True

    def promote(self, *args: object, **kwargs: object):  # type: ignore[override]
        out = super().promote(*args, **kwargs)  # type: ignore[arg-type]
        if self.armed and kwargs.get("actor") == "evolve-gate":
            raise Crash("died after the promotion committed")
        return out


def test_resume_reads_a_decision_the_registry_already_has(tmp_path: Path) -> None:
    registry = _DiesAfterPromote(tmp_path / "registry", actor="tester")
    ensure_v0(registry, TASK, modality="code")
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=ScriptedEvaluator(registry, reach_at_least(1)),
        updater=ParamUpdater(registry),
        config=fake_config(iterations=1),
    )
    with pytest.raises(Crash):
        loop.run()
    loop.agent.episodic_memory.close()
    assert registry.get_version("pick.reach").version == 1  # the promotion is in the registry
    assert Journal(tmp_path / "report").last(0, "decided") is None

    registry.armed = False
    evaluator = ScriptedEvaluator(registry, reach_at_least(1))
    updater = ParamUpdater(registry)
    row = (
        make_loop(tmp_path, registry=registry, evaluator=evaluator, updater=updater, config=fake_config(iterations=1))
        .run()
        .rows[0]
    )
    assert updater.requests == []
    assert row.gate is not None and row.gate.decision == "promote" and row.candidate_version == 1
    # the redone live episodes ran the set the interrupted attempt started with (reach v0)
    assert row.active_versions["pick.reach"] == 0 and row.live.successes == 0
    assert evaluator.calls[0][0]["pick.reach"] == 0
    assert [e.action for e in registry.history("pick.reach")].count(Action.GATE) == 1


def test_a_waiting_candidate_is_gated_instead_of_learning(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    # a learner worker published a candidate of grasp before the loop got there
    v0 = registry.get_version("pick.grasp", 0)
    spec = dataclasses.replace(_spec_of(v0), parent=0, origin=Origin.RL)
    registry.publish("pick.grasp", registry.get_artifact("pick.grasp", 0) + b"\n# tuned\n", spec)
    updater = ParamUpdater(registry)
    row = (
        make_loop(
            tmp_path,
            registry=registry,
            evaluator=ScriptedEvaluator(registry, lambda v, s: False),
            updater=updater,
            config=fake_config(iterations=1),
        )
        .run()
        .rows[0]
    )
    assert updater.requests == []
    assert row.ecm_updated == "pick.grasp" and row.candidate_version == 1
    assert row.gate is not None and row.gate.decision == "reject"
    assert "waiting candidate" in row.update_note


def _spec_of(record):  # type: ignore[no-untyped-def]
    from capevo.records import PublishSpec

    return PublishSpec(kind=record.kind, descriptor=record.descriptor, interface=record.interface)


def test_the_manifest_refuses_a_different_run(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    evaluator = ScriptedEvaluator(registry, lambda v, s: False)
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=ParamUpdater(registry),
        config=fake_config(iterations=1),
    )
    loop.agent.episodic_memory.close()
    with pytest.raises(Invalid) as info:
        make_loop(
            tmp_path,
            registry=registry,
            evaluator=evaluator,
            updater=ParamUpdater(registry),
            config=fake_config(iterations=1, live_episodes=4),
        )
    assert info.value.code is ErrorCode.INVALID
    assert "config.live_episodes" in info.value.message and "--report-dir" in info.value.message


def test_the_gate_takes_a_second_look_on_fresh_held_out_seeds(tmp_path: Path) -> None:
    """Gate invariant 8 through the loop: reach v1 wins 6 vs 2 of the 8 paired seeds (McNemar
    p = 0.0625, short of α/2), so the gate runs 8 more seeds from the plan's extension range
    and promotes on all 16 (p = 0.004)."""
    registry = seeded_registry(tmp_path)

    def behaviour(versions: dict[str, int], seed: int) -> bool:
        return seed % 4 != 0 if versions["pick.reach"] >= 1 else seed % 4 == 3

    config = fake_config(iterations=1, gate=dataclasses.replace(fake_config().gate, extend_n=8))
    assert config.step_reserve("T1") == (3 + 2 * 16) * config.episode_steps_max("T1")
    evaluator = ScriptedEvaluator(registry, behaviour)
    progress = RecordingProgress()
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=evaluator,
        updater=ParamUpdater(registry),
        config=config,
        progress=progress,
    )
    (row,) = loop.run().rows
    assert row.ecm_updated == "pick.reach" and row.gate is not None and row.gate.decision == "promote"
    evidence = registry.get_version("pick.reach", 1).gate_evidence
    first, second = evidence["looks"]
    assert (first["n"], first["decision"], second["n"], second["decision"]) == (8, "reject", 16, "promote")
    assert evidence["seeds"] == sorted(PLAN.gate(8) + PLAN.gate_extension(8))
    assert all(PLAN.purpose_of(s) == "gate" for s in evidence["seeds"])
    assert ("phase", {"name": "gate", "episodes": 16}) in progress.calls
