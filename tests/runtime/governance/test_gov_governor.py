"""The governor's contract: allow path, short-circuit on ⊥, governance-off counting, guards, records."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from typing import Any, ClassVar

import numpy as np
import pytest
from govcheck import actions, finite_state, robot_states, state_of
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import Conflict, ErrorCode, Invalid
from capevo.runtime.governance import (
    CONSTRAINTS,
    TWO_ARM_NO_GRIPPER,
    GovernanceStats,
    Intervention,
    Phi,
    Verdict,
    hold_action,
    make,
    register,
    verdict_of,
)
from capevo.runtime.governance.base import normalize
from capevo.runtime.governance.governor import NO_INTERVENTIONS
from capevo.runtime.state import SINGLE_PANDA, ActionLayout, ArmActionLayout

INSIDE = state_of(((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)))
CALM = (0.1, -0.2, 0.3, 0.01, 0.02, -0.03, 1.0)


@pytest.mark.parametrize("kind", [tuple, list, np.array])
def test_allow_path_returns_the_very_same_object_and_the_shared_empty_tuple(kind: Any) -> None:
    gov = Phi.default().governor(SINGLE_PANDA)
    action = kind(CALM)
    out, records = gov(INSIDE, action)
    assert out is action
    assert records is NO_INTERVENTIONS
    assert verdict_of(records) is Verdict.ALLOW


def test_modify_returns_a_new_tuple_of_floats_and_chains_constraints_in_order() -> None:
    gov = Phi.default().governor(SINGLE_PANDA)
    state = state_of(((0.55, 0.0, 0.9), (0.0, 0.0, 40.0)))
    action = np.array([1.0, 1.5, -1.0, 1.0, 0.5, 0.0, 1.0], dtype=np.float32)
    out, records = gov(state, action)
    assert type(out) is tuple and all(type(x) is float for x in out)  # numpy's tolist() gives Python floats
    assert [r.constraint for r in records] == ["workspace_box", "contact_force", "velocity_cap"]
    assert records[0].original == (1.0, 1.5, -1.0, 1.0, 0.5, 0.0, 1.0)
    # Each record starts where the previous one ended; the last result is what is returned.
    for prev, nxt in itertools.pairwise(records):
        assert nxt.original == prev.result
    assert records[-1].result == out
    assert out[0] == 0.0 and out[2] == 0.0 and out[6] == 1.0
    assert verdict_of(records) is Verdict.MODIFY
    assert all(r.enforced for r in records)


def test_reject_short_circuits_so_later_constraints_do_not_run() -> None:
    gov = Phi.default().governor(SINGLE_PANDA)
    # The position is NaN (workspace_box rejects); the 40 N force would have made contact_force act.
    state = state_of(((math.nan, 0.0, 0.9), (0.0, 0.0, 40.0)))
    out, records = gov(state, (0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0))
    assert out is None
    (rec,) = records
    assert rec.constraint == "workspace_box" and rec.result is None
    assert rec.reason.startswith("arm 0: end-effector position (nan, 0.0, 0.9) is not finite")
    assert verdict_of(records) is Verdict.REJECT
    assert gov.stats().by_constraint == {"workspace_box": 1}


@pytest.mark.parametrize(
    ("action", "state", "reason"),
    [
        ((0.0,) * 6, INSIDE, "action has 6 components; the layout expects 7"),
        (CALM, state_of(((0, 0, 1), (0, 0, 0)), ((0, 0, 1), (0, 0, 0))), "state has 2 arm(s); the layout expects 1"),
        ((0.0, 0.0, "x", 0.0, 0.0, 0.0, 0.0), INSIDE, "action components [2] are not finite numbers"),
        (None, INSIDE, "action of type NoneType is not a flat sequence of numbers"),
        (np.zeros((7, 1)), INSIDE, "action of type ndarray is not a flat sequence of numbers"),
        (np.float64(1.0), INSIDE, "action of type float64 is not a flat sequence of numbers"),
        (np.array(1.0), INSIDE, "action of type ndarray is not a flat sequence of numbers"),
        ([[0.0]] * 7, INSIDE, "action components [0, 1, 2, 3, 4, 5, 6] are not finite numbers"),
        ((0.0, 0.0, 1j, 0.0, 0.0, 0.0, 0.0), INSIDE, "action components [2] are not finite numbers"),
        (
            (0.0, math.inf, -math.inf, 0.0, 0.0, 0.0, math.nan),
            INSIDE,
            "action components [1, 2, 6] are not finite numbers",
        ),
    ],
)
def test_guard_rejects_malformed_input_with_a_reason(action: Any, state: Any, reason: str) -> None:
    for enforce in (True, False):
        gov = Phi.default().governor(SINGLE_PANDA, enforce=enforce)
        out, (rec,) = gov(state, action)
        assert rec.constraint == "governor" and rec.result is None and rec.reason == reason
        assert rec.enforced is enforce
        assert out is (None if enforce else action)
        assert gov.stats().rejected == 1


def test_huge_finite_components_whose_sum_overflows_are_not_mistaken_for_inf() -> None:
    gov = Phi.default().governor(SINGLE_PANDA)
    out, records = gov(INSIDE, (1.7e308, 1.7e308, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert out is not None and [r.constraint for r in records] == ["velocity_cap"]


@settings(max_examples=200, deadline=None)
@given(state=robot_states(2), action=actions(12))
def test_governance_off_passes_everything_through_and_counts_what_it_would_have_done(state, action) -> None:
    on = Phi.default().governor(TWO_ARM_NO_GRIPPER)
    off = Phi.default().governor(TWO_ARM_NO_GRIPPER, enforce=False)
    _, rec_on = on(state, action)
    out_off, rec_off = off(state, action)
    assert out_off is action
    assert [dataclasses.replace(r, enforced=True) for r in rec_off] == list(rec_on)
    assert all(not r.enforced for r in rec_off)
    assert verdict_of(rec_off) == verdict_of(rec_on)
    s_on, s_off = on.stats(), off.stats()
    assert (s_on.enforced, s_off.enforced) == (True, False)
    assert dataclasses.replace(s_off, enforced=True) == s_on
    assert s_off.intervened == (1 if rec_on else 0)


def test_stats_count_steps_modifications_rejections_and_reset() -> None:
    gov = Phi.default().governor(SINGLE_PANDA)
    gov(INSIDE, CALM)
    gov(INSIDE, (2.0, 0, 0, 0, 0, 0, 0))
    gov(state_of(((0.59, 0, 1.0), (0, 0, 0))), (2.0, 0, 0, 0, 0, 0, 0))
    gov(INSIDE, (math.nan,) * 7)
    assert gov.stats() == GovernanceStats(
        enforced=True,
        steps=4,
        modified=2,
        rejected=1,
        by_constraint={"governor": 1, "workspace_box": 1, "velocity_cap": 1},
    )
    assert gov.stats().intervened == 3
    assert gov.stats().to_dict()["by_constraint"] == {"governor": 1, "workspace_box": 1, "velocity_cap": 1}
    gov.reset_stats()
    assert gov.stats() == GovernanceStats(enforced=True, steps=0, modified=0, rejected=0, by_constraint={})


def test_hold_action_zeroes_pose_and_keeps_each_gripper() -> None:
    assert hold_action(SINGLE_PANDA) == (0.0,) * 7
    assert hold_action(SINGLE_PANDA, (1, 1, 1, 1, 1, 1, -1)) == (0.0,) * 6 + (-1.0,)
    assert hold_action(SINGLE_PANDA, (1, 1, 1, 1, 1, 1, math.nan)) == (0.0,) * 7
    assert hold_action(TWO_ARM_NO_GRIPPER, (1.0,) * 12) == (0.0,) * 12
    two_grippers = ActionLayout(
        dim=14, arms=(ArmActionLayout(offset=0, gripper=6), ArmActionLayout(offset=7, gripper=13))
    )
    held = hold_action(two_grippers, tuple(float(i) for i in range(14)))
    assert held[6] == 6.0 and held[13] == 13.0 and sum(held) == 19.0


@settings(max_examples=200, deadline=None)
@given(
    original=st.lists(st.floats(), max_size=12),
    result=st.none() | st.lists(st.floats(allow_nan=False), max_size=12),
    reason=st.text(),
    enforced=st.booleans(),
)
def test_intervention_round_trips_through_strict_json(original, result, reason, enforced) -> None:
    rec = Intervention(
        constraint="workspace_box",
        original=tuple(original),
        result=None if result is None else tuple(result),
        reason=reason,
        enforced=enforced,
    )
    wire = json.loads(json.dumps(rec.to_dict(), allow_nan=False))
    back = Intervention.from_dict(wire)
    assert repr(back) == repr(rec)  # repr, because nan != nan


def test_intervention_from_dict_rejects_bad_payloads() -> None:
    with pytest.raises(Invalid) as e:
        Intervention.from_dict({"constraint": "x", "original": [], "reason": "r"})
    assert e.value.code is ErrorCode.INVALID and e.value.message == "intervention: missing key 'result'"
    with pytest.raises(Invalid) as e:
        Intervention.from_dict({"constraint": "x", "original": [1, "a"], "result": None, "reason": "r"})
    assert e.value.message == "original[1]: expected a number, got str"
    assert e.value.details["field"] == "original[1]"


@pytest.mark.parametrize(
    ("frames", "message"),
    [
        ([(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)] * 2, "frames: 2 given; the layout has 1 arm(s)"),
        ([(2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)], "frames[0]: not a rotation matrix"),
        ([(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0)], "frames[0]: not a rotation matrix"),  # a reflection
        ([(1.0, 0.0, 0.0)], "frames[0]: expected 9 finite floats (row-major 3x3)"),
    ],
)
def test_frames_must_be_one_rotation_per_arm(frames: Any, message: str) -> None:
    with pytest.raises(Invalid) as e:
        Phi.default().governor(SINGLE_PANDA, frames=frames)
    assert e.value.code is ErrorCode.INVALID and e.value.message == message


def test_layout_indices_must_fit_without_overlap() -> None:
    with pytest.raises(Invalid) as e:
        Phi.default().governor(ActionLayout(dim=7, arms=(ArmActionLayout(offset=2, gripper=0),)))
    assert e.value.message == "layout.arms[0]: index 7 is outside an action of 7"
    with pytest.raises(Invalid) as e:
        Phi.default().governor(ActionLayout(dim=7, arms=(ArmActionLayout(offset=0, gripper=3),)))
    assert e.value.message == "layout.arms[0]: index 3 is used twice"


def test_a_registered_custom_constraint_runs_in_the_chain_and_duplicates_conflict() -> None:
    kind = "test_gov_reject_when_gripper_closed"

    @register(kind)
    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class RejectClosedGripper:
        kind: ClassVar[str]
        threshold: float = 0.5
        name: str | None = None

        def __post_init__(self) -> None:
            normalize(self)

        @property
        def label(self) -> str:
            return self.name or self.kind

        def to_config(self) -> dict[str, Any]:
            return {"threshold": self.threshold, "name": self.name}

        def compile(self, layout: ActionLayout) -> Any:
            g = layout.arms[0].gripper
            t = self.threshold
            return lambda arms, a: (None, f"gripper {a[g]} above {t}") if a[g] > t else None

        def unsafe(self, arms: Any, action: Any, layout: ActionLayout) -> str | None:
            return None

    try:
        c = make(kind, threshold=1)
        assert c.threshold == 1.0 and type(c.threshold) is float
        phi = Phi((c, *Phi.default().constraints))
        gov = phi.governor(SINGLE_PANDA)
        out, (rec,) = gov(state_of(((0.59, 0, 1), (0, 0, 99))), (1.0, 0, -1.0, 0, 0, 0, 2.0))
        assert out is None and rec.constraint == kind and rec.reason == "gripper 2.0 above 1.0"
        with pytest.raises(Conflict) as e:
            register(kind)(RejectClosedGripper)
        assert e.value.code is ErrorCode.CONFLICT
        assert e.value.message == f"constraint kind {kind!r} is already registered"
    finally:
        CONSTRAINTS.pop(kind, None)


@settings(max_examples=100, deadline=None)
@given(state=robot_states(1), action=actions(7))
def test_numpy_list_and_tuple_inputs_govern_identically(state, action) -> None:
    gov = Phi.default().governor(SINGLE_PANDA)
    results = [gov(state, kind(action)) for kind in (tuple, list, np.array)]
    outs = [None if o is None else tuple(float(x) for x in o) for o, _ in results]
    assert outs[0] == outs[1] == outs[2] or not finite_state(state)
    assert results[0][1] == results[1][1] == results[2][1]


def test_several_edits_by_one_constraint_share_one_record_with_reasons_joined_in_arm_and_axis_order() -> None:
    gov = Phi.default().governor(TWO_ARM_NO_GRIPPER)
    # Arm 0 beyond +x and pushing down into a 35 N contact; arm 1 near +y and +z.
    state = state_of(((0.55, -0.2, 1.0), (0.0, 0.0, 35.0)), ((0.0, 0.56, 1.25), (0.0, 0.0, 0.0)))
    action = (1.0, 0.4, -1.0, 1.0, 1.0, 0.5, 0.0, 1.0, 1.0, 1.2, 1.2, 0.0)
    out, (box, force, cap) = gov(state, action)
    face = "within 0.08 m of the {} face ({} m) or beyond: motion out through it zeroed"
    assert box.reason == "; ".join(
        [f"arm 0: {face.format('+x', 0.6)}", f"arm 1: {face.format('+y', 0.6)}", f"arm 1: {face.format('+z', 1.3)}"]
    )
    assert box.result == (0.0, 0.4, -1.0, 1.0, 1.0, 0.5, 0.0, 0.0, 0.0, 1.2, 1.2, 0.0)
    assert force.reason == "arm 0: contact force above 20.0 N: motion into the contact along z zeroed"
    assert cap.reason == "; ".join(f"arm {i}: pose-delta norm above the cap 1.5: scaled down to it" for i in (0, 1))
    assert out is cap.result and all(type(x) is float for x in out)
    assert gov.stats().by_constraint == {"workspace_box": 1, "contact_force": 1, "velocity_cap": 1}
