"""DecompositionPolicy (π_A) on hand-made signals and EcmVersion records with real descriptors.

Covers policy invariants 1-5 and the decision rules of the module docstring: walk order,
switching on termination, applicability gating, re-planning after FAILED / BUDGET_EXHAUSTED,
attempt limits and the end of the episode.
"""

from __future__ import annotations

import dataclasses

import pytest
from _agent_helpers import (
    PICK_AT_CAN_OPEN,
    PICK_DROPPED_OPEN,
    PICK_FAR,
    PICK_GRASPED,
    PICK_LIFTED,
    PICK_SLIPPED,
    context,
    pred,
    step_version,
    task_capabilities,
    version,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.agent import ALL_DONE, DecompositionPolicy, IdentityMemory, PolicyParameters
from capevo.errors import ErrorCode, Invalid
from capevo.records import Descriptor
from capevo.registry.predicates import predicate_holds
from capevo.runtime.policy import Decision, DecisionPolicy, StepEnd
from capevo.runtime.tasks import task_spec


@pytest.fixture
def policy() -> DecompositionPolicy:
    return DecompositionPolicy(identity=IdentityMemory.default())


PICK = task_capabilities("pick")


def test_it_is_a_decision_policy(policy: DecompositionPolicy) -> None:
    assert isinstance(policy, DecisionPolicy)


def test_a_clean_pick_runs_reach_grasp_lift_then_ends(policy: DecompositionPolicy) -> None:
    d = policy.decide(context("pick", PICK_FAR, PICK))
    assert d.ecm == "pick.reach" and d.reason.startswith("start")
    d = policy.decide(context("pick", PICK_AT_CAN_OPEN, PICK, prev="pick.reach", end=StepEnd.TERMINATED))
    assert d.ecm == "pick.grasp"
    # Once grasped the gripper is closed, so reach's termination no longer holds: the walk
    # continues after the step that terminated instead of going back to reach.
    assert not predicate_holds(PICK["pick.reach"].descriptor.termination, PICK_GRASPED)
    d = policy.decide(context("pick", PICK_GRASPED, PICK, prev="pick.grasp", end=StepEnd.TERMINATED))
    assert d == Decision(ecm="pick.lift", reason="pick.grasp done; next: pick.lift")
    d = policy.decide(context("pick", PICK_LIFTED, PICK, prev="pick.lift", end=StepEnd.TERMINATED))
    assert d == Decision(ecm=None, reason=ALL_DONE)


def test_steps_already_done_are_skipped_at_start(policy: DecompositionPolicy) -> None:
    assert policy.decide(context("pick", PICK_AT_CAN_OPEN, PICK)).ecm == "pick.grasp"


def test_every_termination_holding_ends_the_episode(policy: DecompositionPolicy) -> None:
    everything = {**PICK_AT_CAN_OPEN, "grasped": 1.0, "object_height_above_start": 0.1}
    assert policy.decide(context("pick", everything, PICK)) == Decision(ecm=None, reason="all steps done")


def test_object_slipped_during_lift_replans_from_reach(policy: DecompositionPolicy) -> None:
    for end in (StepEnd.FAILED, StepEnd.BUDGET_EXHAUSTED):
        d = policy.decide(context("pick", PICK_SLIPPED, PICK, prev="pick.lift", end=end))
        assert d.ecm == "pick.reach"
        assert d.reason == f"pick.lift {end.value}; re-planned: pick.reach"


def test_dropped_with_open_gripper_at_the_can_replans_from_grasp(policy: DecompositionPolicy) -> None:
    d = policy.decide(context("pick", PICK_DROPPED_OPEN, PICK, prev="pick.lift", end=StepEnd.FAILED))
    assert d.ecm == "pick.grasp"


def test_a_stalled_lift_still_holding_retries_the_lift(policy: DecompositionPolicy) -> None:
    # Grasp's termination still holds, so re-planning keeps the grasp instead of reaching
    # (which would open the gripper and drop the can).
    d = policy.decide(context("pick", PICK_GRASPED, PICK, prev="pick.lift", end=StepEnd.BUDGET_EXHAUSTED))
    assert d.ecm == "pick.lift"


def test_a_failed_step_is_retried_when_nothing_before_it_was_undone(policy: DecompositionPolicy) -> None:
    d = policy.decide(context("pick", PICK_AT_CAN_OPEN, PICK, prev="pick.grasp", end=StepEnd.FAILED))
    assert d.ecm == "pick.grasp"


def test_replan_keeps_objects_already_placed_in_a_multi_object_task(policy: DecompositionPolicy) -> None:
    caps = task_capabilities("pick_place_multi")
    signals = dict.fromkeys(task_spec("pick_place_multi").signal_names, 0.3)
    signals.update(
        {
            "milk_object_in_bin": 1.0,  # milk placed, hand far from it
            "milk_object_target_xy_dist": 0.0,
            "bread_grasped": 0.0,  # bread slipped out during its lift
            "gripper_opening": 0.0,
            "n_placed": 1.0,
            "success": 0.0,
            "bread_object_in_bin": 0.0,
            "can_object_in_bin": 0.0,
            "milk_grasped": 0.0,
            "can_grasped": 0.0,
        }
    )
    d = policy.decide(
        context("pick_place_multi", signals, caps, prev="pick_place_multi.bread.lift", end=StepEnd.FAILED)
    )
    assert d.ecm == "pick_place_multi.bread.reach"


def test_attempt_limit_ends_the_episode_with_a_reason() -> None:
    attempts = {"pick.reach": 3, "pick.grasp": 3, "pick.lift": 3}
    ctx = context("pick", PICK_SLIPPED, PICK, prev="pick.lift", end=StepEnd.FAILED, attempts=attempts)
    d = DecompositionPolicy(identity=IdentityMemory.default()).decide(ctx)
    assert d == Decision(ecm=None, reason="pick.reach reached its attempt limit (3 of 3 starts)")
    more = DecompositionPolicy(identity=IdentityMemory.default(), parameters=PolicyParameters(max_attempts_per_ecm=4))
    assert more.decide(ctx).ecm == "pick.reach"


def test_attempts_below_the_limit_do_not_stop(policy: DecompositionPolicy) -> None:
    ctx = context("pick", PICK_SLIPPED, PICK, prev="pick.lift", end=StepEnd.FAILED, attempts={"pick.reach": 2})
    assert policy.decide(ctx).ecm == "pick.reach"


def test_applicability_gates_the_next_step(policy: DecompositionPolicy) -> None:
    # Reach reported success but the can is 5 cm away now: grasp does not apply, nor does
    # lift, so the policy re-plans and reaches again.
    drifted = {**PICK_FAR, "eef_object_dist": 0.05, "eef_object_xy_dist": 0.04, "eef_object_dz": 0.03}
    d = policy.decide(context("pick", drifted, PICK, prev="pick.reach", end=StepEnd.TERMINATED))
    assert d.ecm == "pick.reach"
    assert "nothing applicable from pick.grasp" in d.reason


def _abc_policy(order: tuple[str, ...] = ("t.a", "t.b", "t.c")) -> tuple[DecompositionPolicy, dict[str, object]]:
    """a applies when x > 0, b always (no applicability), c when y > 0."""
    identity = IdentityMemory(name="t", decompositions={"t": order})
    caps = {
        "t.a": step_version("t.a", "a", ("a", ">=", 1), ("x", ">", 0)),
        "t.b": step_version("t.b", "b", ("b", ">=", 1)),
        "t.c": step_version("t.c", "c", ("c", ">=", 1), ("y", ">", 0)),
    }
    return DecompositionPolicy(identity=identity), caps


def test_an_inapplicable_step_is_passed_over_for_a_later_step_whose_applicability_holds() -> None:
    policy, caps = _abc_policy(("t.a", "t.c", "t.b"))
    signals = {"x": 0.0, "y": 1.0, "a": 0.0, "b": 0.0, "c": 0.0}
    assert policy.decide(context("t", signals, caps)).ecm == "t.c"
    assert policy.candidates(context("t", signals, caps)) == ("t.c",)


def test_the_walk_never_passes_over_a_step_to_one_that_always_applies() -> None:
    # b has no applicability predicate: running it would abandon a, not skip a finished stage.
    policy, caps = _abc_policy()
    signals = {"x": 0.0, "y": 1.0, "a": 0.0, "b": 0.0, "c": 0.0}
    d = policy.decide(context("t", signals, caps))
    assert d == Decision(ecm=None, reason="no applicable step: t.a is not done and needs x > 0")
    assert policy.candidates(context("t", signals, caps)) == ()
    # A planner may still reorder steps that all apply.
    assert policy.candidates(context("t", {**signals, "x": 1.0}, caps)) == ("t.a", "t.b", "t.c")
    assert policy.decide(context("t", {**signals, "a": 1.0}, caps)).ecm == "t.b"


def _multi_signals(**overrides: float) -> dict[str, float]:
    """T5 with nothing placed or grasped, the hand 30 cm from everything, gripper closed."""
    signals = dict.fromkeys(task_spec("pick_place_multi").signal_names, 0.3)
    for key in signals:
        if key.endswith(("grasped", "object_in_bin", "height_above_start")) or key in ("n_placed", "success"):
            signals[key] = 0.0
        if key.endswith("quadrant_margin"):
            signals[key] = -0.3  # in the source bin, outside every goal quadrant
    signals["gripper_opening"] = 0.0
    return {**signals, **overrides}


@pytest.mark.parametrize(
    ("prev", "end"),
    [
        ("pick_place_multi.milk.reach", StepEnd.TERMINATED),  # the hand drifted off the milk
        ("pick_place_multi.milk.grasp", StepEnd.TERMINATED),  # the milk slipped out at once
        ("pick_place_multi.milk.lift", StepEnd.FAILED),
    ],
)
def test_a_multi_object_walk_returns_to_the_object_it_left_not_the_next_one(
    policy: DecompositionPolicy, prev: str, end: StepEnd
) -> None:
    caps = task_capabilities("pick_place_multi")
    d = policy.decide(context("pick_place_multi", _multi_signals(), caps, prev=prev, end=end))
    assert d.ecm == "pick_place_multi.milk.reach"


def test_a_multi_object_walk_moves_on_once_the_object_is_placed(policy: DecompositionPolicy) -> None:
    caps = task_capabilities("pick_place_multi")
    placed = _multi_signals(milk_object_in_bin=1.0, milk_eef_object_dist=0.2, milk_object_quadrant_margin=0.05)
    d = policy.decide(
        context("pick_place_multi", placed, caps, prev="pick_place_multi.milk.release", end=StepEnd.TERMINATED)
    )
    assert d.ecm == "pick_place_multi.bread.reach"


def test_no_applicable_step_ends_the_episode_naming_what_it_waits_for() -> None:
    policy, caps = _abc_policy()
    signals = {"x": 0.0, "y": 0.0, "a": 0.0, "b": 1.0, "c": 0.0}
    d = policy.decide(context("t", signals, caps))
    assert d == Decision(ecm=None, reason="no applicable step: t.a is not done and needs x > 0")


def test_descriptors_from_the_capability_set_drive_the_choice(policy: DecompositionPolicy) -> None:
    stricter = Descriptor(
        description="reach within 1 mm",
        termination=pred("within 1 mm", ("eef_object_xy_dist", "<", 0.001)),
    )
    caps = {**PICK, "pick.reach": version("pick.reach", stricter, v=2)}
    assert policy.decide(context("pick", PICK_AT_CAN_OPEN, PICK)).ecm == "pick.grasp"
    assert policy.decide(context("pick", PICK_AT_CAN_OPEN, caps)).ecm == "pick.reach"


def test_an_ecm_outside_the_plan_replans_from_the_start(policy: DecompositionPolicy) -> None:
    d = policy.decide(context("pick", PICK_FAR, PICK, prev="recovery.home", end=StepEnd.TERMINATED))
    assert d.ecm == "pick.reach" and "not in the plan" in d.reason


def test_task_may_be_named_by_its_id(policy: DecompositionPolicy) -> None:
    assert policy.decide(context("T1", PICK_FAR, PICK)).ecm == "pick.reach"


def test_missing_ecms_are_a_clear_invalid(policy: DecompositionPolicy) -> None:
    caps = {k: v for k, v in PICK.items() if k != "pick.lift"}
    with pytest.raises(Invalid) as info:
        policy.decide(context("pick", PICK_LIFTED, caps))  # raised even when lift is not next
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == (
        "task 'pick' needs ECM(s) pick.lift, which the runtime has not loaded (loaded: pick.grasp, pick.reach)"
    )
    assert info.value.details["missing"] == ["pick.lift"]


def test_unknown_task_is_invalid_and_lists_known_tasks(policy: DecompositionPolicy) -> None:
    with pytest.raises(Invalid) as info:
        policy.decide(context("juggle", PICK_FAR, PICK))
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message.startswith(
        "identity 'capevo-default' has no decomposition for task 'juggle'; known: pick"
    )


def test_a_predicate_over_a_signal_the_task_lacks_is_invalid(policy: DecompositionPolicy) -> None:
    signals = {k: v for k, v in PICK_FAR.items() if k != "grasped"}
    with pytest.raises(Invalid) as info:
        policy.decide(context("pick", signals, PICK))
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message.startswith("pick.grasp v1 termination predicate: predicate uses signal 'grasped'")
    assert info.value.details["ecm"] == "pick.grasp"


def test_plan_checks_signals_up_front(policy: DecompositionPolicy) -> None:
    steps = policy.plan("pick", PICK, signals=task_spec("pick").signal_names)
    assert [s.ecm for s in steps] == ["pick.reach", "pick.grasp", "pick.lift"]
    assert steps[1].descriptor == PICK["pick.grasp"].descriptor
    with pytest.raises(Invalid) as info:
        policy.plan("pick", PICK, signals=["eef_object_dist"])
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == (
        "pick.reach v1 termination predicate uses signal(s) eef_object_dz, eef_object_xy_dist, gripper_opening, "
        "which task 'pick' does not expose"
    )


@pytest.mark.parametrize("bad", [0, -1, 1001, True, 2.0, "3"])
def test_policy_parameters_are_validated(bad: object) -> None:
    with pytest.raises(Invalid) as info:
        PolicyParameters(max_attempts_per_ecm=bad)  # type: ignore[arg-type]
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message.startswith("max_attempts_per_ecm: must be an integer from 1 to 1000")


def test_parameters_are_a_frozen_record_with_a_vector() -> None:
    p = PolicyParameters(max_attempts_per_ecm=4)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.max_attempts_per_ecm = 5  # type: ignore[misc]
    assert PolicyParameters.from_dict(p.to_dict()) == p
    assert DecompositionPolicy(identity=IdentityMemory.default(), parameters=p).parameters_vector() == (4.0,)


_PICK_NAMES = task_spec("pick").signal_names
_PICK_ECMS = ("pick.reach", "pick.grasp", "pick.lift")
_BY_LIMIT = {
    n: DecompositionPolicy(identity=IdentityMemory.default(), parameters=PolicyParameters(max_attempts_per_ecm=n))
    for n in range(1, 5)
}


@settings(max_examples=200, deadline=None)
@given(
    signals=st.fixed_dictionaries(
        {k: st.sampled_from([-0.05, 0.0, 0.01, 0.03, 0.05, 0.07, 0.5, 1.0]) for k in _PICK_NAMES}
    ),
    prev=st.sampled_from([None, *_PICK_ECMS, "other.ecm"]),
    end=st.sampled_from(list(StepEnd)),
    attempts=st.dictionaries(st.sampled_from(_PICK_ECMS), st.integers(0, 4)),
    limit=st.integers(1, 4),
)
def test_every_decision_names_an_unfinished_applicable_ecm_under_its_limit(
    signals: dict[str, float], prev: str | None, end: StepEnd, attempts: dict[str, int], limit: int
) -> None:
    policy = _BY_LIMIT[limit]
    ctx = context("pick", signals, PICK, prev=prev, end=end, attempts=attempts)
    d = policy.decide(ctx)
    assert d == policy.decide(ctx)  # deterministic, stateless
    if d.ecm is None:
        assert d.reason
        return
    desc = PICK[d.ecm].descriptor
    assert d.ecm in _PICK_ECMS
    assert not predicate_holds(desc.termination, signals)
    assert predicate_holds(desc.applicability, signals)
    assert attempts.get(d.ecm, 0) < limit
    assert d.ecm in policy.candidates(ctx)
