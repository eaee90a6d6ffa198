"""obstacle_approach in the fused kernel (csrc/obstacle_approach.c, csrc/hand.c) against its Python check."""

from __future__ import annotations

import math
import random

import pytest
from fused_support import (
    FORCE,
    QUATS,
    SIGNED_PERMUTATIONS,
    Pair,
    actions,
    near_edges,
    robot_states,
    rotation,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi
from capevo.runtime.governance.hand import hand_extent
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.obstacle import ObstacleApproach, extent_of
from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.governance.proximity import ArmScene
from capevo.runtime.governance.zone import Aabb
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState


def from_task(task: str) -> list[ObstacleApproach]:
    return [c for c in Phi.for_task(task).constraints if isinstance(c, ObstacleApproach)]


(T1,) = from_task("T1")
(T4,) = from_task("T4")
T6 = from_task("T6")  # one rule per arm (peg and plate hands)
assert len(T6) == 2 and [c.arm for c in T6] == [0, 1]

WALLS = (Aabb(low=(0.0, -0.2, 0.8), high=(0.02, 0.2, 0.95)), Aabb(low=(0.3, 0.1, 0.7), high=(0.5, 0.3, 1.2)))
PLAIN = ObstacleApproach(boxes=WALLS)
WIDE = ObstacleApproach(boxes=WALLS, hand=T4.hand, clearance=0.03, brake=0.2, rotation=False, name="wide")
STOP = ObstacleApproach(boxes=WALLS, hand=T6[1].hand, clearance=0.02, brake=0.0)

CASES = {
    "plain": (Pair(Phi((PLAIN,)), SINGLE_PANDA), PLAIN),
    "wide": (Pair(Phi((WIDE,)), SINGLE_PANDA), WIDE),
    "stop": (Pair(Phi((STOP,)), SINGLE_PANDA), STOP),
    "off": (Pair(Phi((WIDE,)), SINGLE_PANDA, enforce=False), WIDE),
    "T1": (Pair(Phi((T1,)), SINGLE_PANDA), T1),
    "T4": (Pair(Phi((T4,)), SINGLE_PANDA), T4),
    "T1_two_arms": (Pair(Phi((T1,)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]), T1),
    "T6": (Pair(Phi(tuple(T6)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]), T6[0]),
    "T6_arm1": (Pair(Phi((T6[1],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]), T6[1]),
}

ROTATIONS = st.one_of(
    st.none(),
    st.sampled_from(SIGNED_PERMUTATIONS),
    QUATS.map(rotation),
    # a slight tilt of the gripper-down frame: corners cross the obstacle faces
    st.tuples(st.just(1.0), *[st.floats(-0.15, 0.15) for _ in range(3)]).map(rotation),
)
BAD_ROTATION = st.tuples(*[st.sampled_from([0.0, 1.0, math.nan, math.inf, -math.inf, 1e300]) for _ in range(9)])


def near_obstacle(c: ObstacleApproach) -> st.SearchStrategy[tuple[float, float, float]]:
    """Site positions around one of the obstacles: inside, on a face, within the band, or beyond."""
    reach = 0.3 + c.clearance + c.brake

    def axis(lo: float, hi: float) -> st.SearchStrategy[float]:
        return st.one_of(
            st.floats(lo - reach, hi + reach),
            near_edges(lo, hi, lo - c.clearance, hi + c.clearance, spread=0.15),
            st.floats(lo, hi),
        )

    return st.one_of(*[st.tuples(*[axis(b.low[k], b.high[k]) for k in range(3)]) for b in c.boxes])


NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])


def arms_near(c: ObstacleApproach) -> st.SearchStrategy[ArmState]:
    """Arm states around ``c``'s obstacles; now and then a non-finite position or orientation."""
    spoilt = st.tuples(st.one_of(NON_FINITE, st.floats(-1, 1)), st.floats(-1, 2), NON_FINITE).flatmap(st.permutations)
    position = st.one_of(near_obstacle(c), near_obstacle(c), near_obstacle(c), spoilt.map(tuple))
    forces = st.tuples(FORCE, FORCE, FORCE)
    rot = st.one_of(ROTATIONS, ROTATIONS, ROTATIONS, BAD_ROTATION)
    return st.one_of(
        st.builds(lambda p, f: ArmState(eef_pos=p, eef_force=f), position, forces),
        st.builds(
            lambda p, f, r: (
                ArmState(eef_pos=p, eef_force=f) if r is None else ArmPose(eef_pos=p, eef_force=f, eef_rot=r)
            ),
            position,
            forces,
            rot,
        ),
        st.builds(
            lambda p, f, r: ArmScene(eef_pos=p, eef_force=f, eef_rot=r, near=()),
            position,
            forces,
            rot.filter(lambda r: r is not None),
        ),
    )


ARMS = {name: arms_near(c) for name, (_, c) in CASES.items()}


SMALL = st.one_of(st.floats(-0.2, 0.2), st.sampled_from([0.0, -0.0, 0.05, -0.05, 0.1, -0.1]))


def small_actions(dim: int) -> st.SearchStrategy[list[float]]:
    """Actions around the bounds the rule clamps to (q · dist / Σs is small near an obstacle)."""
    return st.lists(st.one_of(SMALL, st.floats(-1.5, 1.5)), min_size=dim, max_size=dim)


@pytest.mark.parametrize("name", list(CASES))
@settings(max_examples=50, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_near_obstacles(name: str, data: st.DataObject) -> None:
    pair, _ = CASES[name]
    layout = pair.kernel.layout
    n = len(layout.arms)
    state = RobotState(arms=tuple(data.draw(ARMS[name]) for _ in range(n)))
    act = data.draw(st.one_of(actions(layout.dim), small_actions(layout.dim)))
    pair.check(state, act)


@pytest.mark.parametrize("name", ["plain", "T4", "T6"])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_anywhere(name: str, data: st.DataObject) -> None:
    pair, _ = CASES[name]
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


@settings(max_examples=50, deadline=None)
@given(rot=st.one_of(ROTATIONS.filter(lambda r: r is not None), BAD_ROTATION))
def test_extent_of_is_hand_extent(rot: tuple[float, ...]) -> None:
    """The extent hand.c ports: extent_of and hand_extent agree to the bit, NaN included."""
    for hand in ((), T4.hand, T6[0].hand, T6[1].hand):
        want = hand_extent(hand, rot)
        got = extent_of(hand)(rot)
        assert repr(got) == repr(want)


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(11)
    for name in ("T4", "T6"):
        pair, c = CASES[name]
        n = len(pair.kernel.layout.arms)
        before = pair.python.stats().modified
        pair.calls = pair.handled = 0
        for _ in range(600):
            arms = []
            for _ in range(n):
                box = rng.choice(c.boxes)
                p = tuple(rng.uniform(box.low[k] - 0.25, box.high[k] + 0.25) for k in range(3))
                tilt = rotation((1.0, rng.gauss(0, 0.05), rng.gauss(0, 0.05), rng.gauss(0, 0.5)))
                arms.append(ArmPose(eef_pos=p, eef_force=(0.0, 0.0, 0.0), eef_rot=tilt))
            pair.check(RobotState(arms=tuple(arms)), [rng.uniform(-1.0, 1.0) for _ in range(pair.kernel.layout.dim)])
        assert pair.handled == pair.calls
        assert pair.python.stats().modified - before > 100  # the modify path is decided in C too
