"""force_ramp in the fused kernel (csrc/force_ramp.c) against its Python check."""

from __future__ import annotations

import dataclasses
import math
import random

import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, arm_scenes, near_edges, unit
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import ForceRamp, Phi, WorkspaceGuard
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

RAMPS = [
    ForceRamp(),
    ForceRamp(max_force=50.0, soft_from=0.0, speed=0.3, backoff=0.6, name="firm"),
    ForceRamp(max_force=15.0, soft_from=14.0, speed=1.0, backoff=0.0),  # no back-off: zero into the contact
    ForceRamp(max_force=3.0, soft_from=1.0, speed=2.5, backoff=0.001),
]
PAIRS = [Pair(Phi((ramp,)), SINGLE_PANDA) for ramp in RAMPS]
TWO_ARMS = Pair(Phi((RAMPS[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
OFF = Pair(Phi((RAMPS[1],)), SINGLE_PANDA, enforce=False)
AFTER_GUARD = Pair(Phi((WorkspaceGuard(), RAMPS[0])), SINGLE_PANDA)


@st.composite
def forces(draw: st.DrawFn, ramp: ForceRamp, finite: bool = True) -> tuple[float, float, float]:
    """Forces whose magnitude sits at, beside and around the ramp's edges, in any direction."""
    how = draw(st.integers(0, 9))
    if how == 0:  # componentwise, with zeros and signed zeros
        comp = st.one_of(st.sampled_from([0.0, -0.0]), st.floats(-2 * ramp.max_force, 2 * ramp.max_force))
        return (draw(comp), draw(comp), draw(comp))
    if how == 1:  # extremes: squares that overflow or underflow
        comp = st.one_of(st.floats(-1e300, 1e300), st.sampled_from([1e200, -1e200, 1e-200, 5e-324, 0.0]))
        return (draw(comp), draw(comp), draw(comp))
    if how == 2 and not finite:
        k = draw(st.integers(0, 2))
        f = [draw(st.floats(-30.0, 30.0)) for _ in range(3)]
        f[k] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        return (f[0], f[1], f[2])
    mag = draw(
        st.one_of(
            near_edges(ramp.soft_from, ramp.max_force, (ramp.soft_from + ramp.max_force) / 2, spread=1.0),
            st.floats(0.0, 3 * ramp.max_force),
        )
    )
    direction = draw(unit())
    return (mag * direction[0], mag * direction[1], mag * direction[2])


@st.composite
def ramp_states(draw: st.DrawFn, ramp: ForceRamp, n_arms: int, finite: bool = True) -> RobotState:
    arms = []
    for _ in range(n_arms):
        arm = draw(arm_scenes(n_arms))
        f = draw(forces(ramp, finite))
        arms.append(dataclasses.replace(arm, eef_force=f))
    return RobotState(arms=tuple(arms))


def ramp_actions(ramp: ForceRamp, dim: int) -> st.SearchStrategy[list[float]]:
    b = ramp.backoff
    special = [0.0, -0.0, b, -b, ramp.speed, -ramp.speed, ramp.speed / 2, -ramp.speed / 2, 1.0, -1.0, 1e-300]
    component = st.one_of(st.floats(-2.0, 2.0), st.sampled_from(special), st.floats(-1e6, 1e6))
    return st.lists(component, min_size=dim, max_size=dim)


@pytest.mark.parametrize(
    "pair",
    [*PAIRS, TWO_ARMS, OFF, AFTER_GUARD],
    ids=["default", "firm", "no_backoff", "small", "two_arms", "off", "after_guard"],
)
@settings(max_examples=75, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    ramp = pair.kernel.phi.constraints[-1]
    state = data.draw(ramp_states(ramp, len(layout.arms), finite=False))
    pair.check(state, data.draw(ramp_actions(ramp, layout.dim)))


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the test above while doing nothing.

    Forces from none to well above the limit: the ramp and the back-off both fire often.
    """
    rng = random.Random(11)
    pairs = [
        Pair(Phi((RAMPS[0],)), SINGLE_PANDA),
        Pair(Phi((RAMPS[2],)), SINGLE_PANDA),
        Pair(Phi((RAMPS[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]),
    ]
    for pair in pairs:
        layout = pair.kernel.layout
        for _ in range(400):
            arms = tuple(
                ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=tuple(rng.uniform(-25.0, 25.0) for _ in range(3)))
                for _ in layout.arms
            )
            pair.check(RobotState(arms=arms), [rng.uniform(-1.5, 1.5) for _ in range(layout.dim)])
        assert pair.handled == pair.calls
    assert pairs[0].kernel.stats().modified > 100
