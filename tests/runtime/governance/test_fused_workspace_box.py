"""workspace_box in the fused kernel (csrc/workspace_box.c) against its Python check."""

from __future__ import annotations

import random

import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, actions, robot_states
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi, WorkspaceBox
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

BOXES = [
    WorkspaceBox(),
    WorkspaceBox(low=(-0.3, -0.2, 0.8), high=(0.4, 0.5, 1.1), margin=0.0, name="tight"),
    WorkspaceBox(margin=0.3),
]
PAIRS = [Pair(Phi((box,)), SINGLE_PANDA) for box in BOXES]
TWO_ARMS = Pair(Phi((BOXES[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
OFF = Pair(Phi((BOXES[1],)), SINGLE_PANDA, enforce=False)


@pytest.mark.parametrize("pair", [*PAIRS, TWO_ARMS, OFF], ids=["default", "tight", "wide", "two_arms", "off"])
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the test above while doing nothing."""
    rng = random.Random(7)
    pair = PAIRS[0]
    for _ in range(500):
        p = (rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.7), rng.uniform(0.5, 1.4))
        state = RobotState(arms=(ArmState(eef_pos=p, eef_force=(0.0, 0.0, 0.0)),))
        pair.check(state, [rng.uniform(-1.5, 1.5) for _ in range(7)])
    assert pair.handled == pair.calls
