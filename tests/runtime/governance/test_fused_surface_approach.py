"""surface_approach in the fused kernel (csrc/surface_approach.c) against its Python check."""

from __future__ import annotations

import math
import random
from typing import Any

import pytest
from fused_support import QUATS, SIGNED_PERMUTATIONS, Pair, actions, near_edges, robot_states, rotation
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi, SurfaceApproach
from capevo.runtime.governance.hand import hand_reach
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import DOWN, ArmPose
from capevo.runtime.governance.proximity import ArmScene
from capevo.runtime.governance.zone import Aabb
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState


def task_surface(task: str) -> SurfaceApproach:
    return next(c for c in Phi.for_task(task).constraints if isinstance(c, SurfaceApproach))


T1, T3 = task_surface("T1"), task_surface("T3")  # bin floor 0.82, table 0.8; Panda hand, lateral 0.2
SURFACES = {
    "T1": T1,
    "T3": T3,
    "default": SurfaceApproach(height=0.8),  # no hand: the site point; no lateral
    "flat": SurfaceApproach(  # brake 0: only zeroed at the surface; no turning limit; lateral 0
        height=0.9, clearance=0.01, brake=0.0, rotation=False, lateral=0.0, name="flat"
    ),
    "box": SurfaceApproach(
        height=0.75, clearance=-0.01, brake=0.05, hand=(Aabb(low=(-0.03, -0.02, -0.1), high=(0.04, 0.02, 0.0)),),
        lateral=1.0,
    ),
}  # fmt: skip
PAIRS = {name: Pair(Phi((c,)), SINGLE_PANDA) for name, c in SURFACES.items()}
PAIRS["two_arms"] = Pair(Phi((T3,)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
PAIRS["two_arms_box"] = Pair(Phi((SURFACES["box"],)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[3:5])
PAIRS["off"] = Pair(Phi((T1,)), SINGLE_PANDA, enforce=False)
CONSTRAINT = {name: pair.kernel.phi.constraints[0] for name, pair in PAIRS.items()}


def edges(c: SurfaceApproach) -> list[float]:
    """Heights where the check branches: the stop height, the band, the fast-path top, the hand's reach."""
    stop, reach = c.height + c.clearance, hand_reach(c.hand)
    return [stop, stop + c.brake, stop + reach, stop - reach, stop + reach + c.brake, stop + reach + c.brake / 2]


def tilt(angle: float, ax: float, ay: float) -> tuple[float, ...]:
    """DOWN turned by ``angle`` about the horizontal axis (ax, ay) (normalised)."""
    n = math.hypot(ax, ay) or 1.0
    s = math.sin(angle / 2) / n
    w, x, y, z = math.cos(angle / 2), ax * s, ay * s, 0.0
    r = rotation((w, x, y, z))
    # r @ DOWN: DOWN flips the site's y and z.
    return (r[0], -r[1], -r[2], r[3], -r[4], -r[5], r[6], -r[7], -r[8])


ROT = st.one_of(
    st.sampled_from(SIGNED_PERMUTATIONS),
    QUATS.map(rotation),
    st.builds(tilt, st.floats(-0.8, 0.8), st.floats(-1, 1), st.floats(-1, 1)),
    st.builds(tilt, st.sampled_from([0.3, -0.5, math.pi / 3]), st.floats(-1, 1), st.floats(-1, 1)),
)
BAD = st.sampled_from([math.nan, math.inf, -math.inf])


@st.composite
def surface_arm(draw: st.DrawFn, c: SurfaceApproach) -> ArmState:
    z = draw(BAD) if draw(rare()) else draw(st.one_of(st.floats(0.5, 1.3), near_edges(*edges(c), spread=0.03)))
    p = (draw(st.floats(-0.6, 0.6)), draw(st.floats(-0.6, 0.6)), z)
    f = (0.0, 0.0, draw(st.floats(-30.0, 30.0)))
    kind = draw(st.sampled_from(["state", "pose", "pose", "scene"]))
    if kind == "state":
        return ArmState(eef_pos=p, eef_force=f)
    rot = draw(ROT)
    if draw(rare()):  # a broken orientation reading
        k = draw(st.integers(0, 8))
        rot = (*rot[:k], draw(BAD), *rot[k + 1 :])
    if draw(st.integers(0, 30)) == 0:  # finite entries whose sum overflows
        rot = (1e308, 1e308, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
    if kind == "pose":
        return ArmPose(eef_pos=p, eef_force=f, eef_rot=rot)
    return ArmScene(eef_pos=p, eef_force=f, eef_rot=rot, near=())


def rare() -> st.SearchStrategy[bool]:
    return st.integers(0, 40).map(lambda k: k == 0)


@st.composite
def surface_case(draw: st.DrawFn, pair: Pair) -> tuple[RobotState, list[float]]:
    """A state near the surface and an action whose components sit on or beside the bounds it implies."""
    c = pair.kernel.phi.constraints[0]
    layout = pair.kernel.layout
    arms = tuple(draw(surface_arm(c)) for _ in layout.arms)
    a: list[Any] = draw(actions(layout.dim))
    for arm, al in zip(arms, layout.arms, strict=True):
        gap = c.gap(arm) if math.isfinite(arm.eef_pos[2]) else 0.0
        q = (gap / c.brake if c.brake > 0.0 else 0.0) if gap > 0.0 else 0.0
        q = q if math.isfinite(q) else 0.0
        bounds = [q, -q, 0.0, -0.0]
        if c.lateral is not None:
            bounds += [c.lateral, -c.lateral, max(c.lateral, q), -max(c.lateral, q)]
        edge = st.sampled_from(bounds).flatmap(
            lambda v: st.sampled_from([v, math.nextafter(v, math.inf), math.nextafter(v, -math.inf)])
        )
        for j in range(6):
            if draw(st.booleans()):
                a[al.offset + j] = draw(edge)
    return RobotState(arms=arms), a


@pytest.mark.parametrize("name", list(PAIRS))
@settings(max_examples=50, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_near_the_surface(name: str, data: st.DataObject) -> None:
    pair = PAIRS[name]
    pair.check(*data.draw(surface_case(pair)))


@pytest.mark.parametrize("name", ["T1", "default", "two_arms"])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_on_general_states(name: str, data: st.DataObject) -> None:
    pair = PAIRS[name]
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


@pytest.mark.parametrize("name", ["T1", "T3", "two_arms"])
def test_the_kernel_decides_most_calls_itself(name: str) -> None:
    """Realistic states (hands above the table, tilted a little, some in the band): no fallback.

    A port that always fell back would pass the tests above while doing nothing.
    """
    rng = random.Random(11)
    c = CONSTRAINT[name]
    layout = PAIRS[name].kernel.layout
    pair = Pair(Phi((c,)), layout, frames=SIGNED_PERMUTATIONS[2:4] if len(layout.arms) == 2 else None)
    modified = 0
    for _ in range(600):
        arms = []
        for _ in layout.arms:
            p = (rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), c.height + rng.uniform(-0.02, 0.35))
            rot = tilt(rng.uniform(-0.6, 0.6), rng.uniform(-1, 1), rng.uniform(-1, 1)) if rng.random() < 0.8 else DOWN
            arms.append(ArmPose(eef_pos=p, eef_force=(0.0, 0.0, 0.0), eef_rot=rot))
        state = RobotState(arms=tuple(arms))
        action = [rng.uniform(-1.0, 1.0) for _ in range(layout.dim)]
        got = pair.kernel._program(state.arms, action)
        modified += isinstance(got, tuple)
        pair.check(state, action)
    assert pair.handled == pair.calls
    assert modified > 100  # the band was reached: the kernel modified, not just allowed


def test_a_broken_reading_falls_back_to_the_formatted_reason() -> None:
    pair = PAIRS["T1"]
    down = [0.0, 0.0, -1.0, 0.3, 0.0, 0.0, 1.0]
    for arm in (
        ArmPose(eef_pos=(0.0, 0.0, math.nan), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN),
        ArmPose(eef_pos=(0.0, 0.0, 0.85), eef_force=(0.0, 0.0, 0.0), eef_rot=(*DOWN[:8], math.inf)),
    ):
        state = RobotState(arms=(arm,))
        assert pair.kernel._program(state.arms, down) is None
        pair.check(state, down)
        _, (rec,) = Phi((T1,)).governor(SINGLE_PANDA)(state, down)
        assert "not finite" in rec.reason
    # High above the band a broken orientation plays no part (the fast path never reads it).
    high = ArmPose(eef_pos=(0.0, 0.0, 1.3), eef_force=(0.0, 0.0, 0.0), eef_rot=(math.nan,) * 9)
    assert pair.kernel._program((high,), down) is True
