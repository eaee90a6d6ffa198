"""The paper's default Φ (workspace_box, contact_force, velocity_cap) in the fused kernel against the Python checks."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from fused_support import COMPONENT, SIGNED_PERMUTATIONS, Pair, actions, robot_states
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

T6_FRAMES = SIGNED_PERMUTATIONS[2:4]
PAIRS = {
    "one_arm": Pair(Phi.default(), SINGLE_PANDA),
    "one_arm_off": Pair(Phi.default(), SINGLE_PANDA, enforce=False),
    "two_arms": Pair(Phi.default(), TWO_ARM_NO_GRIPPER, frames=T6_FRAMES),
    "two_arms_off": Pair(Phi.default(), TWO_ARM_NO_GRIPPER, frames=T6_FRAMES, enforce=False),
}
CAP_EDGE = 1.5 / math.sqrt(6.0)


@st.composite
def paper_actions(draw: st.DrawFn, dim: int) -> list[float]:
    """Generic components, or components around the cap's edge (so zeroing and scaling interact)."""
    if draw(st.booleans()):
        return draw(actions(dim))
    edge = st.one_of(
        st.sampled_from([CAP_EDGE, -CAP_EDGE, 0.0, -0.0]), st.floats(-CAP_EDGE * 1.2, CAP_EDGE * 1.2), COMPONENT
    )
    return [draw(edge) for _ in range(dim)]


def as_container(a: list[float], kind: str) -> object:
    if kind == "list":
        return a
    if kind == "tuple":
        return tuple(a)
    if kind == "float64":
        return np.array(a, dtype=np.float64)
    return np.array(a, dtype=np.float32)  # widened exactly on both paths


@pytest.mark.parametrize("name", list(PAIRS))
@settings(max_examples=75, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(name: str, data: st.DataObject) -> None:
    pair = PAIRS[name]
    layout = pair.kernel.layout
    state = data.draw(robot_states(len(layout.arms)))
    a = data.draw(paper_actions(layout.dim))
    pair.check(state, as_container(a, data.draw(st.sampled_from(["list", "tuple", "float64", "float32"]))))


def fallback_inputs(dim: int) -> list[object]:
    """Inputs the kernel must hand to the Python checks; the governors still must agree on them."""
    base = [0.3] * dim
    return [
        [1] * dim,  # ints
        [0.3] * (dim - 1) + [2],  # one int among floats
        tuple([1, 0, 0, 0, 0, 0] + [0] * (dim - 6)),
        [math.nan, *base[1:]],
        [0.1, math.inf, *base[2:]],
        [*base, 0.1],  # too long
        base[:-1],  # too short
        [],
        np.ones(dim, dtype=np.int64),  # an int array
        np.full((1, dim), 0.3),  # 2-D
        np.full((2, dim), 0.3),
        (np.arange(2.0 * dim) / (4 * dim))[::2],  # not contiguous
        [np.float64(0.3)] * dim,  # float subclasses, not exact floats
        [True, *base[1:]],
        "x" * dim,
        None,
        [2.0, 2.0, 2.0, 2.0, 2.0, 1e200, *base[6:]],  # the cap's overflow path (math.hypot)
    ]


@pytest.mark.parametrize("name", list(PAIRS))
def test_fallback_inputs_give_identical_results(name: str) -> None:
    pair = PAIRS[name]
    layout = pair.kernel.layout
    rng = random.Random(3)
    for a in fallback_inputs(layout.dim):
        for _ in range(20):
            state = RobotState(
                arms=tuple(
                    ArmState(
                        eef_pos=(rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.7), rng.uniform(0.5, 1.4)),
                        eef_force=tuple(rng.uniform(-25.0, 25.0) for _ in range(3)),
                    )
                    for _ in layout.arms
                )
            )
            assert pair.kernel._program(state.arms, a) is None, a
            pair.check(state, a)


@pytest.mark.parametrize("name", list(PAIRS))
def test_non_finite_state_gives_identical_results(name: str) -> None:
    pair = PAIRS[name]
    layout = pair.kernel.layout
    a = [0.5] * layout.dim
    for bad in (math.nan, math.inf, -math.inf):
        for field in ("eef_pos", "eef_force"):
            for k in range(3):
                v = [0.0, 0.0, 1.0]
                v[k] = bad
                arm = ArmState(
                    eef_pos=tuple(v) if field == "eef_pos" else (0.0, 0.0, 1.0),
                    eef_force=tuple(v) if field == "eef_force" else (0.0, 0.0, 30.0),
                )
                pair.check(RobotState(arms=(arm,) * len(layout.arms)), a)


def test_the_kernel_decides_realistic_calls_itself() -> None:
    """Positions in and around the box, forces up to past the limit, actions up to past the cap."""
    rng = random.Random(11)
    for name in ("one_arm", "two_arms"):
        base = PAIRS[name]
        pair = Pair(Phi.default(), base.kernel.layout, frames=base.kernel.frames)
        layout = pair.kernel.layout
        for n in range(600):
            state = RobotState(
                arms=tuple(
                    ArmState(
                        eef_pos=(rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.7), rng.uniform(0.5, 1.4)),
                        eef_force=tuple(rng.uniform(-25.0, 25.0) for _ in range(3)),
                    )
                    for _ in layout.arms
                )
            )
            a = [rng.uniform(-1.2, 1.2) for _ in range(layout.dim)]
            pair.check(state, a if n % 2 else np.array(a))
        assert pair.handled == pair.calls
        stats = pair.python.stats()
        assert stats.modified > 100
        assert set(stats.by_constraint) == {"workspace_box", "contact_force", "velocity_cap"}
