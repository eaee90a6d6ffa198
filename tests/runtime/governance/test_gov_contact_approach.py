"""contact_approach and the proximity sensor: the predictive force rule for what a fixed Φ cannot know.

The constraint is tested on synthetic proximity pairs (examples, invariants by hypothesis, alone
and inside the per-task Φ); the sensor on a small real MuJoCo scene whose distances are known
in closed form (a sphere over a loose cube on a table, a small box, a loose can, a wall).
"""

from __future__ import annotations

import math
import struct
from typing import Any

import mujoco
import numpy as np
import pytest
from govcheck import violations
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import (
    TWO_ARM_NO_GRIPPER,
    ArmScene,
    ContactApproach,
    Phi,
    ProximitySensor,
    ReachLimit,
    load_phi,
    make,
    near_of,
)
from capevo.runtime.governance.brake import brake_along
from capevo.runtime.governance.cap import SHRINK
from capevo.runtime.governance.pose import DOWN
from capevo.runtime.governance.proximity import FIXED, LOOSE
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState
from capevo.runtime.tasks import task_spec

TOL = 1e-9
RULE = ContactApproach()


def scene(pos: tuple[float, float, float], *pairs: tuple[float, ...]) -> ArmScene:
    return ArmScene(eef_pos=pos, eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=tuple(pairs))


def pair(dist: float, n: tuple[float, float, float], owner: int = FIXED, r: tuple[float, ...] = (0.0, 0.0, 0.0)):
    norm = math.sqrt(sum(x * x for x in n))
    return (dist, *(x / norm for x in n), *r, owner)


def govern(rule: Any, state: RobotState, action: list[float], layout: Any = SINGLE_PANDA) -> Any:
    return Phi((rule,)).governor(layout)(state, action)


# ---------------------------------------------------------------- config


def test_config_round_trips_and_bad_values_name_their_field() -> None:
    phi = Phi((ContactApproach(brake_loose=0.05, touch_loose=0.1),))
    assert load_phi(phi.to_yaml()) == phi
    assert make("contact_approach", brake=0.08) == ContactApproach(brake=0.08)
    for field, value, message in [
        ("clearance", -0.1, "clearance: must be >= 0, got -0.1"),
        ("brake", 0.0, "brake: must be > 0, got 0.0"),
        ("touch", 1.5, "touch: must be in [0, 1], got 1.5"),
        ("touch_loose", -0.1, "touch_loose: must be in [0, 1], got -0.1"),
        ("brake_loose", 0.0, "brake_loose: must be > 0, got 0.0"),
        ("lever", 0.0, "lever: must be > 0, got 0.0"),
        ("touch_arm", 1.01, "touch_arm: must be in [0, 1], got 1.01"),
        ("touch_rotation", -0.5, "touch_rotation: must be in [0, 1], got -0.5"),
    ]:
        with pytest.raises(Invalid) as e:
            ContactApproach(**{field: value})
        assert e.value.code is ErrorCode.INVALID
        assert e.value.message == message and e.value.details["field"] == field


def test_bound_ramps_from_the_touch_speed_at_the_clearance_to_full_speed() -> None:
    assert RULE.bound(-0.01) == RULE.touch == RULE.bound(RULE.clearance)
    assert RULE.bound(RULE.clearance + RULE.brake / 2) == pytest.approx(RULE.touch + (1 - RULE.touch) / 2)
    assert RULE.bound(RULE.clearance + RULE.brake) == 1.0 == RULE.bound(1.0)
    loose = ContactApproach(touch_loose=0.2, brake_loose=0.05)
    assert loose.bound(0.0, LOOSE) == 0.2 and loose.bound(0.0, FIXED) == loose.touch
    assert loose.bound(0.03, LOOSE) == pytest.approx(0.2 + 0.8 * 0.5)


# ---------------------------------------------------------------- examples


def test_motion_straight_at_a_near_pair_is_slowed_to_its_bound() -> None:
    state = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(0.055, (0.0, 0.0, -1.0))),))
    out, records = govern(RULE, state, [0.3, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0])
    q = RULE.bound(0.055)
    assert out[2] == pytest.approx(-q) and out[0] == 0.3 and out[6] == 1.0
    assert records[0].constraint == "contact_approach"
    assert records[0].reason == "arm 0: hand near a contact: motion towards it braked"


def test_receding_and_tangential_motion_is_left_alone() -> None:
    state = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(0.0, (0.0, 0.0, -1.0))),))
    action = [1.0, -1.0, 0.5, 0.0, 0.0, 0.0, -1.0]
    out, records = govern(RULE, state, action)
    assert out is action and records == ()


def test_an_oblique_pair_removes_the_closing_motion_along_its_direction() -> None:
    state = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(0.0, (1.0, 0.0, -1.0))),))
    out, _ = govern(RULE, state, [0.8, 0.5, -0.4, 0.0, 0.0, 0.0, 0.0])
    n = 1 / math.sqrt(2)
    # Least change: both approaching components lose the same multiple of n; z reaches 0
    # first and stops there, x carries the rest of the bound; y (tangential) is untouched.
    assert out[2] == 0.0 and out[1] == 0.5
    assert 0.0 < out[0] < 0.8
    assert out[0] * n == pytest.approx(RULE.touch)


UNIT = st.floats(-1.0, 1.0, allow_nan=False)


@given(a=st.lists(UNIT, min_size=3, max_size=3), n=st.lists(UNIT, min_size=3, max_size=3), q=st.floats(0.0, 1.0))
def test_brake_along_is_the_least_change_that_meets_the_bound(a: list[float], n: list[float], q: float) -> None:
    norm = math.sqrt(sum(x * x for x in n))
    assume(norm > 1e-3)
    n = [x / norm for x in n]
    axes = tuple(enumerate(n))
    out = list(a)
    brake_along(out, axes, q)
    closing = sum(max(0.0, out[k] * n[k]) for k in range(3))
    assert closing <= q + 1e-9
    for k in range(3):
        if a[k] * n[k] > 0.0:  # approaching: shrunk towards 0, never flipped
            assert 0.0 <= out[k] / a[k] <= 1.0 if a[k] else out[k] == 0.0
        else:
            assert out[k] == a[k]
    # No larger a change than scaling the approaching components by one factor to the same
    # target, q * SHRINK: brake_along aims that far below the bound so rounding cannot cross it
    # (with a parallel to n the two changes are equal, and scaling to q itself would be smaller).
    c = sum(max(0.0, a[k] * n[k]) for k in range(3))
    f = min(1.0, q * SHRINK / c) if c > 0 else 1.0
    scaled = [a[k] * f if a[k] * n[k] > 0 else a[k] for k in range(3)]
    assert math.dist(out, a) <= math.dist(scaled, a) + 1e-9


def test_motion_past_a_pair_that_points_mostly_sideways_keeps_its_speed() -> None:
    # A finger descending beside a cube: the pair points mostly sideways, a little down.
    side = pair(0.006, (-0.96, 0.0, -0.27))
    state = RobotState(arms=(scene((0.0, 0.0, 1.0), side),))
    action = [-0.2, 0.1, -0.3, 0.0, 0.0, 0.0, 1.0]
    out, _ = govern(RULE, state, action)
    n = side[1:4]
    q = RULE.bound(0.006)
    closing = sum(max(0.0, out[k] * n[k]) for k in range(3))
    assert closing == pytest.approx(q, rel=1e-6)
    # Scaling both approaching components by one factor would leave z at -0.3 * q / 0.273;
    # removing the motion along n keeps most of the descent.
    one_factor = -0.3 * q / (0.2 * 0.96 + 0.3 * 0.27)
    assert out[2] < 2 * one_factor < 0.0
    assert out[0] <= 0.0 and out[1] == 0.1


def test_pairs_beyond_the_band_and_states_without_pairs_are_ignored() -> None:
    action = [1.0, 1.0, -1.0, 1.0, 1.0, 1.0, 1.0]
    far = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(RULE.clearance + RULE.brake, (0.0, 0.0, -1.0))),))
    plain = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)),))
    for state in (far, plain):
        out, records = govern(RULE, state, action)
        assert out is action and records == ()


def test_a_loose_object_slides_sideways_but_is_pinned_when_pushed_down() -> None:
    rule = ContactApproach(touch_loose=0.2)
    side = [1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0]
    # A loose object beside and below the hand (n mostly +x, a little down).
    loose = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(0.0, (0.8, 0.0, -0.6), LOOSE)),))
    fixed = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(0.0, (0.8, 0.0, -0.6), FIXED)),))
    out, _ = govern(rule, loose, side)
    assert out[0] * 0.8 == pytest.approx(0.2)  # sideways: the loose touch speed
    assert out[2] * -0.6 == pytest.approx(rule.touch)  # downwards: the fixed scene's
    out, _ = govern(rule, fixed, side)
    assert out[0] * 0.8 + out[2] * -0.6 == pytest.approx(rule.touch)
    # Below the hand's level (n_z > 0: the object is above), a loose pair is one closing sum.
    above = RobotState(arms=(scene((0.0, 0.0, 1.0), pair(0.0, (0.0, 0.0, 1.0), LOOSE)),))
    assert govern(rule, above, [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0])[0][2] == pytest.approx(0.2)


def test_rotation_is_limited_the_more_the_farther_the_pair_is_from_the_site() -> None:
    turn = [0.0, 0.0, 0.0, 1.0, -1.0, 0.5, 0.0]
    near_site = RobotState(arms=(scene((0, 0, 1), pair(0.0, (0.0, 0.0, -1.0), r=(0.0, 0.0, 0.05))),))
    far_out = RobotState(arms=(scene((0, 0, 1), pair(0.0, (0.0, 0.0, -1.0), r=(0.0, 0.0, 0.4))),))
    a, _ = govern(RULE, near_site, turn)
    b, _ = govern(RULE, far_out, turn)
    assert a[3:6] == pytest.approx((RULE.touch, -RULE.touch, RULE.touch))
    assert b[3:6] == pytest.approx((RULE.touch / 4, -RULE.touch / 4, RULE.touch / 4))
    assert govern(ContactApproach(rotation=False), near_site, turn)[0] is turn


def test_a_pair_with_the_other_arm_slows_both_arms() -> None:
    # Arm 0's hand is 1 cm from a link of arm 1, which lies towards +y.
    arm0 = scene((0.0, -0.1, 1.0), pair(0.01, (0.0, 1.0, 0.0), owner=1))
    arm1 = scene((0.0, 0.1, 1.0))
    state = RobotState(arms=(arm0, arm1))
    out, _ = govern(RULE, state, [0.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.0, -1.0, 0.0, 0.3, 0.0, 0.0], TWO_ARM_NO_GRIPPER)
    q = RULE.bound(0.01)
    assert out[1] == pytest.approx(q) and out[7] == pytest.approx(-q)
    assert out[5] == pytest.approx(q) and out[9] == pytest.approx(q)
    away, _ = govern(RULE, state, [0.0, -1.0, 0.0, 0, 0, 0, 0.0, 1.0, 0.0, 0, 0, 0], TWO_ARM_NO_GRIPPER)
    assert away[1] == -1.0 and away[7] == 1.0


def test_another_arm_and_turning_get_their_own_floor_at_the_clearance() -> None:
    rule = ContactApproach(touch=0.04, touch_arm=0.01, touch_rotation=0.01)
    arm0 = scene((0.0, -0.1, 1.0), pair(0.0, (0.0, 1.0, 0.0), owner=1), pair(0.0, (0.0, 0.0, -1.0)))
    state = RobotState(arms=(arm0, scene((0.0, 0.1, 1.0))))
    push = [0.0, 1.0, -1.0, 0.5, -0.5, 0.5, 0.0, -1.0, 0.0, 0.5, 0.5, 0.5]
    out, _ = govern(rule, state, push, TWO_ARM_NO_GRIPPER)
    # towards the other arm at touch_arm, both sides; down onto the fixed scene at touch
    assert out[1] == pytest.approx(0.01) and out[7] == pytest.approx(-0.01)
    assert out[2] == pytest.approx(-0.04)
    # turning at touch_rotation on both arms, below both translation floors
    assert out[3:6] == pytest.approx((0.01, -0.01, 0.01)) and out[9:12] == pytest.approx((0.01, 0.01, 0.01))
    # half-way through the band every floor has ramped half-way to full speed
    half = ContactApproach(touch_rotation=0.0).rotation_bound(0.005 + 0.05)
    assert half == pytest.approx(0.5)
    assert ContactApproach().rotation_bound(0.0) == math.inf


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_pair_is_rejected(bad: float) -> None:
    state = RobotState(arms=(scene((0.0, 0.0, 1.0), (bad, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, FIXED)),))
    out, records = govern(RULE, state, [0.0] * 7)
    assert out is None and records[-1].constraint == "contact_approach"
    assert records[-1].reason.startswith("arm 0: proximity pair (")


# ---------------------------------------------------------------- invariants


UNIT = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: sum(x * x for x in v) > 0.1)
PAIRS = st.builds(
    lambda d, n, r, owner: pair(d, n, owner, r),
    st.one_of(st.floats(-0.02, 0.12), st.sampled_from([0.0, 0.005, 0.105])),
    UNIT,
    st.tuples(*[st.floats(-0.3, 0.3)] * 3),
    st.sampled_from([FIXED, LOOSE, 0, 1]),
)
RULES = st.builds(
    ContactApproach,
    clearance=st.floats(0.0, 0.02),
    brake=st.floats(0.01, 0.2),
    touch=st.floats(0.0, 1.0),
    touch_loose=st.floats(0.0, 1.0),
    brake_loose=st.one_of(st.none(), st.floats(0.01, 0.2)),
    touch_arm=st.one_of(st.none(), st.floats(0.0, 1.0)),
    rotation=st.booleans(),
    touch_rotation=st.one_of(st.none(), st.floats(0.0, 1.0)),
)
COMPONENT = st.one_of(st.floats(-3.0, 3.0), st.sampled_from([0.0, 1.0, -1.0]))


@settings(max_examples=300, deadline=None)
@given(rule=RULES, data=st.data())
def test_alone_any_action_ends_within_every_pairs_bound(rule: ContactApproach, data: st.DataObject) -> None:
    two = data.draw(st.booleans())
    layout = TWO_ARM_NO_GRIPPER if two else SINGLE_PANDA
    arms = tuple(scene((0.0, 0.0, 1.0), *data.draw(st.lists(PAIRS, max_size=4))) for _ in range(2 if two else 1))
    state = RobotState(arms=arms)
    action = data.draw(st.lists(COMPONENT, min_size=layout.dim, max_size=layout.dim))
    out, records = govern(rule, state, action, layout)
    assert violations(Phi((rule,)), layout, state, out, tol=TOL) == []
    assert (out is action) == (not records)
    for x, y in zip(action, out, strict=True):
        assert abs(y) <= abs(x) and (y == 0.0 or (x > 0) == (y > 0))


def reference(rule: ContactApproach, arms: Any, a: list[float], layout: Any) -> Any:
    """The rule as its docstring states it, pair by pair through ``bound`` and ``brake_along``:
    the compiled check inlines both and skips what a met bound makes moot, and must agree to the bit."""
    band = rule.clearance + max(rule.brake, rule.brake_loose or 0.0)
    offsets = [arm.offset for arm in layout.arms]
    n = len(offsets)
    poses = [[a[o + j] for j in range(6)] for o in offsets]
    q_rot = [math.inf] * n
    for i in range(n):
        for p in near_of(arms[i]):
            dist, nx, ny, nz, rx, ry, rz, owner = p
            if not all(math.isfinite(v) for v in (dist, nx, ny, nz)):
                return None, f"arm {i}: proximity pair {p} is not finite"
            if dist >= band:
                continue
            q = rule.bound(dist, owner)
            q_down = rule.bound(dist, FIXED) if owner == LOOSE and nz < 0.0 else q
            if q >= 1.0 and q_down >= 1.0:
                continue
            arm = poses[i]
            if q_down < q:
                if arm[2] * nz > q_down:
                    arm[2] = q_down / nz * SHRINK
                brake_along(arm, ((0, nx), (1, ny)), q)
            else:
                brake_along(arm, ((0, nx), (1, ny), (2, nz)), q)
            q = min(q, q_down)
            q_turn = min(q, rule.rotation_bound(dist))
            if rule.rotation:
                r = math.sqrt(rx * rx + ry * ry + rz * rz) if math.isfinite(rx + ry + rz) else math.inf
                q_rot[i] = min(q_rot[i], q_turn * (rule.lever / r if r > rule.lever else 1.0))
            if 0 <= owner < n and owner != i:
                brake_along(poses[owner], ((0, nx), (1, ny), (2, nz)), q, sign=-1.0)
                if rule.rotation:
                    q_rot[owner] = min(q_rot[owner], q_turn)
    b, notes = None, []
    for i, o in enumerate(offsets):
        arm = poses[i]
        for k in (3, 4, 5):
            if abs(arm[k]) > q_rot[i]:
                arm[k] = q_rot[i] if arm[k] > 0.0 else -q_rot[i]
        if any(arm[j] != a[o + j] for j in range(6)):
            b = list(a) if b is None else b
            b[o : o + 6] = arm
            notes.append(f"arm {i}: hand near a contact: motion towards it braked")
    return None if b is None else (b, "; ".join(notes))


def bits(x: Any) -> Any:
    """``x`` with every float as its bytes: equal exactly when equal to the bit (-0.0 is not 0.0)."""
    if isinstance(x, float):
        return struct.pack("<d", x)
    if isinstance(x, (tuple, list)):
        return type(x)(bits(v) for v in x)
    return x


NEAR_EDGE = st.one_of(
    PAIRS, st.sampled_from([(0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, LOOSE), (math.nan, *[0.0] * 6, FIXED)])
)


@settings(max_examples=500, deadline=None)
@given(rule=RULES, data=st.data())
def test_the_compiled_check_agrees_with_the_reference_rule_to_the_bit(
    rule: ContactApproach, data: st.DataObject
) -> None:
    two = data.draw(st.booleans())
    layout = TWO_ARM_NO_GRIPPER if two else SINGLE_PANDA
    arms = tuple(scene((0.0, 0.0, 1.0), *data.draw(st.lists(NEAR_EDGE, max_size=6))) for _ in range(2 if two else 1))
    action = data.draw(st.lists(COMPONENT, min_size=layout.dim, max_size=layout.dim))
    assert bits(rule.compile(layout)(arms, action)) == bits(reference(rule, arms, action, layout))


@pytest.mark.parametrize("task", ["T1", "T3", "T4"])
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_inside_the_task_phi_every_rule_holds_at_once_where_nothing_restores(task: str, data: st.DataObject) -> None:
    phi = Phi.for_task(task_spec(task))
    reach = next(c for c in phi.constraints if isinstance(c, ReachLimit))
    c = reach.centres[0]
    # Well inside the reach and out of the column and the box's margins: no restoring edit fires.
    p = (c[0] + data.draw(st.floats(0.4, 0.55)), data.draw(st.floats(-0.3, 0.3)), data.draw(st.floats(0.85, 1.1)))
    assume(abs(p[1]) < 0.45)
    f = data.draw(st.tuples(*[st.floats(-11.0, 11.0)] * 3))
    arm = ArmScene(eef_pos=p, eef_force=f, eef_rot=DOWN, near=tuple(data.draw(st.lists(PAIRS, max_size=4))))
    state = RobotState(arms=(arm,))
    action = data.draw(st.lists(COMPONENT, min_size=7, max_size=7))
    out, _ = phi.governor(SINGLE_PANDA)(state, action)
    assert violations(phi, SINGLE_PANDA, state, out, tol=TOL) == []


def test_the_task_phi_adds_contact_approach_before_the_cap() -> None:
    for task in ("T1", "T2", "T3", "T4", "T5", "T6"):
        phi = Phi.for_task(task_spec(task))
        assert phi == Phi.for_task(task_spec(task))
        labels = phi.labels
        assert "contact_approach" in labels and labels[-1] == "velocity_cap"
        assert labels[:2] == ("workspace_box", "contact_force")
    rule = next(c for c in Phi.for_task(task_spec("T3")).constraints if isinstance(c, ContactApproach))
    assert rule == ContactApproach(
        clearance=0.005, brake=0.1, touch=0.04, touch_loose=0.04, touch_arm=0.01, touch_rotation=0.01
    )


def test_reach_creep_leaves_a_slow_outward_motion_up_to_the_edge_only() -> None:
    reach = ReachLimit(centres=((0.0, 0.0, 1.0),), max_radius=0.8, margin=0.01, brake=0.05, creep=0.05)
    gov = Phi((reach,)).governor(SINGLE_PANDA)
    out = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    inside_margin = RobotState(arms=(ArmState(eef_pos=(0.795, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)),))
    in_band = RobotState(arms=(ArmState(eef_pos=(0.77, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)),))
    beyond = RobotState(arms=(ArmState(eef_pos=(0.81, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)),))
    assert gov(inside_margin, out)[0][0] == pytest.approx(0.05)  # no creep: 0
    assert gov(in_band, out)[0][0] == pytest.approx(0.4)  # (0.03 - 0.01) / 0.05, above the creep
    assert gov(beyond, out)[0][0] == pytest.approx(-reach.restore)  # past the edge: steered back
    with pytest.raises(Invalid) as e:
        ReachLimit(centres=((0.0, 0.0, 1.0),), max_radius=0.8, creep=1.5)
    assert e.value.message == "creep: must be in [0, 1], got 1.5" and e.value.details["field"] == "creep"


# ---------------------------------------------------------------- the sensor, on a real MuJoCo scene

SCENE = """
<mujoco>
  <worldbody>
    <geom name="table" type="box" size="0.5 0.5 0.02" pos="0 0 0.8"/>
    <geom name="wall" type="box" size="0.01 0.2 0.1" pos="0.4 0 0.9"/>
    <body name="arm" pos="0 0 1.2">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <geom name="link" type="capsule" size="0.02" fromto="0 0 0 0 0 0.2"/>
      <body name="hand">
        <geom name="palm" type="sphere" size="0.02"/>
        <geom name="pad" type="box" size="0.005 0.005 0.005" pos="0.05 0 0"/>
        <site name="eef" pos="0 0 -0.01"/>
      </body>
    </body>
    <body name="cube" pos="0 0 0.84">
      <freejoint/>
      <geom name="cube" type="box" size="0.02 0.02 0.02"/>
    </body>
    <body name="can" pos="0.15 0 0.87">
      <freejoint/>
      <geom name="can" type="cylinder" size="0.03 0.05"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture()
def world() -> Any:
    model = mujoco.MjModel.from_xml_string(SCENE)
    data = mujoco.MjData(model)

    def place(x: float, z: float) -> ProximitySensor:
        data.qpos[0], data.qpos[1] = x, z
        mujoco.mj_forward(model, data)
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "hand")
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "eef")
        return ProximitySensor(model, data, [body], [site])

    return model, data, place


def _by_distance(pairs: tuple) -> list[tuple]:
    return sorted(pairs)


def test_sensor_reports_nothing_far_from_everything(world: Any) -> None:
    _, _, place = world
    assert place(0.0, 0.0).near(0) == ()


def test_sensor_finds_the_loose_cube_below_the_palm_exactly(world: Any) -> None:
    _, _, place = world
    sensor = place(0.0, -0.3)  # palm centre at z 0.9, 2 cm above the cube's top (0.86)
    pairs = sensor.near(0)
    cube = [p for p in pairs if p[7] == LOOSE and abs(p[1]) < 1e-6 and p[3] < -0.99]
    assert cube, pairs
    dist, nx, ny, nz, rx, ry, rz, _ = min(cube)
    assert dist == pytest.approx(0.02, abs=1e-6)
    assert (nx, ny, nz) == pytest.approx((0.0, 0.0, -1.0), abs=1e-6)
    assert (rx, ry, rz) == pytest.approx((0.0, 0.0, -0.01), abs=1e-6)  # palm bottom, 1 cm under the site
    # The can's side (x 0.12) is 6.5 cm from the pad and 10 cm from the palm, along +x.
    can = sorted(p for p in pairs if p[7] == LOOSE and p[1] > 0.99)
    assert [p[0] for p in can] == pytest.approx([0.065, 0.1], abs=1e-4)
    assert all(p[0] < sensor.reach for p in pairs)
    assert not any(p[7] == 0 for p in pairs)  # nothing of the arm's own chain (the link capsule)


def test_box_pairs_are_bounded_from_below_by_a_sphere(world: Any) -> None:
    _, _, place = world
    sensor = place(0.0, -0.3)
    # pad (box, 5 mm half size) at (0.05, 0, 0.9) vs the cube (box): 2.5 cm apart in x, 3.5 cm in z.
    pad = sensor._sphere_to_box(
        mujoco.mj_name2id(sensor.model, mujoco.mjtObj.mjOBJ_GEOM, "pad"),
        mujoco.mj_name2id(sensor.model, mujoco.mjtObj.mjOBJ_GEOM, "cube"),
    )
    assert pad is not None
    assert pad[0] == pytest.approx(math.hypot(0.03, 0.04) - math.sqrt(3) * 0.005, abs=1e-9)
    assert pad[0] <= math.hypot(0.025, 0.035)  # a lower bound on the true distance


def test_a_pad_beside_a_cube_is_measured_across_the_face_it_faces(world: Any) -> None:
    _, _, place = world
    # The pad (5 mm half size) 1 cm beside the cube's -x face, its bottom 2 cm above the table and
    # its top 0.5 cm above the cube's: the separation across the face is exact, and points along x.
    sensor = place(-0.085, -0.355)
    pairs = sensor.near(0)
    cube = sorted(p for p in pairs if p[7] == LOOSE and p[1] > 0.99)
    assert [p[0] for p in cube] == pytest.approx([0.01, 0.045], abs=1e-9)  # pad, palm
    assert cube[0][1:4] == pytest.approx((1.0, 0.0, 0.0), abs=1e-9)
    pad, box = (mujoco.mj_name2id(sensor.model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("pad", "cube"))
    sphere = sensor._sphere_to_box(pad, box)
    assert sphere is not None and sphere[0] < 0.01 - 0.003  # the sphere alone says less, diagonally
    # So motion down past the cube is not braked by it, motion towards it is.
    state = RobotState(arms=(scene((-0.085, 0.0, 0.835), *cube),))
    down, _ = govern(RULE, state, [0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0])
    towards, _ = govern(RULE, state, [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert down == [0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0]
    assert towards[0] == pytest.approx(RULE.bound(0.01))


def test_the_reach_limit_brakes_the_outward_part_only() -> None:
    # At full stretch with the wrist 15 cm below the shoulder, lowering the hand is mostly motion
    # along the reach sphere: it keeps most of its speed, while the outward part is held to the creep.
    reach = ReachLimit(centres=((0.0, 0.0, 1.0),), max_radius=0.8, margin=0.01, brake=0.05, creep=0.25)
    gov = Phi((reach,)).governor(SINGLE_PANDA)
    p = (0.78, 0.0, 0.846)
    r = math.hypot(p[0], p[2] - 1.0)
    u = (p[0] / r, 0.0, (p[2] - 1.0) / r)
    state = RobotState(arms=(ArmState(eef_pos=p, eef_force=(0.0, 0.0, 0.0)),))
    lower = [0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0]
    assert gov(state, lower)[0] is lower  # outward speed 0.19: under the creep
    out = gov(state, [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])[0]
    assert out[0] * u[0] == pytest.approx(reach.creep)
    both = gov(state, [1.0, 0.5, -1.0, 0.0, 0.0, 0.0, 0.0])[0]
    assert both[0] * u[0] + both[2] * u[2] == pytest.approx(reach.creep)
    assert both[1] == 0.5 and both[2] < -0.8 and 0.0 < both[0] < 0.1


def test_a_touched_loose_object_becomes_part_of_the_hand(world: Any) -> None:
    model, _, place = world
    sensor = place(0.0, -0.3 - 0.021)  # the palm pressed 1 mm into the cube's top
    cube_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "cube")
    assert sensor.held(0) == (cube_body,)
    pairs = sensor.near(0)
    # No palm-to-cube pair any more; the cube's own pair with the table it rests on is there instead.
    assert not any(p[7] == LOOSE and p[3] < -0.99 and abs(p[1]) < 1e-6 and p[0] < 0.0 for p in pairs)
    table = [p for p in pairs if p[7] == FIXED and p[3] < -0.99]
    assert table and min(table)[0] < 0.005


def test_near_of_reads_pairs_only_from_scene_states() -> None:
    assert near_of(ArmState(eef_pos=(0, 0, 0), eef_force=(0, 0, 0))) == ()
    assert near_of(scene((0, 0, 0), pair(0.01, (0, 0, -1)))) == (pair(0.01, (0, 0, -1)),)


# ---------------------------------------------------------------- real robosuite: a loose cube


@pytest.mark.slow
def test_a_constant_push_into_a_loose_cube_is_contained() -> None:
    # T3 stack: the hand brought 9 cm beside cube A at its height, then a constant full-speed
    # push sideways through it. The paper's envelope alone strikes it (and what it is shoved
    # against) over the force limit; the task's envelope slows the hand before the contact.
    from capevo.runtime.episode import make_governor
    from capevo.runtime.governance import hold_action, is_unsafe
    from capevo.runtime.tasks import Perturbations, make_task

    env = make_task("T3", seed=0, perturbations=Perturbations.none(), terminate_on_success=False)
    try:
        layout = env.task_spec.action_layout
        results = {}
        for name, phi in (("task", Phi.for_task(task_spec("T3"))), ("paper", Phi.default())):
            env.reset(seed=0)
            govern_ = make_governor(env, phi)
            cube = np.asarray(env.obs_dict["cubeA_pos"], dtype=np.float64).copy()
            side = 1.0 if cube[1] >= 0 else -1.0
            unsafe, max_force, last = 0, 0.0, None
            for t in range(80):
                eef = np.asarray(env.obs_dict["robot0_eef_pos"], dtype=np.float64)
                if t < 35:
                    move = np.clip((cube + np.array([0.0, -side * 0.09, 0.01]) - eef) * 10.0, -1.0, 1.0)
                else:
                    move = np.array([0.0, side, 0.0])
                state = env.robot_state()
                out, _ = govern_(state, np.array([*move, 0.0, 0.0, 0.0, -1.0]))
                executed = hold_action(layout, last) if out is None else np.asarray(out, dtype=np.float64)
                unsafe += is_unsafe(state, executed, phi, layout)
                max_force = max(max_force, float(np.linalg.norm(state.arms[0].eef_force)))
                env.step(executed)
                last = executed
            results[name] = (unsafe, max_force)
        assert results["task"][0] == 0 and results["task"][1] <= 20.0, results
        assert results["paper"][0] > 0 and results["paper"][1] > 20.0, results
    finally:
        env.close()


ROWS = st.tuples(*[st.floats(-3.0, 3.0)] * 6)


@settings(max_examples=300, deadline=None)
@given(rule=RULES, data=st.data())
def test_a_link_pair_is_braked_along_its_row_translation_and_rotation_alike(
    rule: ContactApproach, data: st.DataObject
) -> None:
    """A pair whose hand side is a wrist link carries a row ``g`` (``link_motion``): after the
    check its closing speed ``Σ_{g_k a_k > 0} g_k a_k`` is within the pair's bound, and every
    component only shrinks towards 0."""
    pairs = data.draw(st.lists(PAIRS, min_size=1, max_size=4))
    linked = sorted(data.draw(st.sets(st.integers(0, len(pairs) - 1), min_size=1)))
    rows = tuple((k, data.draw(ROWS)) for k in linked)
    arm = ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=tuple(pairs), link_rows=rows)
    action = data.draw(st.lists(COMPONENT, min_size=7, max_size=7))
    out, _ = govern(rule, RobotState(arms=(arm,)), action)
    band = rule.clearance + max(rule.brake, rule.brake_loose or 0.0)
    for k, g in rows:
        dist, *_, owner = pairs[k]
        q = rule.bound(dist, owner)
        if dist < band and q < 1.0:
            closing = sum(max(0.0, gk * out[j]) for j, gk in enumerate(g))
            assert closing <= q + 1e-9, (k, g, out)
    for x, y in zip(action, out, strict=True):
        assert abs(y) <= abs(x) and (y == 0.0 or (x > 0) == (y > 0))


def test_a_link_pair_brakes_the_turn_that_drives_the_link_in() -> None:
    """The forearm case: the hand turns about x and moves clear, the row says the turn closes the
    forearm's pair; the turn is braked and the translation away from it kept."""
    link = pair(0.0, (0.0, 1.0, 0.0))  # at the clearance: the touch speed
    arm = ArmScene(
        eef_pos=(0.0, 0.0, 1.0),
        eef_force=(0.0, 0.0, 0.0),
        eef_rot=DOWN,
        near=(link,),
        link_rows=((0, (0.0, 0.65, 0.0, 1.07, -0.11, 0.14)),),
    )
    out, _ = govern(RULE, RobotState(arms=(arm,)), [0.0, -0.5, 0.0, 0.5, 0.0, 0.0, 1.0])
    assert out[1] == -0.5  # moving away along y: the row says it opens the gap
    assert 0.0 <= out[3] * 1.07 <= RULE.touch + 1e-12
