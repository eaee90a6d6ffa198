"""arm_separation in the fused kernel (csrc/arm_separation.c, csrc/hand.c) against its Python check."""

from __future__ import annotations

import math
import random

import pytest
from fused_support import FORCE, QUATS, SIGNED_PERMUTATIONS, Pair, actions, robot_states, rotation
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.governance.proximity import ArmScene
from capevo.runtime.governance.separation import ArmSeparation
from capevo.runtime.governance.zone import Aabb
from capevo.runtime.state import ActionLayout, ArmActionLayout, ArmState, RobotState

(T6,) = [c for c in Phi.for_task("T6").constraints if isinstance(c, ArmSeparation)]
PEG, PLATE = T6.hands
THREE_ARMS = ActionLayout(dim=21, arms=tuple(ArmActionLayout(offset=7 * k, gripper=7 * k + 6) for k in range(3)))
FRAMES = SIGNED_PERMUTATIONS[2:4]

POINTS = ArmSeparation(hands=((), ()))
BOXES = ArmSeparation(
    hands=(PEG, (Aabb(low=(-0.05, -0.05, 0.0), high=(0.05, 0.05, 0.1)), *PLATE)),
    clearance=0.03,
    brake=0.1,
    floor=0.02,
    rotation=False,
    name="boxes",
)
NO_BRAKE = ArmSeparation(hands=(PLATE, PEG), clearance=0.05, brake=0.0, floor=0.1)
THREE = ArmSeparation(hands=(PEG, (), PLATE), clearance=0.01, brake=0.2, floor=0.05)

CASES = {
    "T6": Pair(Phi((T6,)), TWO_ARM_NO_GRIPPER, frames=FRAMES),
    "T6_off": Pair(Phi((T6,)), TWO_ARM_NO_GRIPPER, frames=FRAMES, enforce=False),
    "points": Pair(Phi((POINTS,)), TWO_ARM_NO_GRIPPER),
    "boxes": Pair(Phi((BOXES,)), TWO_ARM_NO_GRIPPER, frames=FRAMES),
    "no_brake": Pair(Phi((NO_BRAKE,)), TWO_ARM_NO_GRIPPER),
    "three_arms": Pair(Phi((THREE,)), THREE_ARMS),
}

ROTATIONS = st.one_of(
    st.none(),
    st.sampled_from(SIGNED_PERMUTATIONS),
    QUATS.map(rotation),
    st.tuples(st.just(1.0), *[st.floats(-0.15, 0.15) for _ in range(3)]).map(rotation),
)
BAD_ROTATION = st.tuples(*[st.sampled_from([0.0, 1.0, math.nan, math.inf, -math.inf, 1e300]) for _ in range(9)])
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])
# Offsets of one site from the other: coincident, overlapping, within the band, beyond it.
GAP = st.one_of(
    st.floats(-0.05, 0.05),
    st.floats(-0.4, 0.4),
    st.sampled_from([0.0, -0.0, 0.15, -0.15, 0.2, -0.2, 0.3, -0.3]),
    st.floats(-1.2, 1.2),
)
CENTRE = st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(0.8, 1.3))


def arm_at(p: tuple[float, ...], f: tuple[float, ...], rot: tuple[float, ...] | None, scene: bool) -> ArmState:
    if rot is None:
        return ArmState(eef_pos=p, eef_force=f)
    if scene:
        return ArmScene(eef_pos=p, eef_force=f, eef_rot=rot, near=())
    return ArmPose(eef_pos=p, eef_force=f, eef_rot=rot)


@st.composite
def close_states(draw: st.DrawFn, n_arms: int) -> RobotState:
    """Arms whose hands are near each other (sites around one point), now and then non-finite."""
    c = draw(CENTRE)
    arms = []
    for _ in range(n_arms):
        p = tuple(c[k] + draw(GAP) for k in range(3))
        if draw(st.integers(0, 19)) == 0:
            p = tuple(draw(st.one_of(st.just(v), NON_FINITE)) for v in p)
        rot = draw(BAD_ROTATION) if draw(st.integers(0, 49)) == 0 else draw(ROTATIONS)
        arms.append(arm_at(p, draw(st.tuples(FORCE, FORCE, FORCE)), rot, draw(st.booleans())))
    return RobotState(arms=tuple(arms))


SMALL = st.one_of(st.floats(-0.2, 0.2), st.sampled_from([0.0, -0.0, 0.05, -0.05, 0.02, -0.02, 0.1, -0.1]))


def small_actions(dim: int) -> st.SearchStrategy[list[float]]:
    """Actions around the floor and the bounds the rule clamps to."""
    return st.lists(st.one_of(SMALL, st.floats(-1.5, 1.5)), min_size=dim, max_size=dim)


@pytest.mark.parametrize("name", list(CASES))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_near_each_other(name: str, data: st.DataObject) -> None:
    pair = CASES[name]
    layout = pair.kernel.layout
    state = data.draw(close_states(len(layout.arms)))
    pair.check(state, data.draw(st.one_of(actions(layout.dim), small_actions(layout.dim))))


@pytest.mark.parametrize("name", ["T6", "three_arms"])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_anywhere(name: str, data: st.DataObject) -> None:
    pair = CASES[name]
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(5)
    for name in ("T6", "three_arms"):
        pair = CASES[name]
        n, dim = len(pair.kernel.layout.arms), pair.kernel.layout.dim
        before = pair.python.stats().modified
        pair.calls = pair.handled = 0
        for _ in range(600):
            c = (rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.9, 1.2))
            arms = []
            for _ in range(n):
                p = tuple(c[k] + rng.gauss(0.0, 0.15) for k in range(3))
                tilt = rotation((1.0, rng.gauss(0, 0.05), rng.gauss(0, 0.05), rng.gauss(0, 0.5)))
                arms.append(ArmPose(eef_pos=p, eef_force=(0.0, 0.0, 0.0), eef_rot=tilt))
            pair.check(RobotState(arms=tuple(arms)), [rng.uniform(-1.0, 1.0) for _ in range(dim)])
        assert pair.handled == pair.calls
        assert pair.python.stats().modified - before > 100  # the modify path is decided in C too
