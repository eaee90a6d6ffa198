"""forbidden_zone in the fused kernel (csrc/forbidden_zone.c) against its Python check."""

from __future__ import annotations

import math
import random

import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, actions, near_edges, robot_states
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Aabb, ForbiddenZone, Phi
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

ONE = (Aabb(low=(0.1, -0.2, 0.8), high=(0.3, 0.2, 1.0)),)
THREE = (  # the first two overlap; the third sits apart
    Aabb(low=(0.1, -0.2, 0.8), high=(0.3, 0.2, 1.0)),
    Aabb(low=(0.25, -0.1, 0.7), high=(0.5, 0.4, 0.95)),
    Aabb(low=(-0.3, -0.3, 0.6), high=(-0.1, 0.1, 0.7)),
)
ZONES = [
    ForbiddenZone(boxes=ONE),
    ForbiddenZone(boxes=THREE, margin=0.0, name="keep_out"),
    ForbiddenZone(boxes=THREE, margin=0.13),
]
PAIRS = [Pair(Phi((z,)), SINGLE_PANDA) for z in ZONES]
TWO_ARMS = Pair(Phi((ZONES[2],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
OFF = Pair(Phi((ZONES[1],)), SINGLE_PANDA, enforce=False)
CASES = [(PAIRS[0], ZONES[0]), (PAIRS[1], ZONES[1]), (PAIRS[2], ZONES[2]), (TWO_ARMS, ZONES[2]), (OFF, ZONES[1])]
IDS = ["one", "three_named", "wide_margin", "two_arms", "off"]


def coordinate(zone: ForbiddenZone, k: int) -> st.SearchStrategy[float]:
    """Axis ``k`` of a position: at and beside every face of every zone, grown and not, and its centre."""
    edges = sorted(
        {
            v
            for b in zone.boxes
            for v in (b.low[k] - zone.margin, b.low[k], (b.low[k] + b.high[k]) / 2, b.high[k], b.high[k] + zone.margin)
        }
    )
    return st.one_of(near_edges(*edges, spread=0.03), st.floats(-1.0, 1.5))


@st.composite
def on_faces(draw: st.DrawFn, zone: ForbiddenZone) -> list[float]:
    """A point of one zone's grown box, each coordinate on one of its planes (or just beside) or between them."""
    b = draw(st.sampled_from(zone.boxes))
    m = zone.margin
    p = []
    for k in range(3):
        planes = (b.low[k] - m, b.low[k], (b.low[k] + b.high[k]) / 2, b.high[k], b.high[k] + m)
        v = draw(st.one_of(st.sampled_from(planes), st.floats(planes[0], planes[-1])))
        p.append(draw(st.sampled_from([v, v, math.nextafter(v, -math.inf), math.nextafter(v, math.inf)])))
    return p


@st.composite
def zone_states(draw: st.DrawFn, n_arms: int, zone: ForbiddenZone) -> RobotState:
    arms = []
    for _ in range(n_arms):
        p = draw(on_faces(zone)) if draw(st.booleans()) else [draw(coordinate(zone, k)) for k in range(3)]
        if draw(st.integers(0, 19)) == 0:  # non-finite: provably outside (inf) or not (NaN)
            p[draw(st.integers(0, 2))] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        f = (0.0, 0.0, 0.0)
        if draw(st.booleans()):
            arms.append(ArmState(eef_pos=(p[0], p[1], p[2]), eef_force=f))
        else:
            rot = draw(st.sampled_from(SIGNED_PERMUTATIONS))
            arms.append(ArmPose(eef_pos=(p[0], p[1], p[2]), eef_force=f, eef_rot=rot))
    return RobotState(arms=tuple(arms))


@pytest.mark.parametrize(("pair", "zone"), CASES, ids=IDS)
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, zone: ForbiddenZone, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    pair.check(data.draw(zone_states(len(layout.arms), zone)), data.draw(actions(layout.dim)))


@pytest.mark.parametrize("pair", [PAIRS[2], TWO_ARMS], ids=["wide_margin", "two_arms"])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_on_generic_states(pair: Pair, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


def test_every_branch_is_exercised() -> None:
    pair = Pair(Phi((ZONES[1],)), TWO_ARM_NO_GRIPPER)
    far = (0.0, 0.9, 1.2)
    a = [0.5, -0.5, 0.5, 0.1, 0.2, 0.3, -0.5, 0.5, -0.5, 0.0, 0.0, 0.0]
    cases = [
        ((far, far), True),  # allow, provably outside every zone
        (((0.1, 0.0, 0.9), far), True),  # on zone 0's -x face: towards it along x zeroed
        (((0.2, 0.0, 0.9), (0.2, 0.0, 0.9)), True),  # inside zone 0, at the centre: nothing to zero
        (((0.15, -0.15, 0.85), (0.27, 0.0, 0.9)), True),  # inside zones 0 and 1: several reasons
        (((0.3, 0.2, 1.0), far), True),  # on zone 0's corner (margin 0): inside, away from the centre zeroed
        (((math.inf, 0.0, 0.9), far), True),  # provably outside although not finite: allowed
        (((math.inf, 0.0, 0.9), (0.2, 0.0, 0.9)), False),  # the other arm is in a zone: formatted reason
        (((math.nan, 0.0, 0.9), far), False),
    ]
    for (p0, p1), decided in cases:
        state = RobotState(arms=tuple(ArmState(eef_pos=p, eef_force=(0.0, 0.0, 0.0)) for p in (p0, p1)))
        assert (pair.kernel._program(state.arms, a) is not None) == decided, (p0, p1)
        pair.check(state, a)
    assert pair.python.stats().modified == 3
    assert pair.python.stats().rejected == 2


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(7)
    one = Pair(Phi((ZONES[2],)), SINGLE_PANDA)
    two = Pair(Phi((ZONES[2],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
    for pair in (one, two):
        for _ in range(400):
            arms = tuple(
                ArmState(
                    eef_pos=(rng.uniform(-0.5, 0.7), rng.uniform(-0.5, 0.6), rng.uniform(0.5, 1.2)),
                    eef_force=(0.0, 0.0, 0.0),
                )
                for _ in pair.kernel.layout.arms
            )
            pair.check(RobotState(arms=arms), [rng.uniform(-1.5, 1.5) for _ in range(pair.kernel.layout.dim)])
        assert pair.handled == pair.calls
        assert pair.python.stats().modified > 50  # the zeroing ran in C, not only allow
