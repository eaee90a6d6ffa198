"""reach_limit in the fused kernel (csrc/reach_limit.c) against its Python check."""

from __future__ import annotations

import math
import random

import pytest
from fused_support import QUATS, SIGNED_PERMUTATIONS, Pair, actions, near_edges, robot_states, rotation, unit
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import Phi
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import DOWN, ArmPose
from capevo.runtime.governance.reach import ReachLimit
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState


def from_task(task: str) -> ReachLimit:
    return next(c for c in Phi.for_task(task).constraints if isinstance(c, ReachLimit))


T1 = from_task("T1")  # one arm, the wrist limited (a lever of 0.2 m), creep
T6 = from_task("T6")  # two arms, the site itself limited
SHOULDER = (-0.56, 0.0, 1.245)
LIMITS = {
    "approach": ReachLimit(centres=(SHOULDER,), max_radius=0.8, min_radius=0.25),
    "t1": T1,
    "sharp": ReachLimit(
        centres=(SHOULDER,), max_radius=0.7, min_radius=0.2, margin=0.0, brake=0.0, restore=0.6, name="sharp"
    ),
    "lever": ReachLimit(
        centres=((-0.5, 0.1, 1.0),),
        max_radius=0.9,
        margin=0.05,
        brake=0.2,
        restore=0.0,
        creep=1.0,
        point=(0.1, -0.05, -0.3),
    ),
    "wide_band": ReachLimit(
        centres=(SHOULDER,),
        max_radius=0.5,
        min_radius=0.3,
        margin=0.02,
        brake=0.4,
        restore=0.25,
        creep=0.2,
        point=(0.0, 0.0, -0.2),
    ),
}
PAIRS = {name: Pair(Phi((c,)), SINGLE_PANDA) for name, c in LIMITS.items()}
PAIRS["t6"] = Pair(Phi((T6,)), TWO_ARM_NO_GRIPPER, frames=SIGNED_PERMUTATIONS[2:4])
PAIRS["t6_wrist"] = Pair(
    Phi((ReachLimit(centres=T6.centres, max_radius=0.808, min_radius=0.3, creep=0.05, point=(0.0, 0.0, -0.2)),)),
    TWO_ARM_NO_GRIPPER,
    frames=(SIGNED_PERMUTATIONS[0], SIGNED_PERMUTATIONS[4]),
)
PAIRS["off"] = Pair(Phi((T1,)), SINGLE_PANDA, enforce=False)
LIMIT_OF = {**LIMITS, "t6": T6, "t6_wrist": PAIRS["t6_wrist"].kernel.phi.constraints[0], "off": T1}


def rot_of(draw: st.DrawFn) -> tuple[float, ...] | None:
    kind = draw(st.sampled_from(["none", "perm", "quat", "quat"]))
    if kind == "none":
        return None
    if kind == "perm":
        return draw(st.sampled_from(SIGNED_PERMUTATIONS))
    return draw(QUATS.map(rotation))


@st.composite
def reach_arm(draw: st.DrawFn, reach: ReachLimit, i: int) -> ArmState:
    """An arm around ``reach``'s edges: its limited point near the sphere, its site near the column."""
    c = reach.centres[i]
    rot = rot_of(draw)
    r = rot if rot is not None else DOWN
    pt = reach.point
    lever = math.sqrt(sum(v * v for v in pt))
    m, band, r_out, r_in = reach.margin, reach.margin + reach.brake, reach.max_radius, reach.min_radius
    where = draw(st.sampled_from(["sphere", "sphere", "column", "column", "centre", "any", "non_finite"]))
    if where == "sphere":
        # Directions with components so small their squares underflow: brake_along's fallback scaling.
        n = draw(st.one_of(unit(), st.sampled_from([(1.0, 1e-170, 0.0), (-0.6, -3e-162, 0.8), (1e-300, -1.0, 1e-170)])))
        radius = draw(
            st.one_of(
                near_edges(r_out, r_out - m, r_out - band, r_out - band - lever, r_out + 0.1, spread=0.02),
                st.just(0.0),
            )
        )
        w = [c[k] + radius * n[k] for k in range(3)]
        p = tuple(w[k] - (r[3 * k] * pt[0] + r[3 * k + 1] * pt[1] + r[3 * k + 2] * pt[2]) for k in range(3))
    elif where == "column":
        theta = draw(st.one_of(st.floats(0.0, 2 * math.pi), st.sampled_from([0.0, math.pi / 2, math.pi, math.pi / 4])))
        rho = draw(
            st.one_of(near_edges(r_in, r_in + m, r_in + band, r_in + band * (1 + 1e-9), spread=0.02), st.just(0.0))
        )
        dz = draw(st.one_of(st.floats(-0.7, 0.7), st.just(0.0)))
        p = (c[0] + rho * math.cos(theta), c[1] + rho * math.sin(theta), c[2] + dz)
    elif where == "centre":
        p = (c[0], c[1], draw(st.floats(c[2] - 1.0, c[2] + 1.0)))
    elif where == "any":
        p = tuple(draw(st.floats(c[k] - 1.2, c[k] + 1.2)) for k in range(3))
    else:  # Python rejects with a formatted reason: the kernel must fall back
        p = [draw(st.floats(-1.0, 1.0)) for _ in range(3)]
        bad = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        if rot is not None and draw(st.booleans()):
            rot = tuple(bad if k == draw(st.integers(0, 8)) else v for k, v in enumerate(rot))
        else:
            p[draw(st.integers(0, 2))] = bad
    p = (float(p[0]), float(p[1]), float(p[2]))
    if rot is None:
        return ArmState(eef_pos=p, eef_force=(0.0, 0.0, 0.0))
    return ArmPose(eef_pos=p, eef_force=(0.0, 0.0, 0.0), eef_rot=rot)


def reach_states(reach: ReachLimit) -> st.SearchStrategy[RobotState]:
    return st.tuples(*[reach_arm(reach, i) for i in range(len(reach.centres))]).map(lambda a: RobotState(arms=a))


def reach_actions(dim: int, reach: ReachLimit) -> st.SearchStrategy[list[float]]:
    """Mostly moderate components, with the values the check clamps and restores to."""
    rs, creep = reach.restore, reach.creep
    comp = st.one_of(
        st.floats(-1.0, 1.0),
        near_edges(0.0, rs, -rs, creep, -creep, spread=0.01),
        st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-300, -5e-324, 1e6, -1e6]),
    )
    return st.one_of(actions(dim), st.lists(comp, min_size=dim, max_size=dim))


@pytest.mark.parametrize("name", list(PAIRS))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_at_the_edges(name: str, data: st.DataObject) -> None:
    pair, reach = PAIRS[name], LIMIT_OF[name]
    pair.check(data.draw(reach_states(reach)), data.draw(reach_actions(pair.kernel.layout.dim, reach)))


@pytest.mark.parametrize("name", ["approach", "t1", "t6"])
@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_kernel_matches_python_anywhere(name: str, data: st.DataObject) -> None:
    pair = PAIRS[name]
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


def test_the_kernel_decides_the_common_cases_itself() -> None:
    """A port that always fell back would pass the tests above while doing nothing."""
    rng = random.Random(11)
    for pair, reach in ((Pair(Phi((T1,)), SINGLE_PANDA), T1), (Pair(Phi((T6,)), TWO_ARM_NO_GRIPPER), T6)):
        decided = modified = 0
        for _ in range(600):
            arms = []
            for c in reach.centres:
                # Around the whole working range, including the braking band, beyond the reach and the column.
                theta, rho, dz = rng.uniform(0, 2 * math.pi), rng.uniform(0.0, 0.9), rng.uniform(-0.6, 0.4)
                p = (c[0] + rho * math.cos(theta), c[1] + rho * math.sin(theta), c[2] + dz)
                q = [rng.gauss(0, 1) for _ in range(4)]
                arms.append(ArmPose(eef_pos=p, eef_force=(0.0, 0.0, 0.0), eef_rot=rotation(q)))
            state = RobotState(arms=tuple(arms))
            action = [rng.uniform(-1.0, 1.0) for _ in range(pair.kernel.layout.dim)]
            r = pair.kernel._program(state.arms, action)
            decided += r is not None
            modified += isinstance(r, tuple)
            pair.check(state, action)
        assert decided == pair.calls == pair.handled == 600
        assert modified > 100  # the braking and restoring paths were decided in C too
