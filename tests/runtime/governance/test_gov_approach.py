"""Property tests for the speed-and-separation kinds: each governed action satisfies its rule.

Kinds: workspace_guard, force_ramp, surface_approach, obstacle_approach, arm_separation,
reach_limit, and the per-task Φ that combines them with the paper's envelope. The rules are
restated independently in :mod:`govcheck`.
"""

from __future__ import annotations

import math

import pytest
from govcheck import QUATS, arm_rot, hand_box, rotation, violations
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from capevo.errors import Invalid
from capevo.runtime.governance import (
    TWO_ARM_NO_GRIPPER,
    Aabb,
    ArmPose,
    ArmSeparation,
    ForceRamp,
    ObstacleApproach,
    Phi,
    ReachLimit,
    SurfaceApproach,
    VelocityCap,
    WorkspaceGuard,
)
from capevo.runtime.governance.hand import hand_extent, hand_reach, lowest_offset
from capevo.runtime.governance.obstacle import extent_of
from capevo.runtime.governance.task_phi import PANDA_HAND
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState
from capevo.runtime.tasks import task_spec

TOL = 1e-9
COORD = st.floats(-1.0, 2.0)
COMPONENT = st.one_of(st.floats(-3.0, 3.0), st.sampled_from([0.0, 1.0, -1.0]))


@st.composite
def arms(draw: st.DrawFn, pos: st.SearchStrategy[float] = COORD, force: float = 40.0) -> ArmState:
    p = (draw(pos), draw(pos), draw(pos))
    f = tuple(draw(st.floats(-force, force)) for _ in range(3))
    if draw(st.booleans()):
        return ArmPose(eef_pos=p, eef_force=f, eef_rot=rotation(draw(QUATS)))
    return ArmState(eef_pos=p, eef_force=f)


@st.composite
def in_reach(draw: st.DrawFn, centre: tuple[float, float, float], reach: ReachLimit) -> tuple[float, float, float]:
    """A point neither beyond ``reach``'s radius from ``centre`` nor inside its column, drawn without filtering."""
    theta = draw(st.floats(0.0, 2 * math.pi))
    rho = draw(st.floats(reach.min_radius + 1e-6, reach.max_radius - 1e-6))
    h = math.sqrt(max(0.0, reach.max_radius**2 - rho**2)) * 0.999
    dz = draw(st.floats(-h, h))
    return (centre[0] + rho * math.cos(theta), centre[1] + rho * math.sin(theta), centre[2] + dz)


def within_reach(reach: ReachLimit, i: int, arm: ArmPose) -> bool:
    """The limited point (the wrist, for the per-task Φ) is within the reach."""
    r, p, c = arm.eef_rot, arm.eef_pos, reach.centres[i]
    w = [p[k] + sum(r[3 * k + j] * reach.point[j] for j in range(3)) for k in range(3)]
    return math.dist(w, c) <= reach.max_radius


def states(n: int, **kw: object) -> st.SearchStrategy[RobotState]:
    return st.lists(arms(**kw), min_size=n, max_size=n).map(lambda a: RobotState(arms=tuple(a)))


def actions(dim: int) -> st.SearchStrategy[list[float]]:
    return st.lists(COMPONENT, min_size=dim, max_size=dim)


def unchanged_or_clamped(before: list[float], after: tuple[float, ...]) -> None:
    """Shrinking edits only: no component grows or flips sign."""
    for x, y in zip(before, after, strict=True):
        assert abs(y) <= abs(x) + TOL and (y == 0.0 or (x > 0) == (y > 0))


GUARD = WorkspaceGuard()
RAMP = ForceRamp()
SURFACE = SurfaceApproach(height=0.8, clearance=-0.004, hand=PANDA_HAND)
OBSTACLES = ObstacleApproach(
    boxes=(Aabb(low=(-0.11, -0.01, 0.8), high=(0.31, 0.01, 0.9)), Aabb(low=(0.2, 0.1, 0.75), high=(0.25, 0.15, 0.95))),
    hand=PANDA_HAND,
)
REACH = ReachLimit(centres=((-0.56, 0.0, 1.245),), max_radius=0.8, min_radius=0.25)
PEG = (Aabb(low=(-0.023, -0.023, 0.0), high=(0.023, 0.023, 0.26)),)
PLATE = (Aabb(low=(-0.01, -0.17, 0.0), high=(0.01, 0.17, 0.34)),)
SEPARATION = ArmSeparation(hands=(PEG, PLATE))


@pytest.mark.parametrize("constraint", [GUARD, RAMP, SURFACE, OBSTACLES, REACH], ids=lambda c: c.kind)
@settings(max_examples=300, deadline=None)
@given(state=states(1), action=actions(7))
def test_each_kind_alone_satisfies_its_rule_and_edits_minimally(constraint, state, action) -> None:
    phi = Phi((constraint,))
    out, records = phi.governor(SINGLE_PANDA)(state, action)
    assert out is not None
    assert violations(phi, SINGLE_PANDA, state, out, tol=TOL) == []
    assert out[6] == action[6]  # the gripper is never touched
    if not records:
        assert out is action
    else:
        assert list(out) != list(action)  # a record means a real change


@settings(max_examples=300, deadline=None)
@given(state=states(2, pos=st.floats(-0.6, 1.6)), action=actions(12))
def test_arm_separation_slows_every_approach_but_never_below_the_floor(state, action) -> None:
    phi = Phi((SEPARATION,))
    out, records = phi.governor(TWO_ARM_NO_GRIPPER)(state, action)
    assert violations(phi, TWO_ARM_NO_GRIPPER, state, out, tol=TOL) == []
    unchanged_or_clamped(action, out)
    for x, y in zip(action, out, strict=True):  # clamped to a bound of at least the floor
        assert y == x or abs(y) >= SEPARATION.floor - TOL
    assert (out is action) == (not records)


@pytest.mark.parametrize("constraint", [SURFACE, OBSTACLES, REACH, SEPARATION], ids=lambda c: c.kind)
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_shrinking_kinds_never_grow_or_flip_a_component(constraint, data) -> None:
    layout = TWO_ARM_NO_GRIPPER if constraint is SEPARATION else SINGLE_PANDA
    state = data.draw(states(len(layout.arms)))
    if constraint is REACH:  # stay clear of the restoring states (beyond the reach, inside the column)
        p = data.draw(in_reach(REACH.centres[0], REACH))
        state = RobotState(arms=(ArmState(eef_pos=p, eef_force=(0.0, 0.0, 0.0)),))
    action = data.draw(actions(layout.dim))
    out, _ = Phi((constraint,)).governor(layout)(state, action)
    unchanged_or_clamped(action, out)


@settings(max_examples=300, deadline=None)
@given(
    p=st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(0.3, 1.6)),
    action=actions(7),
    restore=st.floats(0.01, 0.6),
)
# within 1 cm of the floor face, moving fast along it: the cap scales the push (found by hypothesis)
@example(p=(0.0, 0.0, 0.609375), action=(0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0), restore=0.5)
# already pushing inward at exactly the restore speed: nothing changes, and the governor hands back
# the action it was given, a list here (found by hypothesis)
@example(p=(0.0, 0.0, 0.5), action=[0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0], restore=0.5)
def test_workspace_guard_steers_an_arm_outside_the_box_back_slowly(p, action, restore) -> None:
    guard = WorkspaceGuard(restore=restore)
    state = RobotState(arms=(ArmState(eef_pos=p, eef_force=(0.0, 0.0, 0.0)),))
    out, _ = Phi((guard, VelocityCap())).governor(SINGLE_PANDA)(state, action)
    outside = [
        (k, -1.0 if p[k] > guard.high[k] else 1.0) for k in range(3) if not guard.low[k] <= p[k] <= guard.high[k]
    ]
    if outside:
        for k, inward in outside:
            assert out[k] * inward >= restore - TOL
        assert all(abs(x) <= restore + TOL for x in out[:6])
        assert tuple(out[3:6]) == (0.0, 0.0, 0.0)  # frozen: outside is within the margin
    else:
        # the guard alone keeps its invariants, 7 included (within restore_within of a face,
        # steered back in proportion); the cap after it may scale a push down, never turn it
        alone, _ = Phi((guard,)).governor(SINGLE_PANDA)(state, action)
        assert violations(Phi((guard,)), SINGLE_PANDA, state, alone, tol=TOL) == []
        for k in range(3):
            for d, inward in ((guard.high[k] - p[k], -1.0), (p[k] - guard.low[k], 1.0)):
                if 0.0 <= d < guard.restore_within:
                    assert out[k] * inward > 0.0


def test_workspace_guard_examples() -> None:
    gov = Phi((WorkspaceGuard(),)).governor(SINGLE_PANDA)
    free = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)),))
    a = (1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 1.0)
    assert gov(free, a) == (a, ())
    # 13 cm under the ceiling: 5 cm into the 10 cm band above the 8 cm margin: up at most 0.5.
    band = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.17), eef_force=(0.0, 0.0, 0.0)),))
    out, (rec,) = gov(band, a)
    assert out[:3] == (1.0, 1.0, pytest.approx(0.5)) and out[3:] == a[3:]
    assert rec.constraint == "workspace_guard" and "braked" in rec.reason
    # 2 cm above the ceiling: pushed down at 0.2, everything else within +-0.2, no turning.
    above = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.32), eef_force=(0.0, 0.0, 0.0)),))
    out, (rec,) = gov(above, a)
    assert out == (0.2, 0.2, -0.2, 0.0, 0.0, 0.0, 1.0)
    assert "steered back inward" in rec.reason
    # 4 mm under the ceiling (within restore_within, 1 cm): the zero or upward command becomes a
    # push down at 0.2 * (1 - 0.4); no clamp of the rest, rotation frozen (within the margin).
    creeping = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.296), eef_force=(0.0, 0.0, 0.0)),))
    out, records = gov(creeping, (0.5, 0.3, 0.0, 0.4, 0.0, 0.0, 1.0))
    assert out[:3] == (0.5, 0.3, pytest.approx(-0.12)) and out[3:] == (0.0, 0.0, 0.0, 1.0)
    assert any("within 0.01 m of a workspace-box face: steered back inward" in r.reason for r in records)
    assert gov(creeping, (0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0)) == ((0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0), ())
    # 1 cm or more inside: nothing pushes back
    level = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.29), eef_force=(0.0, 0.0, 0.0)),))
    assert gov(level, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)) == ((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), ())
    off = Phi((WorkspaceGuard(restore_within=0.0),)).governor(SINGLE_PANDA)
    assert off(creeping, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)) == ((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), ())


def test_workspace_guard_rejects_bad_config() -> None:
    with pytest.raises(Invalid) as e:
        WorkspaceGuard(restore=0.7)
    assert e.value.details["field"] == "restore" and e.value.message == "restore: must be in [0, 0.6], got 0.7"
    with pytest.raises(Invalid) as e:
        WorkspaceGuard(margin=0.05, restore_within=0.06)
    assert e.value.details["field"] == "restore_within"
    assert e.value.message == "restore_within: must be in [0, margin = 0.05], got 0.06"
    with pytest.raises(Invalid) as e:
        WorkspaceGuard(low=(0.0, 0.0, 0.0), high=(0.3, 1.0, 1.0))
    assert e.value.details["field"] == "high" and "must be longer than 2 * (margin + brake)" in e.value.message


@settings(max_examples=300, deadline=None)
@given(f=st.tuples(*[st.floats(-60.0, 60.0)] * 3), action=actions(7))
def test_force_ramp_backs_off_above_the_limit(f, action) -> None:
    n = math.hypot(*f)
    assume(n > RAMP.max_force * 1.001)
    state = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=f),))
    out, _ = Phi((RAMP,)).governor(SINGLE_PANDA)(state, action)
    for k in range(3):
        if f[k] != 0.0:
            assert out[k] * math.copysign(1.0, f[k]) >= RAMP.backoff * abs(f[k]) / n - TOL
    assert all(abs(x) <= RAMP.backoff + TOL for x in out[:6])


def test_force_ramp_examples() -> None:
    gov = Phi((RAMP,)).governor(SINGLE_PANDA)
    table = lambda fz: RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 0.81), eef_force=(0.0, 0.0, fz)),))  # noqa: E731
    down = (0.3, 0.0, -1.0, 0.2, 0.0, 0.0, 1.0)
    assert gov(table(9.0), down) == (down, ())  # below half the limit: untouched
    out, (rec,) = gov(table(15.0), down)  # halfway up the ramp: the push is at most 0.025
    assert out == (0.3, 0.0, pytest.approx(-0.025), 0.2, 0.0, 0.0, 1.0) and "slowed" in rec.reason
    out, _ = gov(table(30.0), down)  # above the limit: lift off slowly, everything within +-0.05
    assert out == (0.05, 0.0, 0.05, 0.05, 0.0, 0.0, 1.0)
    with pytest.raises(Invalid) as e:
        ForceRamp(soft_from=25.0)
    assert e.value.details["field"] == "soft_from"


HOLDING = ForceRamp(release=0.02)


def test_force_ramp_holds_motion_into_a_contact_after_a_spike_until_the_hand_has_backed_off() -> None:
    gov = Phi((HOLDING,)).governor(SINGLE_PANDA)
    at = lambda z, fz: RobotState(arms=(ArmState(eef_pos=(0.1, 0.0, z), eef_force=(0.0, 0.0, fz)),))  # noqa: E731
    down = (0.3, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0)
    assert gov(at(0.9, 0.0), down) == (down, ())  # no contact yet: untouched
    gov(at(0.85, 40.0), down)  # the spike: the table pushes up at 40 N
    # The reading drops (the hand bounced, or the rule backed it off): still no pushing down...
    out, (rec,) = gov(at(0.855, 0.0), down)
    assert out == (0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) and "held until the hand has backed off 0.02 m" in rec.reason
    assert gov(at(0.869, 5.0), down)[0][2] == 0.0  # backed off 1.9 cm: held
    assert gov(at(0.87, 0.0), down) == (down, ())  # 2 cm: released
    assert gov(at(0.86, 0.0), down) == (down, ())  # and it stays released until the next spike
    # A new episode starts unlatched; without hysteresis nothing is held after the spike.
    gov(at(0.85, 40.0), down)
    gov.new_episode()
    assert gov(at(0.855, 0.0), down) == (down, ())
    plain = Phi((RAMP,)).governor(SINGLE_PANDA)
    plain(at(0.85, 40.0), down)
    assert plain(at(0.855, 0.0), down) == (down, ())


@settings(max_examples=200, deadline=None)
@given(
    f=st.tuples(*[st.floats(-60.0, 60.0)] * 3),
    moves=st.lists(st.tuples(st.floats(-0.03, 0.03), st.floats(-0.03, 0.03), st.floats(-0.03, 0.03)), max_size=6),
    action=actions(7),
)
def test_force_ramp_hysteresis_invariant(f, moves, action) -> None:
    # Invariant 6: after a spike, until the hand is `release` back along the spike's direction,
    # no translational component moves into that contact, whatever the force reads meanwhile.
    n = math.hypot(*f)
    assume(n > HOLDING.max_force * 1.001)
    u = tuple(x / n for x in f)
    gov = Phi((HOLDING,)).governor(SINGLE_PANDA)
    p = [0.0, 0.0, 1.0]
    gov(RobotState(arms=(ArmState(eef_pos=tuple(p), eef_force=f),)), action)
    released = False
    for d in moves:
        p = [p[k] + d[k] for k in range(3)]
        back = sum((p[k] - (0.0, 0.0, 1.0)[k]) * u[k] for k in range(3))
        released = released or back >= HOLDING.release
        out, _ = gov(RobotState(arms=(ArmState(eef_pos=tuple(p), eef_force=(0.0, 0.0, 0.0)),)), action)
        if not released:
            assert all(out[k] * u[k] >= 0.0 or out[k] == 0.0 for k in range(3))


def test_surface_approach_lets_the_hand_touch_softly_and_sees_its_tilt() -> None:
    gov = Phi((SURFACE,)).governor(SINGLE_PANDA)
    down = (0.0, 0.0, -1.0, 0.4, 0.0, 0.0, -1.0)
    pointing_down = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
    # Fingertips 1.2 cm below the site: with the site 6 cm above the table they are 4.8 cm up,
    # 5.2 cm from the stop height (0.796): half speed down, and no faster turning.
    at = ArmPose(eef_pos=(0.0, 0.0, 0.86), eef_force=(0.0, 0.0, 0.0), eef_rot=pointing_down)
    out, (rec,) = gov(RobotState(arms=(at,)), down)
    assert out[2] == pytest.approx(-0.52) and out[3] == pytest.approx(0.4) and "surface" in rec.reason
    # The same height with the hand tilted 60 degrees about the site's y axis (its wide side swung
    # down): a corner of the hand body is 7.5 cm below the site, under the stop height.
    c, s = math.cos(math.radians(60)), math.sin(math.radians(60))
    tilted = (c, 0.0, s, 0.0, -1.0, 0.0, s, 0.0, -c)
    assert lowest_offset(PANDA_HAND, tilted) < -0.06
    out, _ = gov(RobotState(arms=(ArmPose(eef_pos=(0.0, 0.0, 0.86), eef_force=(0, 0, 0), eef_rot=tilted),)), down)
    assert out[2] == 0.0 and out[3:6] == (0.0, 0.0, 0.0)
    # A plain ArmState is taken to point down.
    plain = ArmState(eef_pos=(0.0, 0.0, 0.86), eef_force=(0.0, 0.0, 0.0))
    assert gov(RobotState(arms=(plain,)), down)[0] == gov(RobotState(arms=(at,)), down)[0]
    # High above the band: untouched, the very object returned.
    high = ArmPose(eef_pos=(0.0, 0.0, 1.2), eef_force=(0.0, 0.0, 0.0), eef_rot=tilted)
    assert gov(RobotState(arms=(high,)), down) == (down, ())


@settings(max_examples=300, deadline=None)
@given(q=QUATS, corner=st.tuples(st.floats(0, 1), st.floats(0, 1), st.floats(0, 1)))
def test_hand_geometry_matches_brute_force_over_corners(q, corner) -> None:
    rot = rotation(q)
    arm = ArmPose(eef_pos=(0.0, 0.0, 0.0), eef_force=(0.0, 0.0, 0.0), eef_rot=rot)
    lo, hi = hand_extent(PANDA_HAND, rot)
    blo, bhi = hand_box(PANDA_HAND, arm)
    assert lo == pytest.approx(tuple(blo), abs=1e-12) and hi == pytest.approx(tuple(bhi), abs=1e-12)
    assert lowest_offset(PANDA_HAND, rot) == pytest.approx(blo[2], abs=1e-12)
    reach = hand_reach(PANDA_HAND)
    assert all(-reach - 1e-12 <= v <= reach + 1e-12 for v in (*lo, *hi))
    assert arm_rot(arm) == rot


def test_reach_limit_brakes_outward_and_restores_inward() -> None:
    gov = Phi((REACH,)).governor(SINGLE_PANDA)
    out_x = (1.0, 0.3, 0.0, 0.0, 0.0, 0.0, 1.0)
    # 0.78 m from the shoulder straight along +x: within the 3 cm margin: outward x zeroed, y free.
    edge = RobotState(arms=(ArmState(eef_pos=(0.22, 0.0, 1.245), eef_force=(0.0, 0.0, 0.0)),))
    out, (rec,) = gov(edge, out_x)
    assert out[:3] == (0.0, 0.3, 0.0) and "reach" in rec.reason
    # Beyond it: steered back along -x at 0.1.
    beyond = RobotState(arms=(ArmState(eef_pos=(0.3, 0.0, 1.245), eef_force=(0.0, 0.0, 0.0)),))
    out, _ = gov(beyond, out_x)
    assert out[:6] == (-0.1, 0.1, 0.0, 0.0, 0.0, 0.0)
    # Inside the column around the base: pushed out along +x.
    column = RobotState(arms=(ArmState(eef_pos=(-0.4, 0.0, 1.2), eef_force=(0.0, 0.0, 0.0)),))
    out, _ = gov(column, (-1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert out[0] == pytest.approx(0.1)
    with pytest.raises(Invalid) as e:
        ReachLimit(centres=((0, 0, 1),), max_radius=0.8).compile(TWO_ARM_NO_GRIPPER)
    assert e.value.details["field"] == "centres" and e.value.message == "centres: 1 given; the layout has 2 arm(s)"


def test_obstacle_approach_lets_the_hand_pass_over_a_wall_but_not_into_it() -> None:
    gov = Phi((OBSTACLES,)).governor(SINGLE_PANDA)
    # Fingers along y, hand 10 cm above the wall top at y = 0: moving along x is barely slowed.
    over = ArmState(eef_pos=(0.1, -0.08, 1.02), eef_force=(0.0, 0.0, 0.0))
    out, _ = gov(RobotState(arms=(over,)), (-1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert out[0] < -0.9
    # Beside the wall (hand 7.8 cm from it, fingers along x): moving towards it at most 0.68.
    beside = ArmState(eef_pos=(0.1, -0.12, 0.86), eef_force=(0.0, 0.0, 0.0))
    out, _ = gov(RobotState(arms=(beside,)), (0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert out[1] == pytest.approx(0.68)
    # Within the 1 cm clearance: stopped; moving away is free.
    touching = ArmState(eef_pos=(0.1, -0.045, 0.86), eef_force=(0.0, 0.0, 0.0))
    out, _ = gov(RobotState(arms=(touching,)), (0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert out[1] == 0.0
    away = (0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert gov(RobotState(arms=(touching,)), away) == (away, ())
    with pytest.raises(Invalid) as e:
        ObstacleApproach(boxes=OBSTACLES.boxes, arm=1).compile(SINGLE_PANDA)
    assert e.value.details["field"] == "arm"


@pytest.mark.parametrize("arm", [0, 1])
def test_per_arm_obstacle_rules_only_govern_their_arm(arm: int) -> None:
    rule = ObstacleApproach(boxes=(Aabb(low=(-1.0, -1.0, 0.0), high=(1.0, 1.0, 0.5)),), arm=arm)
    gov = Phi((rule,)).governor(TWO_ARM_NO_GRIPPER)
    low = ArmState(eef_pos=(0.0, 0.0, 0.52), eef_force=(0.0, 0.0, 0.0))
    out, (record,) = gov(RobotState(arms=(low, low)), (0.0, 0.0, -1.0, 0.0, 0.0, 0.0) * 2)
    governed, other = (out[2], out[8]) if arm == 0 else (out[8], out[2])
    assert other == -1.0 and governed == pytest.approx(-0.1)  # 2 cm above, 1 cm past the clearance
    assert record.reason == f"arm {arm}: hand near obstacle 0: motion towards it braked"


TASK_PHIS = {t: Phi.for_task(task_spec(t)) for t in ("T1", "T3", "T4")}


def clear_of_faces(guard: WorkspaceGuard, p: tuple[float, float, float]) -> bool:
    """Inside the box and at least ``restore_within`` from each face, where the guard steers back."""
    w = guard.restore_within
    return all(guard.low[k] + w <= p[k] <= guard.high[k] - w for k in range(3))


@pytest.mark.parametrize("task", list(TASK_PHIS))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_per_task_phi_satisfies_every_rule_at_once_where_nothing_restores(task, data) -> None:
    # Restoring edits fire only in states already past a limit (outside the box or the reach,
    # inside the column, above the force limit); everywhere else every rule must hold together.
    phi = TASK_PHIS[task]
    reach = next(c for c in phi.constraints if isinstance(c, ReachLimit))
    p = data.draw(in_reach(reach.centres[0], reach))
    guard = next(c for c in phi.constraints if isinstance(c, WorkspaceGuard))
    assume(clear_of_faces(guard, p))
    # Up to the force ramp's limit (2 N under the paper's 20 N): above it the ramp backs off.
    limit = next(c for c in phi.constraints if isinstance(c, ForceRamp)).max_force
    f = data.draw(st.tuples(*[st.floats(-limit, limit)] * 3).filter(lambda f: math.hypot(*f) <= limit))
    arm = ArmPose(eef_pos=p, eef_force=f, eef_rot=rotation(data.draw(QUATS)))
    assume(within_reach(reach, 0, arm))
    state = RobotState(arms=(arm,))
    action = data.draw(actions(7))
    out, records = phi.governor(SINGLE_PANDA)(state, action)
    assert violations(phi, SINGLE_PANDA, state, out, tol=TOL) == []
    unchanged_or_clamped(action, out)
    assert (out is action) == (not records)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_two_arm_task_phi_satisfies_every_rule_at_once_where_nothing_restores(data) -> None:
    phi = Phi.for_task(task_spec("T6"))
    reach = next(c for c in phi.constraints if isinstance(c, ReachLimit))
    guard = next(c for c in phi.constraints if isinstance(c, WorkspaceGuard))
    arms_ = []
    for i in range(2):
        p = data.draw(in_reach(reach.centres[i], reach))
        assume(clear_of_faces(guard, p))
        f = data.draw(st.tuples(*[st.floats(-10.0, 10.0)] * 3).filter(lambda f: math.hypot(*f) <= 18.0))
        arms_.append(ArmPose(eef_pos=p, eef_force=f, eef_rot=rotation(data.draw(QUATS))))
        assume(within_reach(reach, i, arms_[-1]))
    state = RobotState(arms=tuple(arms_))
    action = data.draw(actions(12))
    out, _ = phi.governor(TWO_ARM_NO_GRIPPER)(state, action)
    assert violations(phi, TWO_ARM_NO_GRIPPER, state, out, tol=TOL) == []
    unchanged_or_clamped(action, out)


HANDS = st.lists(
    st.tuples(*[st.floats(-0.2, 0.2)] * 3, *[st.floats(0.001, 0.1)] * 3).map(
        lambda v: Aabb(low=v[:3], high=(v[0] + v[3], v[1] + v[4], v[2] + v[5]))
    ),
    max_size=3,
)
ODD = st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -0.0])


@settings(max_examples=300, deadline=None)
@given(hand=HANDS, q=QUATS, odd=st.one_of(st.none(), st.tuples(st.integers(0, 8), ODD)))
def test_compiled_hand_extent_is_hand_extent_to_the_bit(hand, q, odd) -> None:
    rot = list(rotation(q))
    if odd is not None:
        rot[odd[0]] = odd[1]
    got, want = extent_of(hand)(rot), hand_extent(hand, rot)
    assert repr(got) == repr(want)  # repr: NaN equals NaN and -0.0 differs from 0.0


@settings(max_examples=300, deadline=None)
@given(q=QUATS, direction=QUATS, off=st.floats(1e-8, 1e-3), side=st.sampled_from([-1.0, 1.0]), push=st.floats(1.0, 3.0))
def test_reach_limit_on_its_wrist_test_brakes_right_at_the_edge_of_its_band(q, direction, off, side, push) -> None:
    # The check decides from the wrist itself that a state is clear: near the band's edge it
    # must still brake where the rule says so (10 nm and more either side of the edge: at the
    # edge itself the rule and govcheck may round d differently).
    reach = next(c for c in Phi.for_task(task_spec("T4")).constraints if isinstance(c, ReachLimit))
    c, rot = reach.centres[0], rotation(q)
    u = [v / math.sqrt(sum(x * x for x in direction[:3]) or 1.0) for v in direction[:3]]
    assume(sum(x * x for x in u) > 0.5 and abs(u[2]) < 0.7)  # keep out of the base column
    r = reach.max_radius - reach.margin - reach.brake + side * off
    wrist = [c[k] + r * u[k] for k in range(3)]
    pt = reach.point
    p = tuple(wrist[k] - (rot[3 * k] * pt[0] + rot[3 * k + 1] * pt[1] + rot[3 * k + 2] * pt[2]) for k in range(3))
    state = RobotState(arms=(ArmPose(eef_pos=p, eef_force=(0.0, 0.0, 0.0), eef_rot=rot),))
    action = [push * u[0], push * u[1], push * u[2], 0.0, 0.0, 0.0, 0.0]
    out, _ = Phi((reach,)).governor(SINGLE_PANDA)(state, action)
    assert violations(Phi((reach,)), SINGLE_PANDA, state, out, tol=TOL) == []
