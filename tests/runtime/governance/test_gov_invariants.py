"""Property tests: whatever the action and state, the governed action satisfies every constraint of Φ."""

from __future__ import annotations

import math

import numpy as np
import pytest
from govcheck import (
    ANY_FLOAT,
    FINITE,
    QUATS,
    actions,
    finite_state,
    robot_states,
    rotation,
    state_of,
    to_world,
    violations,
)
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import (
    TWO_ARM_NO_GRIPPER,
    Aabb,
    ContactForce,
    ForbiddenZone,
    Phi,
    VelocityCap,
    WorkspaceBox,
)
from capevo.runtime.governance.cap import SHRINK
from capevo.runtime.state import SINGLE_PANDA, ActionLayout

ZONE = ForbiddenZone(boxes=(Aabb(low=(0.2, -0.1, 0.8), high=(0.4, 0.1, 1.0)),), margin=0.05)
FULL = Phi((WorkspaceBox(), ContactForce(), VelocityCap(), ZONE))
"""Every built-in kind, defaults plus one forbidden zone."""
REVERSED = Phi(tuple(reversed(FULL.constraints)))

LAYOUTS = {"single": SINGLE_PANDA, "two_arm": TWO_ARM_NO_GRIPPER}


RZ90 = (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
RZ_90 = (0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
FLIP = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
SIGNED_PERMUTATIONS = st.sampled_from([RZ90, RZ_90, FLIP, (0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0)])


def _check_edit_is_minimal(layout: ActionLayout, before: list[float], after: tuple[float, ...], rotated: bool) -> None:
    """Each arm: a common factor 0 < s <= 1; every component is s * input or 0; the gripper is untouched."""
    for arm in layout.arms:
        o = arm.offset
        if arm.gripper is not None:
            assert after[arm.gripper] == before[arm.gripper]
        if rotated:
            continue
        # Zeroed (or scaled down to a subnormal that underflows), or scaled by a positive factor.
        for x, y in zip(before[o : o + 6], after[o : o + 6], strict=True):
            assert abs(y) <= abs(x)
            assert y == 0.0 or (x > 0) == (y > 0)


@pytest.mark.parametrize("phi", [FULL, REVERSED], ids=["order", "reversed"])
@pytest.mark.parametrize("layout_name", list(LAYOUTS))
@settings(max_examples=250, deadline=None)
@given(data=st.data())
def test_governed_action_satisfies_every_constraint(phi: Phi, layout_name: str, data: st.DataObject) -> None:
    layout = LAYOUTS[layout_name]
    state = data.draw(robot_states(len(layout.arms)))
    action = data.draw(actions(layout.dim))
    assume(finite_state(state))
    out, records = phi.governor(layout)(state, action)
    assert out is not None, records  # finite inputs are never rejected by the built-ins
    assert violations(phi, layout, state, out) == []
    _check_edit_is_minimal(layout, action, out if records else tuple(action), rotated=False)
    if not records:
        assert out is action


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
@settings(max_examples=200, deadline=None)
@given(data=st.data(), exact=st.booleans())
def test_governed_action_satisfies_every_constraint_in_rotated_action_frames(
    layout_name: str, data: st.DataObject, exact: bool
) -> None:
    layout = LAYOUTS[layout_name]
    frames = [data.draw(SIGNED_PERMUTATIONS if exact else QUATS.map(rotation)) for _ in layout.arms]
    state = data.draw(robot_states(len(layout.arms)))
    action = data.draw(actions(layout.dim, st.floats(-10, 10)))
    assume(finite_state(state))
    out, records = FULL.governor(layout, frames=frames)(state, action)
    assert out is not None
    tol = 0.0 if exact else 1e-9
    assert violations(FULL, layout, state, out, frames=frames, tol=tol) == []
    if not records:
        assert out is action


@settings(max_examples=300, deadline=None)
@given(state=robot_states(1), action=actions(7))
def test_workspace_box_zeroes_exactly_the_outward_components(state, action) -> None:
    box = WorkspaceBox()
    assume(finite_state(state))
    out, _ = Phi((box,)).governor(SINGLE_PANDA)(state, action)
    (p,) = [arm.eef_pos for arm in state.arms]
    for k in range(3):
        outward_hi = p[k] >= box.high[k] - box.margin and action[k] > 0
        outward_lo = p[k] <= box.low[k] + box.margin and action[k] < 0
        assert out[k] == (0.0 if outward_hi or outward_lo else action[k])
    assert list(out[3:]) == list(action[3:])


@settings(max_examples=300, deadline=None)
@given(action=actions(12, FINITE), cap=st.floats(min_value=1e-3, max_value=1e3))
def test_velocity_cap_bounds_each_arm_and_keeps_direction(action, cap) -> None:
    state = state_of(((0, 0, 1), (0, 0, 0)), ((0, 0, 1), (0, 0, 0)))
    out, records = Phi((VelocityCap(max_norm=cap),)).governor(TWO_ARM_NO_GRIPPER)(state, action)
    for o in (0, 6):
        before, after = action[o : o + 6], out[o : o + 6]
        n2 = after[0] ** 2 + after[1] ** 2 + after[2] ** 2 + after[3] ** 2 + after[4] ** 2 + after[5] ** 2
        assert n2 <= cap * cap
        big = max(abs(x) for x in before)
        n_before = big * math.hypot(*[x / big for x in before]) if big else 0.0
        if n_before <= cap:
            assert list(after) == list(before)
        else:  # the same direction, at just under the cap
            unit = [x / big for x in before]
            for u, y in zip(unit, after, strict=True):
                assert y == pytest.approx(u / math.hypot(*unit) * cap * SHRINK, rel=1e-9, abs=1e-300)
            assert math.sqrt(n2) == pytest.approx(cap, rel=1e-8)
    assert bool(records) == any(not sum(x * x for x in action[o : o + 6]) <= cap * cap for o in (0, 6))


@settings(max_examples=300, deadline=None)
@given(
    state=robot_states(1, force=st.floats(-100, 100)),
    action=actions(7),
    limit=st.floats(min_value=0.1, max_value=80),
)
def test_contact_force_removes_motion_into_the_contact_above_the_limit(state, action, limit) -> None:
    assume(finite_state(state))
    out, _ = Phi((ContactForce(max_force=limit),)).governor(SINGLE_PANDA)(state, action)
    f = state.arms[0].eef_force
    above = f[0] ** 2 + f[1] ** 2 + f[2] ** 2 > limit**2
    for k in range(3):
        if above:
            against = (action[k] > 0 > f[k]) or (action[k] < 0 < f[k])
            assert not ((out[k] > 0 > f[k]) or (out[k] < 0 < f[k]))
            assert out[k] == (0.0 if against else action[k])
        else:
            assert out[k] == action[k]
    if above:
        assert sum(out[k] * f[k] for k in range(3)) >= 0.0
    assert list(out[3:]) == list(action[3:])


@settings(max_examples=300, deadline=None)
@given(
    state=robot_states(1, pos=st.floats(-0.2, 0.8)),
    action=actions(7, st.floats(-2, 2)),
    margin=st.floats(0, 0.2),
)
def test_forbidden_zone_blocks_every_approach_within_the_margin(state, action, margin) -> None:
    zone = ForbiddenZone(boxes=(Aabb(low=(0.2, 0.0, 0.2), high=(0.4, 0.3, 0.5)),), margin=margin)
    phi = Phi((zone,))
    out, _ = phi.governor(SINGLE_PANDA)(state, action)
    assert violations(phi, SINGLE_PANDA, state, out) == []
    p = state.arms[0].eef_pos
    near = all(lo - margin <= x <= hi + margin for x, lo, hi in zip(p, (0.2, 0.0, 0.2), (0.4, 0.3, 0.5), strict=True))
    if not near:
        assert out is action


def test_forbidden_zone_examples() -> None:
    phi = Phi((ForbiddenZone(boxes=(Aabb(low=(0.2, -0.1, 0.8), high=(0.4, 0.1, 1.0)),), margin=0.05),))
    gov = phi.governor(SINGLE_PANDA)
    a = (1.0, 1.0, -1.0, 0.0, 0.0, 0.0, 0.5)
    # 3 cm in front of the -x face, level with the zone: +x is zeroed, y and z slide along.
    out, (rec,) = gov(state_of(((0.17, 0.0, 0.9), (0, 0, 0))), a)
    assert out == (0.0, 1.0, -1.0, 0.0, 0.0, 0.0, 0.5)
    assert rec.constraint == "forbidden_zone" and "zone 0" in rec.reason
    # Beyond the margin nothing happens.
    assert gov(state_of(((0.1, 0.0, 0.9), (0, 0, 0))), a) == (a, ())
    # Inside the zone, below its centre on x and z, above it on y: only moves away from the centre remain.
    out, _ = gov(state_of(((0.25, 0.05, 0.85), (0, 0, 0))), (1.0, -1.0, 1.0, 0, 0, 0, 0))
    assert out[:3] == (0.0, 0.0, 0.0)
    out, _ = gov(state_of(((0.25, 0.05, 0.85), (0, 0, 0))), (-1.0, 1.0, -1.0, 0, 0, 0, 0))
    assert out[:3] == (-1.0, 1.0, -1.0)


def test_forbidden_zone_rejects_a_non_finite_position() -> None:
    gov = Phi((ZONE,)).governor(SINGLE_PANDA)
    out, (rec,) = gov(state_of(((0.3, math.nan, 0.9), (0, 0, 0))), (0.0,) * 7)
    assert out is None and rec.constraint == "forbidden_zone"
    assert rec.reason == "arm 0: end-effector position (0.3, nan, 0.9) is not finite"


def test_box_examples_at_each_face_and_outside() -> None:
    gov = Phi((WorkspaceBox(),)).governor(SINGLE_PANDA)
    push = (1.0, 1.0, 1.0, 0.3, 0.3, 0.3, -1.0)
    pull = (*(-x for x in push[:6]), -1.0)
    # Within 8 cm of the +x, +y, +z faces: outward zeroed, rotation and gripper kept; inward allowed.
    out, (rec,) = gov(state_of(((0.55, 0.53, 1.25), (0, 0, 0))), push)
    assert out == (0.0, 0.0, 0.0, 0.3, 0.3, 0.3, -1.0)
    assert rec.constraint == "workspace_box" and rec.original == push and rec.result == out
    assert "+x face" in rec.reason and "+y face" in rec.reason and "+z face" in rec.reason
    assert gov(state_of(((0.55, 0.53, 1.25), (0, 0, 0))), pull) == (pull, ())
    # Already outside below z: further -z is zeroed too; x, y free (9 cm from their faces).
    out, _ = gov(state_of(((0.0, 0.0, 0.5), (0, 0, 0))), pull)
    assert out == (-1.0, -1.0, 0.0, -0.3, -0.3, -0.3, -1.0)
    # Exactly on the margin boundary counts as within it.
    out, _ = gov(state_of(((0.6 - 0.08, 0.0, 1.0), (0, 0, 0))), push)
    assert out[0] == 0.0


def test_contact_force_examples_table_and_oblique() -> None:
    gov = Phi((ContactForce(),)).governor(SINGLE_PANDA)
    table = ((0.0, 0.0, 0.9), (0.0, 0.0, 30.0))  # the table pushes up with 30 N
    out, (rec,) = gov(state_of(table), (0.5, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0))
    assert out == (0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert rec.reason == "arm 0: contact force above 20.0 N: motion into the contact along z zeroed"
    lift = (0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    assert gov(state_of(table), lift) == (lift, ())  # moving away from the contact is free
    assert gov(state_of(((0, 0, 0.9), (0.0, 0.0, 20.0))), (0, 0, -1.0, 0, 0, 0, 0))[1] == ()  # at the limit: allowed
    oblique = ((0, 0, 0.9), (-15.0, 0.0, 15.0))  # a wall ahead in +x and a table below
    out, _ = gov(state_of(oblique), (1.0, 0.3, -1.0, 0, 0, 0, 0))
    assert out[:3] == (0.0, 0.3, 0.0)


def test_velocity_cap_examples() -> None:
    gov = Phi((VelocityCap(),)).governor(SINGLE_PANDA)
    st_ = state_of(((0, 0, 1), (0, 0, 0)))
    out, (rec,) = gov(st_, (2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 7.0))
    assert out == (1.5 * SHRINK, 0.0, 0.0, 0.0, 0.0, 0.0, 7.0)
    assert rec.reason == "arm 0: pose-delta norm above the cap 1.5: scaled down to it"
    out, _ = gov(st_, (1.2e308,) * 6 + (0.0,))  # squares overflow; the result still points the same way
    assert all(x == pytest.approx(1.5 * SHRINK / math.sqrt(6)) for x in out[:6])
    ok = (1.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # exactly at the cap: allowed
    assert gov(st_, ok) == (ok, ())


def test_two_arm_layout_governs_each_arm_on_its_own_slice() -> None:
    gov = Phi.default().governor(TWO_ARM_NO_GRIPPER)
    arm0 = ((0.55, 0.0, 1.0), (0.0, 0.0, 0.0))  # near +x
    arm1 = ((0.0, 0.0, 0.9), (0.0, 0.0, 50.0))  # pressing on the table
    action = (1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0)
    out, records = gov(state_of(arm0, arm1), action)
    assert out == (0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert [r.constraint for r in records] == ["workspace_box", "contact_force"]
    assert "arm 0" in records[0].reason and "arm 1" in records[1].reason
    out, (rec,) = gov(state_of(((0, 0, 1), (0, 0, 0)), ((0, 0, 1), (0, 0, 0))), (0.0,) * 6 + (2.0,) + (0.0,) * 5)
    assert out[6] == pytest.approx(1.5) and out[:6] == (0.0,) * 6 and "arm 1" in rec.reason


def test_rotated_frame_maps_world_faces_to_base_frame_components() -> None:
    # Robot 0 of TwoArmPegInHole: base turned +90° about z, so action +y points along world -x.
    gov = Phi((WorkspaceBox(),)).governor(TWO_ARM_NO_GRIPPER, frames=[RZ90, RZ_90])
    near_minus_x = ((-0.55, 0.0, 1.0), (0, 0, 0))
    near_plus_x = ((0.55, 0.0, 1.0), (0, 0, 0))
    action = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0) * 2
    out, records = gov(state_of(near_minus_x, near_plus_x), action)
    # Arm 0: action +y = world -x (outward at -x): zeroed. Arm 1 (turned -90°): action +y = world +x: zeroed.
    assert out == (0.0,) * 12
    assert records[0].original == action
    out, records = gov(state_of(near_plus_x, near_minus_x), action)
    assert (out, records) == (action, ())  # both move inward
    assert to_world(action, TWO_ARM_NO_GRIPPER, [RZ90, RZ_90])[:3] == [-1.0, 0.0, 0.0]


@settings(max_examples=300, deadline=None)
@given(
    state=robot_states(1),
    action=actions(7, ANY_FLOAT),
    where=st.integers(0, 6),
    bad=st.sampled_from([math.nan, math.inf, -math.inf]),
)
def test_non_finite_actions_are_rejected_with_a_reason(state, action, where, bad) -> None:
    action[where] = bad
    for layout_action in (action, tuple(action), np.array(action)):
        out, records = Phi.default().governor(SINGLE_PANDA)(state, layout_action)
        assert out is None
        (rec,) = records
        assert rec.constraint == "governor" and rec.result is None
        bad = [k for k, x in enumerate(action) if not math.isfinite(x)]
        assert rec.reason == f"action components {bad} are not finite numbers"


@settings(max_examples=300, deadline=None)
@given(
    values=st.lists(ANY_FLOAT, min_size=12, max_size=12),
    where=st.integers(0, 11),
    bad=st.sampled_from([math.nan, math.inf, -math.inf]),
    action=actions(12, st.floats(-2, 2)),
)
def test_non_finite_state_readings_are_rejected_by_the_default_phi(values, where, bad, action) -> None:
    values[where] = bad  # arm 0 pos, arm 0 force, arm 1 pos, arm 1 force
    v = values
    state = state_of((v[0:3], v[3:6]), (v[6:9], v[9:12]))
    out, records = Phi.default().governor(TWO_ARM_NO_GRIPPER)(state, action)
    assert out is None
    assert "is not finite" in records[-1].reason
    assert records[-1].constraint in ("workspace_box", "contact_force")
