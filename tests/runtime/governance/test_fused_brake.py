"""brake_along in the fused kernel (csrc/brake.c), reached through contact_approach states.

Its rare branches need odd inputs: squares of the normal's components that underflow (the
scaling branch, with a bound already met by what is left or not), an action parallel to the
normal (components that reach 0 together) and components that stop at 0 before the rest (the
removal loop). A tracer on the Python ``brake_along`` proves the inputs below reach each branch.
"""

from __future__ import annotations

import inspect
import random
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from fused_support import Pair
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import ContactApproach, Phi
from capevo.runtime.governance.brake import brake_along
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import DOWN
from capevo.runtime.governance.proximity import FIXED, ArmScene
from capevo.runtime.state import SINGLE_PANDA, RobotState

ZERO = ContactApproach(touch=0.0, touch_loose=0.0)  # q = 0 at the clearance: every approach is braked
TINY = ContactApproach(touch=1e-17, touch_loose=1e-17)  # a bound below the rounding of a closing speed
RULES = [ZERO, TINY, ContactApproach()]
PAIRS = [Pair(Phi((rule,)), SINGLE_PANDA) for rule in RULES]
TWO = Pair(Phi((ZERO,)), TWO_ARM_NO_GRIPPER)

_CODE = brake_along.__code__
_LINES, _FIRST = inspect.getsourcelines(brake_along)


def _line(text: str) -> int:
    (n,) = [_FIRST + k for k, line in enumerate(_LINES) if line.strip().startswith(text)]
    return n


SCALE = _line("f = q / c * SHRINK")
STEP = _line("arm[k] = v if v * arm[k] > 0.0 else 0.0")
REMOVE = _line("arm[k0] = 0.0")


@contextmanager
def branches() -> Iterator[set[str]]:
    """The branches of the Python ``brake_along`` taken inside the block."""
    hit: set[str] = set()

    def local(frame: FrameType, event: str, arg: Any) -> Callable[..., Any]:
        if event == "line":
            f = frame.f_locals
            if frame.f_lineno == SCALE:
                hit.add("scale" if f["c"] > f["q"] else "keep")
            elif frame.f_lineno == STEP:
                hit.add("step" if f["v"] * f["arm"][f["k"]] > 0.0 else "together")
            elif frame.f_lineno == REMOVE:
                hit.add("remove")
        return local

    def tracer(frame: FrameType, event: str, arg: Any) -> Callable[..., Any] | None:
        return local if frame.f_code is _CODE else None

    old = sys.gettrace()
    sys.settrace(tracer)
    try:
        yield hit
    finally:
        sys.settrace(old)


def state(*pairs: tuple[float, ...]) -> RobotState:
    return RobotState(arms=(ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=pairs),))


def near(dist: float, n: tuple[float, float, float], owner: int = FIXED) -> tuple[float, ...]:
    return (dist, *n, 0.0, 0.0, 0.0, owner)


EXAMPLES = [
    # All approaching components' squares underflow: one factor for all, here 0.
    ("scale", PAIRS[0], state(near(0.0, (1e-200, 0.0, -1.0))), [1.0, 0.3, 0.5, 0.0, 0.0, 0.0, 0.0]),
    # Two components stop at 0, the rounding left over is more than the tiny third one closes: kept.
    (
        "keep",
        PAIRS[1],
        state(near(0.0, (0.06310682188770933, 0.11791870367106105, 1e-200))),
        [0.5692038748222122, 0.8022650611681835, 0.784866200421318, 0.0, 0.0, 0.0, 0.0],
    ),
    # Straight at the geom with a bound of 0: components reach 0 at once and cross it by rounding.
    (
        "together",
        PAIRS[0],
        state(near(0.0, (-0.5814251598383926, -0.6584721716563602, -0.19250548625510033))),
        [-0.24403812256385138, -0.2763766063653398, -0.0807991822404, 0.0, 0.0, 0.0, 0.0],
    ),
    # A component that would cross 0 stops there and the others share the rest.
    ("remove", PAIRS[2], state(near(0.0, (0.6, 0.8, 0.0))), [0.01, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
]


def test_each_rare_branch_matches_python() -> None:
    for name, pair, s, a in EXAMPLES:
        assert pair.kernel._program(s.arms, a) is not None, name  # decided in C, not by fallback
        with branches() as hit:
            pair.check(s, a)
        assert name in hit, (name, hit)


SMALL = st.one_of(st.floats(-1.0, 1.0), st.sampled_from([0.0, -0.0, 1e-200, -1e-170, 1e-162, 5e-324]))


@st.composite
def brake_cases(draw: st.DrawFn, n_arms: int) -> tuple[RobotState, list[float]]:
    """Pairs at or within the clearance (the smallest bound) with odd normals, and actions along them."""
    arms = []
    a: list[float] = []
    for _ in range(n_arms):
        pairs = []
        for _ in range(draw(st.integers(1, 3))):
            n = draw(st.tuples(SMALL, SMALL, SMALL))
            dist = draw(st.sampled_from([0.0, 0.005, -0.01, 0.02]))
            pairs.append((dist, *n, 0.0, 0.0, 0.0, draw(st.sampled_from([FIXED, *range(n_arms)]))))
        arms.append(ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=tuple(pairs)))
        t = draw(st.one_of(st.sampled_from([1.0, -1.0, 2.0, 1e170]), st.floats(-3.0, 3.0)))
        _, nx, ny, nz, *_ = draw(st.sampled_from(pairs))
        arm = [t * nx, t * ny, t * nz] if draw(st.booleans()) else [draw(SMALL) for _ in range(3)]
        a += arm + [draw(SMALL) for _ in range(3)]
    if n_arms == 1:
        a.append(draw(SMALL))
    return RobotState(arms=tuple(arms)), a


@settings(max_examples=75, deadline=None)
@given(data=st.data())
def test_kernel_brakes_as_python(data: st.DataObject) -> None:
    pair = data.draw(st.sampled_from([*PAIRS, TWO]))
    pair.check(*data.draw(brake_cases(len(pair.kernel.layout.arms))))


def test_random_brake_states_reach_every_branch() -> None:
    rng = random.Random(0)
    seen: set[str] = set()
    pair = Pair(Phi((ZERO,)), SINGLE_PANDA)
    for _ in range(600):
        v = [rng.choice([rng.uniform(-1, 1), rng.uniform(-1, 1), 1e-200, 0.0]) for _ in range(3)]
        n = tuple(v)
        t = rng.uniform(-2, 2)
        a = [t * n[0], t * n[1], t * n[2]] if rng.random() < 0.7 else [rng.uniform(-1, 1) for _ in range(3)]
        s = state(near(rng.choice([0.0, 0.003]), n))
        with branches() as hit:
            pair.check(s, [*a, rng.uniform(-1, 1), 0.0, 0.0, 0.0])
        seen |= hit
    assert {"scale", "together", "remove", "step"} <= seen, seen
    assert pair.handled == pair.calls
