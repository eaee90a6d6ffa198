"""velocity_cap in the fused kernel (csrc/velocity_cap.c) against its Python check."""

from __future__ import annotations

import math
import random

import pytest
from fused_support import COMPONENT, SIGNED_PERMUTATIONS, Pair, actions, near_edges, robot_states
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi, VelocityCap
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

CAPS = [VelocityCap(), VelocityCap(max_norm=0.37, name="slow"), VelocityCap(max_norm=1e-3)]
PAIRS = [Pair(Phi((c,)), SINGLE_PANDA) for c in CAPS]
TWO_ARMS = Pair(Phi((CAPS[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
OFF = Pair(Phi((CAPS[1],)), SINGLE_PANDA, enforce=False)
CASES = [(PAIRS[0], 1.5), (PAIRS[1], 0.37), (PAIRS[2], 1e-3), (TWO_ARMS, 1.5), (OFF, 0.37)]
IDS = ["default", "slow", "tiny", "two_arms", "off"]
STILL = RobotState(arms=(ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)),))
STILL2 = RobotState(arms=STILL.arms * 2)


@st.composite
def pose_deltas(draw: st.DrawFn, cap: float) -> list[float]:
    """Six pose components: generic, with the norm right at the cap, tiny beside huge, or overflowing."""
    kind = draw(st.sampled_from(["components", "at_cap", "at_cap", "mixed", "overflow"]))
    if kind == "components":
        return [draw(COMPONENT) for _ in range(6)]
    if kind == "at_cap":  # a direction scaled to the cap: the sum of squares on either side of cap2
        d = [draw(st.sampled_from([-1.0, -0.5, -0.0, 0.0, 0.3, 1.0])) for _ in range(6)]
        n = math.sqrt(sum(x * x for x in d)) or 1.0
        m = draw(near_edges(cap, spread=cap / 1e6))
        return [x / n * m for x in d]
    if kind == "mixed":  # components that underflow to a signed zero when scaled
        return [draw(st.sampled_from([5e-324, -5e-324, 1e-300, -0.0, 0.0, 3.0, -7.0, 1e150])) for _ in range(6)]
    # The squares overflow: Python takes math.hypot, the kernel must fall back.
    v = [draw(COMPONENT) for _ in range(6)]
    v[draw(st.integers(0, 5))] = draw(st.sampled_from([1e155, -1e200, 1.7e308, -1.7976931348623157e308]))
    return v


@st.composite
def cap_actions(draw: st.DrawFn, dim: int, n_arms: int, cap: float) -> list[float]:
    # The layouts here put the arms back to back from offset 0 (6 components each, then any gripper).
    a: list[float] = []
    for _ in range(n_arms):
        a += draw(pose_deltas(cap))
    a += [draw(COMPONENT) for _ in range(dim - len(a))]  # the gripper, untouched
    return a


@pytest.mark.parametrize(("pair", "cap"), CASES, ids=IDS)
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, cap: float, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    n = len(layout.arms)
    pair.check(STILL if n == 1 else STILL2, data.draw(cap_actions(layout.dim, n, cap)))


@pytest.mark.parametrize("pair", [PAIRS[0], TWO_ARMS], ids=["default", "two_arms"])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_on_generic_states(pair: Pair, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


def test_every_branch_is_exercised() -> None:
    pair = Pair(Phi((VelocityCap(),)), TWO_ARM_NO_GRIPPER)
    s = 1.5 / math.sqrt(6.0)
    cases = [
        ([0.0] * 12, True),  # allow
        ([1.5, 0.0, 0.0, 0.0, 0.0, 0.0] * 2, True),  # exactly at the cap: allowed
        ([s, -s, s, -s, s, -s, 2.0, 0.0, 0.0, 0.0, 0.0, -0.0], True),  # the second arm scaled
        ([3.0, 5e-324, -0.0, 0.0, 1.0, 1.0, 2.0, 2.0, 2.0, 0.0, 0.0, 0.0], True),  # both arms: two reasons
        ([1e200, 0.0, 0.0, 0.0, 0.0, 0.0, *[0.0] * 6], False),  # overflow: math.hypot, fallback
        ([2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1e155, 1.0, 0.0, 0.0, 0.0, 0.0], False),
    ]
    for a, decided in cases:
        assert (pair.kernel._program(STILL2.arms, a) is not None) == decided, a
        pair.check(STILL2, a)
    _, ivs = pair.kernel(STILL2, cases[3][0])
    assert ivs[0].reason.count("; ") == 1


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(7)
    one = Pair(Phi((CAPS[0],)), SINGLE_PANDA)
    two = Pair(Phi((CAPS[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
    for pair, state in ((one, STILL), (two, STILL2)):
        for _ in range(400):
            pair.check(state, [rng.uniform(-1.2, 1.2) for _ in range(pair.kernel.layout.dim)])
        assert pair.handled == pair.calls
        assert pair.python.stats().modified > 50  # the scaling ran in C, not only allow
