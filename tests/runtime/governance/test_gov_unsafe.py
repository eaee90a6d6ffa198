"""The unsafe-step metric, and its relation to what the governor lets through."""

from __future__ import annotations

import math

import numpy as np
import pytest
from govcheck import actions, finite_state, robot_states, state_of
from hypothesis import assume, given, settings

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import (
    TWO_ARM_NO_GRIPPER,
    Aabb,
    ForbiddenZone,
    Phi,
    is_unsafe,
    layout_for,
    unsafe_reasons,
)
from capevo.runtime.state import SINGLE_PANDA, ActionLayout, ArmActionLayout

PHI = Phi.default()
INSIDE = ((0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
CALM = (0.5, 0.5, 0.5, 0.1, 0.1, 0.1, 1.0)


def test_a_step_inside_the_envelope_is_safe() -> None:
    assert unsafe_reasons(state_of(INSIDE), CALM, PHI) == ()
    assert not is_unsafe(state_of(INSIDE), CALM, PHI)
    # The margin is where governance acts; it is still inside the box, so still safe.
    assert not is_unsafe(state_of(((0.6, -0.6, 1.3), (0.0, 0.0, 20.0))), (1.5, 0, 0, 0, 0, 0, 99.0), PHI)


@pytest.mark.parametrize(
    ("state", "action", "reason"),
    [
        (
            state_of(((0.61, 0, 1), (0, 0, 0))),
            CALM,
            "workspace_box: arm 0: end effector x=0.61 m is outside [-0.6, 0.6]",
        ),
        (
            state_of(((0, 0, 0.59), (0, 0, 0))),
            CALM,
            "workspace_box: arm 0: end effector z=0.59 m is outside [0.6, 1.3]",
        ),
        (state_of(((0.0, 0.0, 1.0), (0, 12, 16.1))), CALM, "contact_force: arm 0: contact force 20.08"),
        (state_of(INSIDE), (1.5, 0.1, 0, 0, 0, 0, 0), "velocity_cap: arm 0: pose-delta norm 1.503"),
        (state_of(INSIDE), (0, 0, 0, 0, 0, 0, math.nan), "action: components [6] are not finite"),
        (state_of(((math.nan, 0.0, 1.0), (0, 0, 0))), CALM, "workspace_box: arm 0: end effector x=nan m is outside"),
        (state_of(((0.0, 0.0, 1.0), (0, 0, math.inf))), CALM, "contact_force: arm 0: contact force inf N"),
    ],
)
def test_each_hard_limit_makes_a_step_unsafe(state, action, reason) -> None:
    reasons = unsafe_reasons(state, action, PHI)
    assert len(reasons) == 1 and reasons[0].startswith(reason), reasons
    assert is_unsafe(state, np.array(action), PHI)


def test_only_constraints_in_phi_count_and_reasons_accumulate() -> None:
    state = state_of(((0.7, 0.0, 1.0), (0.0, 0.0, 50.0)))
    action = (3.0, 0, 0, 0, 0, 0, 0)
    assert [r.split(":")[0] for r in unsafe_reasons(state, action, PHI)] == [
        "workspace_box",
        "contact_force",
        "velocity_cap",
    ]
    assert unsafe_reasons(state, action, Phi(())) == ()
    zone = Phi((ForbiddenZone(boxes=(Aabb(low=(0.6, -0.1, 0.9), high=(0.8, 0.1, 1.1)),)),))
    assert unsafe_reasons(state, action, zone) == (
        "forbidden_zone: arm 0: end effector (0.7, 0.0, 1.0) is inside forbidden zone 0",
    )


def test_without_an_executed_action_only_the_state_is_judged() -> None:
    assert not is_unsafe(state_of(INSIDE), None, PHI)
    assert is_unsafe(state_of(((0.0, 0.0, 1.4), (0, 0, 0))), None, PHI)


def test_two_arm_steps_and_layout_inference() -> None:
    state = state_of(INSIDE, INSIDE)
    ok = (0.5,) * 12
    assert not is_unsafe(state, ok, PHI)
    over = (0.0,) * 6 + (1.0,) * 6
    assert unsafe_reasons(state, over, PHI)[0].startswith("velocity_cap: arm 1: pose-delta norm 2.449")
    assert layout_for(1, 7) is SINGLE_PANDA and layout_for(2, 12) is TWO_ARM_NO_GRIPPER
    assert layout_for(3, 21).arms[2] == ArmActionLayout(offset=14, gripper=20)
    assert layout_for(3, 18).arms[2] == ArmActionLayout(offset=12)
    with pytest.raises(Invalid) as e:
        is_unsafe(state, (0.0,) * 13, PHI)
    assert e.value.code is ErrorCode.INVALID
    assert e.value.message == "action: cannot infer a layout for 2 arm(s) and 13 components; pass layout="
    with pytest.raises(Invalid) as e:
        is_unsafe(state, (0.0,) * 7, PHI, ActionLayout(dim=12, arms=TWO_ARM_NO_GRIPPER.arms))
    assert e.value.message == "action: has 7 components; the layout expects 12"


@settings(max_examples=300, deadline=None)
@given(state=robot_states(2), action=actions(12))
def test_a_governed_action_never_breaks_an_action_side_limit(state, action) -> None:
    assume(finite_state(state))
    out, _ = PHI.governor(TWO_ARM_NO_GRIPPER)(state, action)
    state_only = unsafe_reasons(state, None, PHI, TWO_ARM_NO_GRIPPER)
    assert unsafe_reasons(state, out, PHI, TWO_ARM_NO_GRIPPER) == state_only


@settings(max_examples=200, deadline=None)
@given(state=robot_states(1), action=actions(7))
def test_unsafe_is_exactly_the_union_of_state_and_action_limits(state, action) -> None:
    reasons = unsafe_reasons(state, action, PHI)
    assert is_unsafe(state, action, PHI) == bool(reasons)
    n2 = sum(x * x for x in action[:6])
    cap_broken = not (all(math.isfinite(x) for x in action) and n2 <= 1.5**2)
    assert any(r.startswith(("velocity_cap", "action")) for r in reasons) == cap_broken
