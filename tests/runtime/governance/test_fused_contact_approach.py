"""contact_approach in the fused kernel (csrc/contact_approach.c) against its Python check."""

from __future__ import annotations

import math
import random
from typing import Any

import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, actions, near_edges, unit
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import ContactApproach, Phi
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import DOWN
from capevo.runtime.governance.proximity import FIXED, LOOSE, ArmScene
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

RULES = [
    ContactApproach(),
    ContactApproach(clearance=0.0, brake=0.05, touch=0.0, touch_loose=0.2, brake_loose=0.02, lever=0.05, name="tight"),
    # A touch of -0.0 against a loose touch of 0.0: two bounds (split) that differ only in a signed zero.
    ContactApproach(touch=-0.0, touch_loose=0.0),
    ContactApproach(touch=0.3, touch_loose=0.01, brake_loose=0.3, rotation=False),
    ContactApproach(touch=1.0, touch_loose=1.0),
    ContactApproach(brake_loose=0.1),  # the same numbers as the fixed bound: no split
]
PAIRS = [Pair(Phi((rule,)), SINGLE_PANDA) for rule in RULES]
TWO_ARMS = [
    Pair(Phi((RULES[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]),
    Pair(Phi((RULES[1],)), TWO_ARM_NO_GRIPPER),
    Pair(Phi((RULES[2],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[3:5]),
]
OFF = Pair(Phi((RULES[1],)), SINGLE_PANDA, enforce=False)
ALL = [*PAIRS, *TWO_ARMS, OFF]
IDS = ["default", "tight", "signed_zero", "no_rotation", "touch_one", "same_loose", "two_arms", "two_tight", "two_zero"]
IDS.append("off")

ODD_NORMALS = st.sampled_from(
    [
        (0.0, 0.0, -1.0),
        (-0.0, 0.0, -1.0),
        (0.6, 0.8, 0.0),
        (1e-200, 1e-170, -1.0),  # squares that underflow next to a unit component
        (1e-200, -1e-180, 1e-170),  # all squares underflow: brake's scaling branch
        (0.0, 0.0, 0.0),
        (3.0, -2.0, 0.5),  # not a unit vector: the check takes it as given
    ]
)
SMALL = st.one_of(st.floats(-1.0, 1.0), st.sampled_from([0.0, -0.0, 1e-170, -1e-200, 5e-324]))


def rule_of(pair: Pair) -> ContactApproach:
    (rule,) = pair.kernel.phi.constraints
    return rule


def normals() -> st.SearchStrategy[tuple[float, float, float]]:
    return st.one_of(unit(), ODD_NORMALS, st.tuples(SMALL, SMALL, SMALL))


def levers(rule: ContactApproach) -> st.SearchStrategy[tuple[float, float, float]]:
    """Vectors from the site to the hand's near point: around |r| = lever, and odd ones."""
    lever = rule.lever

    def scaled(v: tuple[float, float, float], f: float) -> tuple[float, float, float]:
        n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        return (v[0] / n * lever * f, v[1] / n * lever * f, v[2] / n * lever * f)

    factors = st.sampled_from([1.0, 1 + 1e-12, 1 - 1e-12, 1 + 2e-16, 1 - 2e-16, 0.5, 2.0])
    return st.one_of(
        st.tuples(*[st.floats(-0.3, 0.3) for _ in range(3)]),
        st.builds(scaled, unit(), factors),
        st.sampled_from([(lever, 0.0, 0.0), (0.0, 0.0, -lever), (0.0, 0.0, 0.0)]),
        st.sampled_from([(math.inf, 0.0, 0.1), (-math.inf, 0.0, 0.0), (math.nan, 0.0, 0.0), (1e200, -1e200, 1e160)]),
    )


@st.composite
def near_pairs(draw: st.DrawFn, rule: ContactApproach, n_arms: int, finite: bool = False) -> tuple[Any, ...]:
    """Pairs at the bound's edges: the clearance, the ends of both bands, the band."""
    cl = rule.clearance
    edges = (cl, cl + rule.brake, cl + (rule.brake_loose or rule.brake), 0.0, cl + rule.brake / 2)
    out = []
    for _ in range(draw(st.integers(0, 4))):
        dist = draw(st.one_of(near_edges(*edges, spread=0.01), st.floats(-0.02, 0.2), st.just(-0.0)))
        n = draw(normals())
        if not finite and draw(st.integers(0, 40)) == 0:
            dist, n = draw(st.sampled_from([(math.nan, n), (math.inf, n), (0.0, (math.nan, 0.0, 1.0))]))
        owner = draw(st.sampled_from([LOOSE, LOOSE, FIXED, *range(n_arms), n_arms, -3]))
        out.append((dist, *n, *draw(levers(rule)), owner))
    return tuple(out)


@st.composite
def states_and_actions(draw: st.DrawFn, pair: Pair, finite: bool = False) -> tuple[RobotState, list[float]]:
    layout = pair.kernel.layout
    rule = rule_of(pair)
    n_arms = len(layout.arms)
    arms: list[ArmState] = []
    for _ in range(n_arms):
        if draw(st.integers(0, 9)) == 0:
            arms.append(ArmState(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0)))
        else:
            near = draw(near_pairs(rule, n_arms, finite))
            arms.append(ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=near))
    a = draw(actions(layout.dim))
    for i, arm in enumerate(arms):
        near = getattr(arm, "near", ())
        if near and draw(st.booleans()):
            # Motion straight along (or against) a pair's normal: components reach 0 together.
            _, nx, ny, nz, *_ = draw(st.sampled_from(near))
            t = draw(st.one_of(st.sampled_from([1.0, -1.0, 0.5, 3.0]), st.floats(-2.0, 2.0)))
            o = layout.arms[i].offset
            a[o : o + 3] = [t * nx, t * ny, t * nz]
    return RobotState(arms=tuple(arms)), a


@pytest.mark.parametrize("pair", ALL, ids=IDS)
@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_kernel_matches_python(pair: Pair, data: st.DataObject) -> None:
    pair.check(*data.draw(states_and_actions(pair)))


def test_a_non_finite_pair_falls_back_to_the_python_reason() -> None:
    pair = Pair(Phi((RULES[0],)), SINGLE_PANDA)
    for bad in [(math.nan, 0.0, 0.0, -1.0), (0.01, math.inf, 0.0, 0.0), (0.01, 0.0, 0.0, -math.nan)]:
        near = ((*bad, 0.0, 0.0, 0.0, FIXED),)
        scene = ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=near)
        state = RobotState(arms=(scene,))
        assert pair.kernel._program(state.arms, [0.0] * 7) is None
        pair.check(state, [0.0] * 7)
    got, ivs = pair.kernel(state, [0.0] * 7)
    assert got is None and "is not finite" in ivs[-1].reason


def test_another_arms_pair_brakes_both_arms_and_joins_the_reasons() -> None:
    pair = TWO_ARMS[1]
    near = ((0.0, 1.0, 0.0, 0.0, 0.01, 0.0, 0.0, 1),)
    scene = ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=near)
    state = RobotState(arms=(scene, ArmState(eef_pos=(0.5, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0))))
    a = [0.5, 0.2, 0.0, 0.3, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 0.0, -0.2]
    assert pair.kernel._program(state.arms, a) is not None
    pair.check(state, a)
    _, (iv,) = pair.kernel(state, a)
    assert (
        iv.reason
        == "arm 0: hand near a contact: motion towards it braked; arm 1: hand near a contact: motion towards it braked"
    )


def test_the_kernel_decides_the_common_cases_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(11)
    pairs = [
        Pair(Phi((RULES[0],)), SINGLE_PANDA),
        Pair(Phi((RULES[0],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4]),
    ]
    for _ in range(800):
        pair = pairs[rng.randrange(2)]
        n_arms = len(pair.kernel.layout.arms)
        arms = []
        for _ in range(n_arms):
            near = []
            for _ in range(rng.randrange(4)):
                v = [rng.gauss(0.0, 1.0) for _ in range(3)]
                n = math.sqrt(sum(x * x for x in v))
                r = [rng.uniform(-0.15, 0.15) for _ in range(3)]
                near.append(
                    (rng.uniform(-0.005, 0.15), *(x / n for x in v), *r, rng.choice([LOOSE, FIXED, 0, 1][: 2 + n_arms]))
                )
            arms.append(ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=tuple(near)))
        pair.check(RobotState(arms=tuple(arms)), [rng.uniform(-1.0, 1.0) for _ in range(pair.kernel.layout.dim)])
    for pair in pairs:
        assert pair.handled == pair.calls
        assert pair.kernel.stats().modified > pair.calls // 4  # the usual modify, decided in C
