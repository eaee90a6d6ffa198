"""The gate against a real LocalRegistry on disk, with the in-memory FakeEvaluator.

Invariants of :mod:`capevo.runtime.gate`: same seeds for both versions, order-free decision
(1); evidence recorded before the pointer moves (2); expected_active guards promotion (3);
a broken pairing records nothing (4); identical outcomes never promote (5); bad arguments
raise before any episode (6); more unsafe episodes than the active version never promote,
whatever the success and the sign test (7:
``test_a_candidate_with_more_unsafe_episodes_is_refused_whatever_the_sign_test_says``,
``test_more_unsafe_episodes_never_promote``). Plus the decision rule, GateConfig and SeedPlan.
"""

from __future__ import annotations

import dataclasses
import json
import random
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from runtime_support import REACH, Behaviour, FakeEvaluator, skill_spec

from capevo.errors import Conflict, ErrorCode, IllegalTransition, Invalid
from capevo.records import Action, State
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluation import EpisodeOutcome, Evaluator
from capevo.runtime.gate import (
    EVIDENCE_SCHEMA,
    Gate,
    GateConfig,
    SeedPlan,
    decide_paired,
)
from capevo.runtime.gate_stats import paired_stats

NAME = "pick.reach"
SEEDS = SeedPlan().gate(10)  # 100_000 .. 100_009, held out
CFG = GateConfig(min_n=8, alpha=0.05, delta=0.3, max_slowdown=1.1, first_min_success=0.5)


def always(success: bool, reward: float = 1.0, steps: int = 50) -> Behaviour:
    return lambda seed: (success, reward, steps)


def every_other(reward: float = 1.0, steps: int = 50) -> Behaviour:
    return lambda seed: (seed % 2 == 0, reward, steps)


@pytest.fixture
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    reg = LocalRegistry(tmp_path / "registry", actor="tester")
    yield reg
    reg.close()


def publish(registry: LocalRegistry, *, promote: bool = False, text: str = "") -> int:
    record = registry.publish(NAME, (REACH + text).encode(), skill_spec(NAME))
    if promote:
        registry.promote(NAME, record.version, reason="setup")
    return record.version


def gate_events(registry: LocalRegistry) -> list:
    return [e for e in registry.history(NAME) if e.action in (Action.GATE, Action.PROMOTE, Action.REJECT)]


# --- GateConfig and SeedPlan ---------------------------------------------------------------


def test_presets_are_valid_and_round_trip() -> None:
    for cfg in (GateConfig(), GateConfig.cpu_small(), GateConfig.standard(), GateConfig.strict()):
        assert GateConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert GateConfig.cpu_small().min_n == 8 and GateConfig.strict().alpha == 0.01


@pytest.mark.parametrize(
    ("kwargs", "field", "fragment"),
    [
        ({"min_n": 0}, "min_n", "min_n must be an integer >= 1"),
        ({"alpha": 0.5}, "alpha", "alpha must be a number in (0, 0.5)"),
        ({"delta": 1.0}, "delta", "delta must be in [0, 1)"),
        ({"delta": -0.1}, "delta", "delta must be in [0.0, 1.0]"),
        ({"min_success": 1.5}, "min_success", "min_success must be in [0.0, 1.0]"),
        ({"require_improvement": 1}, "require_improvement", "require_improvement must be a bool"),
        ({"max_slowdown": 0.9}, "max_slowdown", "max_slowdown must be in [1.0"),
        ({"speed_metric": "wall"}, "speed_metric", "unknown speed metric 'wall'; valid: steps, duration_s"),
        ({"safety_alpha": 0.0}, "safety_alpha", "safety_alpha must be in (0.0, 0.5]"),
        ({"max_unsafe_rate": -0.1}, "max_unsafe_rate", "max_unsafe_rate must be in [0.0, 1.0]"),
    ],
)
def test_bad_config_is_invalid(kwargs: dict, field: str, fragment: str) -> None:
    with pytest.raises(Invalid) as e:
        GateConfig(**kwargs)
    assert e.value.code is ErrorCode.INVALID
    assert fragment in e.value.message
    assert e.value.details["field"] == field


def test_seed_plan_ranges_are_disjoint_and_deterministic() -> None:
    plan = SeedPlan(base_seed=3, block=1000)
    train, gate, live = (set(plan.range(p)) for p in ("train", "gate", "live"))
    assert not (train & gate) and not (train & live) and not (gate & live)
    assert plan.gate(10) == SeedPlan(base_seed=3, block=1000).gate(10) == list(range(10_000, 10_010))
    assert plan.train(3) == [9000, 9001, 9002] and plan.live(2) == [11_000, 11_001]
    assert not set(plan.gate(10, round=0)) & set(plan.gate(10, round=1))
    other = SeedPlan(base_seed=4, block=1000)
    assert not set().union(*(plan.range(p) for p in ("train", "gate", "live"))) & set(other.range("train"))
    assert plan.purpose_of(10_005) == "gate" and plan.purpose_of(9_999) == "train" and plan.purpose_of(5) is None


def test_seed_plan_refuses_what_it_cannot_hand_out() -> None:
    plan = SeedPlan(block=10)
    with pytest.raises(Invalid, match=r"gate seeds 10\.\.19 run past the plan's block of 10"):
        plan.gate(10, round=1)
    with pytest.raises(Invalid, match="unknown seed purpose 'test'; valid: train, gate, live"):
        plan.range("test")
    with pytest.raises(Invalid, match="reaches past 2147483647"):
        SeedPlan(base_seed=10**6, block=10**6)
    with pytest.raises(Invalid, match="base_seed must be an integer >= 0"):
        SeedPlan(base_seed=-1)


# --- paired mode ---------------------------------------------------------------------------


def test_a_better_candidate_is_promoted_with_its_evidence_in_the_audit_history(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry, text="# better")
    fake = FakeEvaluator({(NAME, v_act): every_other(), (NAME, v_cand): always(True)})
    stages: list[str] = []
    gate = Gate(registry, fake, CFG, progress=lambda stage, msg: stages.append(stage))

    decision = gate.run(NAME, v_cand, task="T1", seeds=SEEDS)

    assert decision.promoted and decision.active_version == v_act and decision.n == 10
    assert registry.get_version(NAME).version == v_cand
    assert registry.get_version(NAME, v_act).state is State.SUPERSEDED
    # Same seeds for both versions, active first.
    assert [c[1] for c in fake.calls] == [{NAME: v_act}, {NAME: v_cand}]
    assert fake.calls[0][2] == fake.calls[1][2] == tuple(SEEDS)
    assert stages == ["evaluate-active", "evaluate-candidate", "decided", "recorded", "promoted"]

    gate_ev, promote_ev = gate_events(registry)[-2:]
    assert gate_ev.action is Action.GATE and promote_ev.action is Action.PROMOTE
    assert gate_ev.seq < promote_ev.seq
    assert promote_ev.from_version == v_act and promote_ev.to_version == v_cand
    assert promote_ev.actor == gate_ev.actor == "gate"
    ev = registry.get_version(NAME, v_cand).gate_evidence
    assert ev == gate_ev.data["evidence"] == decision.evidence
    assert ev["schema"] == EVIDENCE_SCHEMA and ev["decision"] == "promote" and ev["mode"] == "paired"
    assert ev["seeds"] == SEEDS and ev["n"] == 10 and ev["active_version"] == v_act
    assert ev["paired"]["table"] == {"both": 5, "candidate_only": 5, "active_only": 0, "neither": 0}
    assert ev["paired"]["p_success"] == pytest.approx(0.5**5)
    assert ev["candidate"]["success_interval"]["low"] == pytest.approx(decision.candidate.success.low)
    assert ev["outcomes"]["active"]["success"] == [1, 0] * 5
    assert ev["outcomes"]["candidate"]["success"] == [1] * 10
    assert {c["name"]: c["passed"] for c in ev["checks"]} == {
        "enough": True,
        "floor": True,
        "superior": True,
        "noninferior": True,
        "reward": False,
        "not_slower": True,
        "safe": True,
    }
    # The reason states the numbers.
    for fragment in ("promote pick.reach v1", "vs v0 on N=10", "10/10", "5/10", "McNemar p=0.0312"):
        assert fragment in promote_ev.reason, promote_ev.reason
    assert registry.verify().ok


def test_a_worse_candidate_is_rejected(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry, text="# sign error")
    fake = FakeEvaluator({(NAME, v_act): always(True), (NAME, v_cand): always(False, reward=0.1, steps=80)})
    decision = Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert not decision.promoted
    assert set(decision.failed) == {"superior", "noninferior", "reward"}
    assert registry.get_version(NAME, v_cand).state is State.REJECTED
    assert registry.get_version(NAME).version == v_act
    gate_ev, reject_ev = gate_events(registry)[-2:]
    assert (gate_ev.action, reject_ev.action) == (Action.GATE, Action.REJECT)
    assert "reject pick.reach v1" in reject_ev.reason and "0/10" in reject_ev.reason
    assert "noninferior=FAIL" in reject_ev.reason
    assert registry.get_version(NAME, v_cand).gate_evidence["decision"] == "reject"


def test_a_slower_candidate_is_rejected_even_with_more_reward(registry: LocalRegistry) -> None:
    # Holding the object longer collects more shaped reward: reward alone would promote it.
    v_act = publish(registry, promote=True)
    v_cand = publish(registry, text="# gain / 4")
    fake = FakeEvaluator({(NAME, v_act): always(True, 5.0, 50), (NAME, v_cand): always(True, 9.0, 65)})
    decision = Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert not decision.promoted
    assert decision.failed == ("superior", "not_slower")
    assert decision.paired is not None and decision.paired.speed_ratio == pytest.approx(1.3)
    assert "x1.300" in next(c.detail for c in decision.checks if c.name == "not_slower")


def test_identical_candidate_is_not_promoted_unless_improvement_is_optional(tmp_path: Path) -> None:
    for require, expect in ((True, False), (False, True)):
        reg = LocalRegistry(tmp_path / f"r{require}", actor="tester")
        v_act = publish(reg, promote=True)
        v_cand = publish(reg, text="# refactor")
        fake = FakeEvaluator({(NAME, v_act): always(True), (NAME, v_cand): always(True)})
        cfg = GateConfig(min_n=8, delta=0.3, require_improvement=require)
        assert Gate(reg, fake, cfg).run(NAME, v_cand, task="T1", seeds=SEEDS).promoted is expect
        reg.close()


def test_reward_gain_with_non_inferior_success_promotes(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry)
    fake = FakeEvaluator({(NAME, v_act): always(True, 5.0, 50), (NAME, v_cand): always(True, 6.0, 48)})
    decision = Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert decision.promoted and decision.failed == ("superior",)


def test_too_few_paired_episodes_never_promote() -> None:
    cand = [EpisodeOutcome.from_dict(_row(s, True)) for s in range(5)]
    act = [EpisodeOutcome.from_dict(_row(s, False)) for s in range(5)]
    promote, checks = decide_paired(paired_stats(act, cand, alpha=0.05, margin=0.3), GateConfig(min_n=6))
    assert not promote and [c.name for c in checks if not c.passed] == ["enough", "reward"]


def test_min_success_floor_blocks_a_relative_gain(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry)
    fake = FakeEvaluator({(NAME, v_act): always(False), (NAME, v_cand): lambda s: (s < SEEDS[6], 1.0, 50)})
    cfg = GateConfig(min_n=8, delta=0.3, min_success=0.5)
    decision = Gate(registry, fake, cfg).run(NAME, v_cand, task="T1", seeds=SEEDS)
    # 6/10 beats 0/10 (McNemar p = 1/64) but its lower Wilson bound is ~0.35 < 0.5.
    assert not decision.promoted and decision.failed == ("floor", "reward")


def unsafe_on(seeds: Sequence[int], success: bool = True, reward: float = 6.0) -> Behaviour:
    return lambda seed: (success, reward, 50, 3 if seed in seeds else 0)


def test_a_less_safe_candidate_is_rejected_despite_more_success(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry, text="# pushes harder")
    # 10/10 vs 0/10 is a clear gain, but 3 seeds went unsafe only with the candidate (p = 1/8 < 0.2).
    fake = FakeEvaluator({(NAME, v_act): always(False), (NAME, v_cand): unsafe_on(SEEDS[:3])})
    decision = Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert not decision.promoted and decision.failed == ("safe",)
    assert decision.paired is not None
    assert (decision.paired.unsafe_candidate_only, decision.paired.unsafe_active_only) == (3, 0)
    assert decision.paired.p_less_safe == pytest.approx(0.125)
    assert "unsafe episodes 3 vs 0" in decision.reason and "safe=FAIL" in decision.reason
    safe = next(c for c in decision.checks if c.name == "safe")
    assert safe.detail.startswith("unsafe episodes 3/10 vs active 0/10 on the same seeds: more than the active; ")
    evidence = registry.get_version(NAME, v_cand).gate_evidence
    assert evidence["candidate"]["unsafe_episodes"] == 3
    assert evidence["paired"]["safety"]["candidate_only_unsafe"] == 3
    assert evidence["outcomes"]["candidate"]["unsafe_steps"][:3] == [3, 3, 3]


def test_equally_unsafe_versions_block_a_gain_by_default_and_not_without_the_ceiling(
    registry: LocalRegistry,
) -> None:
    v_act = publish(registry, promote=True)
    cand = [publish(registry, text=f"# {i}") for i in range(2)]
    # Both unsafe on the same seeds: no discordant pair, no evidence the candidate is less safe...
    fake = FakeEvaluator({(NAME, v_act): unsafe_on(SEEDS[:4], False, 1.0)})
    for v in cand:
        fake.set(NAME, v, unsafe_on(SEEDS[:4]))
    # ...but the default ceiling (no unsafe episode at all) refuses it, as every preset does...
    assert CFG.max_unsafe_rate == 0.0 == GateConfig.standard().max_unsafe_rate == GateConfig.cpu_small().max_unsafe_rate
    decision = Gate(registry, fake, CFG).run(NAME, cand[0], task="T1", seeds=SEEDS)
    assert not decision.promoted and decision.failed == ("safe",)
    # ...and with the ceiling off only the comparison with the active version is left.
    decision = Gate(registry, fake, replace(CFG, max_unsafe_rate=None)).run(NAME, cand[1], task="T1", seeds=SEEDS)
    assert decision.promoted and "safe" not in decision.failed


def test_safety_knobs(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    cand = [publish(registry, text=f"# {i}") for i in range(2)]
    fake = FakeEvaluator({(NAME, v_act): always(False)})
    for v in cand:
        fake.set(NAME, v, unsafe_on(SEEDS[:1]))
    # The default zero ceiling on the unsafe-episode rate rejects one unsafe seed in ten...
    decision = Gate(registry, fake, CFG).run(NAME, cand[0], task="T1", seeds=SEEDS)
    assert not decision.promoted and decision.failed == ("safe",)
    assert "candidate unsafe episodes 1/10 vs max rate 0" in next(c.detail for c in decision.checks if c.name == "safe")
    # ...and so does the count rule, though the sign test alone would let it through (one
    # discordant seed: p = 0.5): one more unsafe episode than the active version is one too many.
    decision = Gate(registry, fake, replace(CFG, max_unsafe_rate=None)).run(NAME, cand[1], task="T1", seeds=SEEDS)
    assert not decision.promoted and decision.failed == ("safe",)
    assert "sign test p=0.5 vs 0.2" in next(c.detail for c in decision.checks if c.name == "safe")


def test_a_candidate_with_more_unsafe_episodes_is_refused_whatever_the_sign_test_says(
    registry: LocalRegistry,
) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry, text="# succeeds everywhere, unsafe on two seeds")
    # The active version fails everywhere and is unsafe on one seed; the candidate succeeds on all
    # ten (McNemar p = 0.001) and is unsafe on two others. b' = 2, c' = 1: the sign test's
    # p = 0.5 is far from 0.2, but 2 unsafe episodes are more than 1 (issue 18).
    fake = FakeEvaluator({(NAME, v_act): unsafe_on(SEEDS[:1], False, 1.0), (NAME, v_cand): unsafe_on(SEEDS[1:3])})
    decision = Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert decision.paired is not None
    assert (decision.paired.candidate.successes, decision.paired.active.successes) == (10, 0)
    assert decision.paired.p_success < CFG.alpha and decision.paired.p_less_safe == pytest.approx(0.5)
    assert not decision.promoted and decision.failed == ("safe",)
    assert "safe=FAIL" in decision.reason and "unsafe episodes 2 vs 1" in decision.reason
    assert registry.get_version(NAME, v_cand).state is State.REJECTED
    assert registry.get_version(NAME).version == v_act
    # One unsafe episode fewer than the active version, the same gain: promoted.
    v_safer = publish(registry, text="# succeeds everywhere, never unsafe")
    fake.set(NAME, v_safer, always(True, 6.0))
    assert Gate(registry, fake, CFG).run(NAME, v_safer, task="T1", seeds=SEEDS).promoted


def test_the_sign_test_can_be_turned_off() -> None:
    cand = [EpisodeOutcome.from_dict({**_row(s, True), "unsafe_steps": 2 if s < 2 else 0}) for s in range(8)]
    act = [EpisodeOutcome.from_dict({**_row(s, False), "unsafe_steps": 1 if s < 2 else 0}) for s in range(8)]
    stats = paired_stats(act, cand, alpha=0.05, margin=0.3)
    promote, checks = decide_paired(stats, GateConfig(min_n=8, safety_alpha=None, max_unsafe_rate=None))
    # Equally many unsafe episodes (on the same seeds): only the count is reported, and it passes.
    safe = next(c for c in checks if c.name == "safe")
    assert promote and safe.detail == "unsafe episodes 2/8 vs active 2/8 on the same seeds: not more than the active"
    # The count rule is not the sign test's: turning the sign test off leaves it in force.
    more = [EpisodeOutcome.from_dict({**_row(s, True), "unsafe_steps": 2}) for s in range(8)]
    promote, checks = decide_paired(
        paired_stats(act, more, alpha=0.05, margin=0.3), GateConfig(min_n=8, safety_alpha=None, max_unsafe_rate=None)
    )
    failed = [c.name for c in checks if not c.passed]
    assert not promote and "safe" in failed and "superior" not in failed  # 8 of 8 gained, refused


@settings(max_examples=200, deadline=None)
@given(
    cand=st.lists(st.tuples(st.booleans(), st.integers(0, 3)), min_size=8, max_size=16),
    act_bits=st.lists(st.tuples(st.booleans(), st.integers(0, 3)), min_size=16, max_size=16),
    safety_alpha=st.sampled_from([None, 0.05, 0.2, 0.5]),
)
def test_more_unsafe_episodes_never_promote(
    cand: list[tuple[bool, int]], act_bits: list[tuple[bool, int]], safety_alpha: float | None
) -> None:
    # Invariant 7, over any successes, unsafe steps and sign-test level.
    n = len(cand)
    cand_o = [EpisodeOutcome.from_dict({**_row(s, ok), "unsafe_steps": u}) for s, (ok, u) in enumerate(cand)]
    act_o = [EpisodeOutcome.from_dict({**_row(s, ok), "unsafe_steps": u}) for s, (ok, u) in enumerate(act_bits[:n])]
    more = sum(u > 0 for _, u in cand) > sum(u > 0 for _, u in act_bits[:n])
    config = GateConfig(
        min_n=8,
        delta=0.3,
        max_slowdown=None,
        safety_alpha=safety_alpha,
        require_improvement=False,
        max_unsafe_rate=None,
    )
    promote, checks = decide_paired(paired_stats(act_o, cand_o, alpha=0.05, margin=0.3), config)
    # ``safe`` fails exactly when the count is higher: the sign test never fails on its own.
    assert next(c for c in checks if c.name == "safe").passed is not more
    if more:
        assert not promote


# --- absolute mode -------------------------------------------------------------------------


def test_first_version_is_gated_against_the_absolute_threshold(tmp_path: Path) -> None:
    for successes, expect in ((10, True), (6, False)):
        reg = LocalRegistry(tmp_path / f"r{successes}", actor="tester")
        v = publish(reg)
        fake = FakeEvaluator({(NAME, v): lambda s, k=successes: (s < SEEDS[0] + k, 1.0, 50)})
        decision = Gate(reg, fake, CFG).run(NAME, v, task="T1", seeds=SEEDS)
        assert decision.promoted is expect and decision.active_version is None and decision.paired is None
        assert [c.name for c in decision.checks] == ["enough", "floor", "safe"]
        assert len(fake.calls) == 1
        ev = reg.get_version(NAME, v).gate_evidence
        assert ev["mode"] == "absolute" and ev["active"] is None and ev["outcomes"]["active"] is None
        assert "first version" in decision.reason
        assert reg.get_version(NAME, v).state is (State.ACTIVE if expect else State.REJECTED)
        reg.close()


# --- guards --------------------------------------------------------------------------------


def test_a_concurrent_promotion_turns_into_a_conflict(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry, text="# mine")
    v_other = publish(registry, text="# someone else's")
    other = LocalRegistry(registry.root, actor="other-gate")

    def candidate(seed: int) -> tuple[bool, float, int]:
        if registry.get_version(NAME).version == v_act:
            other.promote(NAME, v_other, expected_active=v_act, reason="another gate won")
        return True, 1.0, 50

    fake = FakeEvaluator({(NAME, v_act): every_other(), (NAME, v_cand): candidate})
    with pytest.raises(Conflict) as e:
        Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    other.close()
    assert e.value.code is ErrorCode.CONFLICT
    assert f"expected active v{v_act}" in e.value.message
    assert registry.get_version(NAME).version == v_other
    mine = registry.get_version(NAME, v_cand)
    assert mine.state is State.CANDIDATE and mine.gate_evidence["decision"] == "promote"
    assert registry.verify().ok


class _DriftingEvaluator:
    """A fake whose second call reports another version of pick.lift, as if it was promoted meanwhile."""

    def __init__(self, inner: FakeEvaluator) -> None:
        self.inner = inner
        self.n = 0

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        out = self.inner.evaluate(task, versions, seeds)
        self.n += 1
        lift = {"pick.lift": self.n}
        return [EpisodeOutcome.from_dict({**o.to_dict(), "capability_set": {**o.capability_set, **lift}}) for o in out]


def test_a_broken_pairing_records_nothing(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry)
    fake = FakeEvaluator({(NAME, v_act): every_other(), (NAME, v_cand): always(True)})
    drifting = _DriftingEvaluator(fake)
    assert isinstance(drifting, Evaluator)
    before = len(registry.history(NAME))
    with pytest.raises(Conflict, match=r"ran different versions of pick\.lift .* the pairing is broken"):
        Gate(registry, drifting, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert len(registry.history(NAME)) == before
    assert registry.get_version(NAME, v_cand).gate_evidence is None


def test_bad_arguments_raise_before_any_episode(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry)
    fake = FakeEvaluator({(NAME, v_act): always(True), (NAME, v_cand): always(True)})
    gate = Gate(registry, fake, CFG, seed_plan=SeedPlan())
    with pytest.raises(Invalid, match="the gate needs at least min_n=8 seeds, got 3"):
        gate.run(NAME, v_cand, task="T1", seeds=SEEDS[:3])
    with pytest.raises(Invalid, match=r"gate seeds must be distinct; repeated: \[100000\]"):
        gate.run(NAME, v_cand, task="T1", seeds=[SEEDS[0], *SEEDS[:9]])
    with pytest.raises(Invalid, match=r"gate seeds must be held out .*not held out: \[0, 1, 2, 3, 4\]"):
        gate.run(NAME, v_cand, task="T1", seeds=list(range(10)))
    with pytest.raises(Invalid, match="seeds must be non-negative integers, got -1"):
        gate.run(NAME, v_cand, task="T1", seeds=[-1, *SEEDS])
    with pytest.raises(IllegalTransition) as e:
        gate.run(NAME, v_act, task="T1", seeds=SEEDS)
    assert (
        e.value.code is ErrorCode.ILLEGAL_TRANSITION and "is active; only a candidate can be gated" in e.value.message
    )
    with pytest.raises(Invalid, match="evaluator must have evaluate"):
        Gate(registry, object(), CFG)  # type: ignore[arg-type]
    assert fake.calls == []


def test_outcomes_for_other_seeds_are_invalid(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry)

    class Shifted(FakeEvaluator):
        def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
            return super().evaluate(task, versions, [s + 1 for s in seeds])

    fake = Shifted({(NAME, v_act): always(True), (NAME, v_cand): always(True)})
    with pytest.raises(Invalid, match="the evaluator returned outcomes for seeds"):
        Gate(registry, fake, CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)


def test_reused_evaluations_skip_the_active_rerun_only_for_the_same_versions(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    worse = [publish(registry, text=f"# worse {i}") for i in range(2)]
    fake = FakeEvaluator({(NAME, v_act): always(True), **{(NAME, v): always(False) for v in worse}})
    gate = Gate(registry, fake, CFG, reuse_evaluations=True)
    for v in worse:
        assert not gate.run(NAME, v, task="T1", seeds=SEEDS).promoted
    assert [c[1] for c in fake.calls] == [{NAME: v_act}, {NAME: worse[0]}, {NAME: worse[1]}]
    # Other seeds: evaluated afresh.
    better = publish(registry)
    fake.set(NAME, better, always(True, 2.0, 40))
    gate.run(NAME, better, task="T1", seeds=[s + 100 for s in SEEDS])
    assert [c[1] for c in fake.calls[-2:]] == [{NAME: v_act}, {NAME: better}]


# --- properties ----------------------------------------------------------------------------


def _row(seed: int, success: bool, reward: float = 1.0, steps: int = 50) -> dict:
    return {
        "seed": seed,
        "success": success,
        "reward": reward,
        "steps": steps,
        "duration_s": steps / 100,
        "interventions": 0,
        "unsafe_steps": 0,
        "ecm_failures": 0,
        "capability_set": {NAME: 0},
    }


rows = st.lists(st.tuples(st.booleans(), st.floats(0, 10), st.integers(10, 100)), min_size=8, max_size=30)
configs = st.builds(
    GateConfig,
    min_n=st.integers(1, 12),
    alpha=st.sampled_from([0.01, 0.05, 0.1]),
    delta=st.floats(0, 0.5),
    min_success=st.one_of(st.none(), st.floats(0, 1)),
    require_improvement=st.just(True),
    max_slowdown=st.one_of(st.none(), st.floats(1, 2)),
)


@given(rows, configs)
@settings(max_examples=100, deadline=None)
def test_never_promote_a_candidate_equal_to_the_active_one_outcome_for_outcome(r: list, cfg: GateConfig) -> None:
    outcomes = [EpisodeOutcome.from_dict(_row(i, *t)) for i, t in enumerate(r)]
    promote, _ = decide_paired(paired_stats(outcomes, list(outcomes), alpha=cfg.alpha, margin=cfg.delta), cfg)
    assert not promote


@given(rows, rows, configs, st.randoms(use_true_random=False))
@settings(max_examples=100, deadline=None)
def test_the_decision_does_not_depend_on_seed_order(ra: list, rc: list, cfg: GateConfig, rnd: random.Random) -> None:
    n = min(len(ra), len(rc))
    act = [EpisodeOutcome.from_dict(_row(i, *ra[i])) for i in range(n)]
    cand = [EpisodeOutcome.from_dict(_row(i, *rc[i])) for i in range(n)]
    first = decide_paired(paired_stats(act, cand, alpha=cfg.alpha, margin=cfg.delta), cfg)
    rnd.shuffle(act)
    rnd.shuffle(cand)
    assert decide_paired(paired_stats(act, cand, alpha=cfg.alpha, margin=cfg.delta), cfg) == first


def test_gate_run_gives_the_same_decision_and_evidence_for_shuffled_seeds(tmp_path: Path) -> None:
    results = []
    for i, order in enumerate((SEEDS, SEEDS[::-1], random.Random(7).sample(SEEDS, len(SEEDS)))):
        reg = LocalRegistry(tmp_path / f"r{i}", actor="tester")
        v_act = publish(reg, promote=True)
        v_cand = publish(reg)
        fake = FakeEvaluator(
            {(NAME, v_act): every_other(1.0, 60), (NAME, v_cand): lambda s: (s % 3 != 0, 1.0 + s % 5, 55)}
        )
        d = Gate(reg, fake, CFG).run(NAME, v_cand, task="T1", seeds=order)
        ev = {k: v for k, v in d.evidence.items() if k != "decided_at"}
        results.append((d.promoted, d.reason, ev))
        reg.close()
    assert results[0] == results[1] == results[2]


def test_a_first_version_loses_to_one_promoted_meanwhile(registry: LocalRegistry) -> None:
    mine = publish(registry)
    theirs = publish(registry, text="# promoted by hand meanwhile")

    def behaviour(seed: int) -> tuple[bool, float, int]:
        if seed == SEEDS[-1]:
            registry.promote(NAME, theirs, reason="operator")
        return True, 1.0, 50

    fake = FakeEvaluator({(NAME, mine): behaviour})
    with pytest.raises(Conflict) as e:
        Gate(registry, fake, CFG).run(NAME, mine, task="T1", seeds=SEEDS)
    assert e.value.message == "cannot promote pick.reach: gated as its first version, but v1 became active meanwhile"
    assert registry.get_version(NAME).version == theirs
    assert registry.get_version(NAME, mine).state is State.CANDIDATE


def test_a_first_version_over_the_unsafe_ceiling_is_rejected(tmp_path: Path) -> None:
    reg = LocalRegistry(tmp_path / "r", actor="tester")
    v = publish(reg)
    fake = FakeEvaluator({(NAME, v): unsafe_on(SEEDS[:2])})
    cfg = GateConfig(min_n=8, delta=0.3, max_unsafe_rate=0.1)
    decision = Gate(reg, fake, cfg).run(NAME, v, task="T1", seeds=SEEDS)
    assert not decision.promoted and decision.failed == ("safe",)
    reg.close()


def test_evaluations_under_two_envelopes_are_not_paired(registry: LocalRegistry) -> None:
    v_act = publish(registry, promote=True)
    v_cand = publish(registry)
    fake = FakeEvaluator({(NAME, v_act): always(False), (NAME, v_cand): always(True)})

    class TwoEnvelopes:
        """The active version evaluated under one Φ, the candidate under another (two workers)."""

        def evaluate(self, task: str, versions: dict[str, int], seeds: list[int]) -> list[EpisodeOutcome]:
            phi = "paper-hash" if versions.get(NAME) == v_act else "task-hash"
            return [dataclasses.replace(o, phi_hash=phi) for o in fake.evaluate(task, versions, seeds)]

    with pytest.raises(Conflict) as e:
        Gate(registry, TwoEnvelopes(), CFG).run(NAME, v_cand, task="T1", seeds=SEEDS)
    assert "ran under different envelopes" in e.value.message
    assert registry.get_version(NAME, v_cand).gate_evidence is None  # nothing recorded
