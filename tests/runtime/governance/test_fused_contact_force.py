"""contact_force in the fused kernel (csrc/contact_force.c) against its Python check."""

from __future__ import annotations

import math
import random

import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, actions, near_edges, robot_states
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import ContactForce, Phi
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

LIMITS = [20.0, 7.3, 0.5]
FORCES = [ContactForce(), ContactForce(max_force=7.3, name="soft"), ContactForce(max_force=0.5)]
PAIRS = [Pair(Phi((c,)), SINGLE_PANDA) for c in FORCES]
TWO_ARMS = Pair(Phi((FORCES[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
TWO_ARMS_SOFT = Pair(Phi((FORCES[1],)), TWO_ARM_NO_GRIPPER, frames=(SIGNED_PERMUTATIONS[0], SIGNED_PERMUTATIONS[4]))
OFF = Pair(Phi((FORCES[1],)), SINGLE_PANDA, enforce=False)
CASES = [
    (PAIRS[0], 20.0),
    (PAIRS[1], 7.3),
    (PAIRS[2], 0.5),
    (TWO_ARMS, 20.0),
    (TWO_ARMS_SOFT, 7.3),
    (OFF, 7.3),
]
IDS = ["default", "soft", "tiny", "two_arms", "two_arms_soft", "off"]


def component(limit: float) -> st.SearchStrategy[float]:
    """A force component: around the limit (on one axis or spread over two or three), signed zeros, extremes."""
    return st.one_of(
        st.floats(-2 * limit, 2 * limit),
        near_edges(0.0, limit, -limit, limit / math.sqrt(2), -limit / math.sqrt(3), spread=limit / 10),
        st.sampled_from([0.0, -0.0, 5e-324, -5e-324, 1e200, -1e200, 1.7e308]),
    )


@st.composite
def forces(draw: st.DrawFn, limit: float) -> tuple[float, float, float]:
    kind = draw(st.sampled_from(["components", "components", "magnitude", "non_finite"]))
    if kind == "components":
        return (draw(component(limit)), draw(component(limit)), draw(component(limit)))
    if kind == "magnitude":  # a direction scaled to just around the limit: n2 on either side of lim2
        x, y, z = draw(st.tuples(*[st.sampled_from([-1.0, -0.5, 0.0, -0.0, 0.5, 1.0])] * 3))
        n = math.sqrt(x * x + y * y + z * z) or 1.0
        m = draw(near_edges(limit, spread=limit / 1000))
        return (x / n * m, y / n * m, z / n * m)
    # Non-finite readings: Python rejects with a formatted reason, the kernel must fall back.
    f = [draw(component(limit)) for _ in range(3)]
    f[draw(st.integers(0, 2))] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    return (f[0], f[1], f[2])


@st.composite
def force_states(draw: st.DrawFn, n_arms: int, limit: float) -> RobotState:
    """Arm states whose forces sit around ``limit``; the position does not matter to this check."""
    arms = []
    for _ in range(n_arms):
        p = draw(st.tuples(st.floats(-1.0, 2.0), st.floats(-1.0, 2.0), st.floats(-1.0, 2.0)))
        f = draw(forces(limit))
        if draw(st.booleans()):
            arms.append(ArmState(eef_pos=p, eef_force=f))
        else:
            arms.append(ArmPose(eef_pos=p, eef_force=f, eef_rot=draw(st.sampled_from(SIGNED_PERMUTATIONS))))
    return RobotState(arms=tuple(arms))


@pytest.mark.parametrize(("pair", "limit"), CASES, ids=IDS)
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, limit: float, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    pair.check(data.draw(force_states(len(layout.arms), limit)), data.draw(actions(layout.dim)))


@pytest.mark.parametrize("pair", [PAIRS[0], TWO_ARMS], ids=["default", "two_arms"])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_on_generic_states(pair: Pair, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


def test_every_branch_is_exercised() -> None:
    """Exactly at, just above the limit; several axes zeroed at once; a non-finite reading."""
    pair = Pair(Phi((ContactForce(),)), SINGLE_PANDA)
    p = (0.0, 0.0, 1.0)
    a = [0.5, -0.5, -0.25, 0.1, 0.2, 0.3, 1.0]
    cases = [
        ((20.0, 0.0, 0.0), True),  # n2 == lim2: allowed
        ((0.0, 0.0, math.nextafter(20.0, 30.0)), True),  # just above: z pushes into the contact
        ((-15.0, 15.0, 15.0), True),  # three axes zeroed, three reasons joined
        ((15.0, -15.0, -15.0), True),  # none moves into the contact: allowed
        ((1e200, 0.0, -1e200), True),  # n2 overflows to inf but the reading is finite
        ((math.nan, 0.0, 0.0), False),  # formatted reason: fallback
        ((math.inf, 0.0, 0.0), False),
    ]
    for f, decided in cases:
        state = RobotState(arms=(ArmState(eef_pos=p, eef_force=f),))
        assert (pair.kernel._program(state.arms, a) is not None) == decided, f
        pair.check(state, a)
    _, ivs = pair.kernel(RobotState(arms=(ArmState(eef_pos=p, eef_force=(-15.0, 15.0, 15.0)),)), a)
    assert ivs[0].reason.count("; ") == 2


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(7)
    one = Pair(Phi((FORCES[0],)), SINGLE_PANDA)
    two = Pair(Phi((FORCES[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
    for pair in (one, two):
        n = len(pair.kernel.layout.arms)
        for _ in range(400):
            arms = tuple(
                ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=tuple(rng.uniform(-25.0, 25.0) for _ in range(3)))
                for _ in range(n)
            )
            pair.check(RobotState(arms=arms), [rng.uniform(-1.5, 1.5) for _ in range(pair.kernel.layout.dim)])
        assert pair.handled == pair.calls
        assert pair.python.stats().modified > 50  # the modify path ran in C, not only allow
