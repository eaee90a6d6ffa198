"""workspace_guard in the fused kernel (csrc/workspace_guard.c) against its Python check."""

from __future__ import annotations

import dataclasses
import math
import random

import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, arm_scenes, near_edges
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import ForceRamp, Phi, WorkspaceGuard
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

GUARDS = [
    WorkspaceGuard(),
    WorkspaceGuard(
        low=(-0.3, -0.2, 0.8),
        high=(0.4, 0.5, 1.1),
        margin=0.0,
        brake=0.05,
        restore=0.6,
        freeze_rotation=False,
        name="tight",
    ),
    WorkspaceGuard(margin=0.05, brake=0.0, restore=0.0),  # no band, no restoring push
    WorkspaceGuard(margin=0.0, brake=0.0, restore=0.01),
]
PAIRS = [Pair(Phi((guard,)), SINGLE_PANDA) for guard in GUARDS]
TWO_ARMS = Pair(Phi((GUARDS[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
OFF = Pair(Phi((GUARDS[1],)), SINGLE_PANDA, enforce=False)
WITH_RAMP = Pair(Phi((GUARDS[0], ForceRamp())), SINGLE_PANDA)  # a restoring edit followed by another check


def edges(guard: WorkspaceGuard, k: int) -> tuple[float, ...]:
    """Where the check branches along axis ``k``: the faces, the margins and the band edges."""
    lo, hi, m, band = guard.low[k], guard.high[k], guard.margin, guard.margin + guard.brake
    return (lo, lo + m, lo + band, hi - m, hi - band, hi, (lo + hi) / 2)


def coords(guard: WorkspaceGuard, k: int) -> st.SearchStrategy[float]:
    lo, hi = guard.low[k], guard.high[k]
    return st.one_of(
        near_edges(*edges(guard, k), spread=0.04),
        st.floats(lo - 0.3, hi + 0.3),
        st.floats(-1e6, 1e6),
    )


@st.composite
def guard_states(draw: st.DrawFn, guard: WorkspaceGuard, n_arms: int, finite: bool = True) -> RobotState:
    arms = []
    for _ in range(n_arms):
        arm = draw(arm_scenes(n_arms))
        p = tuple(draw(coords(guard, k)) for k in range(3))
        if not finite and draw(st.integers(0, 9)) == 0:  # now and then a broken reading
            k = draw(st.integers(0, 2))
            p = (*p[:k], draw(st.sampled_from([math.nan, math.inf, -math.inf])), *p[k + 1 :])
        arms.append(dataclasses.replace(arm, eef_pos=p))
    return RobotState(arms=tuple(arms))


def guard_actions(guard: WorkspaceGuard, dim: int) -> st.SearchStrategy[list[float]]:
    rs = guard.restore
    special = [0.0, -0.0, rs, -rs, math.nextafter(rs, 0.0), -math.nextafter(rs, 0.0), 0.5, -0.5, 1.0, -1.0, 1e-300]
    component = st.one_of(st.floats(-2.0, 2.0), st.sampled_from(special), st.floats(-1e6, 1e6))
    return st.lists(component, min_size=dim, max_size=dim)


@pytest.mark.parametrize(
    "pair",
    [*PAIRS, TWO_ARMS, OFF, WITH_RAMP],
    ids=["default", "tight", "no_band", "thin", "two_arms", "off", "with_ramp"],
)
@settings(max_examples=75, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, data: st.DataObject) -> None:
    layout = pair.kernel.layout
    guard = pair.kernel.phi.constraints[0]
    state = data.draw(guard_states(guard, len(layout.arms), finite=False))
    pair.check(state, data.draw(guard_actions(guard, layout.dim)))


def test_the_kernel_decides_most_calls_itself() -> None:
    """A port that always fell back would pass the test above while doing nothing.

    Positions around the whole box, so most calls take the slow path: braking in the band,
    the restoring push outside, and the rotation freeze.
    """
    rng = random.Random(7)
    pairs = [
        Pair(Phi((GUARDS[0],)), SINGLE_PANDA),
        Pair(Phi((GUARDS[1],)), SINGLE_PANDA),
        Pair(Phi((GUARDS[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]),
    ]
    for pair in pairs:
        layout = pair.kernel.layout
        for _ in range(400):
            arms = tuple(
                ArmState(
                    eef_pos=(rng.uniform(-0.75, 0.75), rng.uniform(-0.75, 0.75), rng.uniform(0.45, 1.45)),
                    eef_force=(0.0, 0.0, 0.0),
                )
                for _ in layout.arms
            )
            pair.check(RobotState(arms=arms), [rng.uniform(-1.5, 1.5) for _ in range(layout.dim)])
        assert pair.handled == pair.calls
    # and it really intervened on most of them
    assert pairs[0].kernel.stats().modified > 100
