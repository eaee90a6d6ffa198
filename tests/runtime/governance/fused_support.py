"""Equivalence of the fused C kernel with the Python checks it was ported from.

The Python checks are the specification: a governor running the kernel must return what a
governor running the Python checks returns, bit for bit (signed zeros and float types
included), with the same interventions and counters. :func:`assert_same` checks one call;
the strategies draw the states the kernel reads (positions, forces, orientations and
proximity pairs), biased towards the edges where checks branch.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any

from govcheck import QUATS, rotation
from hypothesis import strategies as st

from capevo.runtime.governance import Governor, Phi
from capevo.runtime.governance.pose import DOWN, ArmPose
from capevo.runtime.governance.proximity import ArmScene
from capevo.runtime.state import ActionLayout, ArmState, RobotState

# Rotations whose entries are exact (the frames of T6's arms, gripper down, turned about z).
SIGNED_PERMUTATIONS: tuple[tuple[float, ...], ...] = (
    DOWN,
    (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
    (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    (0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    (0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0),
)
COMPONENT = st.one_of(
    st.floats(-2.0, 2.0),
    st.sampled_from([0.0, -0.0, 1.0, -1.0, 1.5, -1.5, 0.04, -0.04, 1e-300, 5e-324]),
    st.floats(-1e6, 1e6),
)
"""Action components: the usual range, exact values the checks compare against, and extremes."""


def near_edges(*edges: float, spread: float = 0.05) -> st.SearchStrategy[float]:
    """Floats at, just beside and around the given values."""
    return st.one_of(
        st.sampled_from(edges),
        st.sampled_from(edges).flatmap(lambda e: st.floats(e - spread, e + spread)),
        st.sampled_from(edges).map(lambda e: math.nextafter(e, math.inf)),
        st.sampled_from(edges).map(lambda e: math.nextafter(e, -math.inf)),
    )


COORD = st.one_of(st.floats(-1.0, 2.0), near_edges(-0.6, -0.52, 0.52, 0.6, 0.68, 0.8, 0.82, 0.9, 1.22, 1.3))
FORCE = st.one_of(st.floats(-40.0, 40.0), near_edges(0.0, 10.0, 20.0, -20.0, spread=2.0))


@st.composite
def unit(draw: st.DrawFn) -> tuple[float, float, float]:
    if draw(st.booleans()):
        return draw(st.sampled_from([(0.0, 0.0, -1.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)]))
    x, y, z = draw(st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda v: sum(c * c for c in v) > 0.01))
    n = math.sqrt(x * x + y * y + z * z)
    return (x / n, y / n, z / n)


@st.composite
def near_pairs(draw: st.DrawFn, n_arms: int) -> tuple[tuple[Any, ...], ...]:
    """Proximity pairs as ProximitySensor reports them: (dist, n, r, owner)."""
    out = []
    for _ in range(draw(st.integers(0, 5))):
        dist = draw(st.one_of(st.floats(-0.01, 0.12), near_edges(0.0, 0.005, 0.105, 0.11, spread=0.003)))
        nx, ny, nz = draw(unit())
        r = draw(st.tuples(*[st.floats(-0.3, 0.3) for _ in range(3)]))
        owner = draw(st.sampled_from([-2, -1, *range(n_arms)]))
        out.append((dist, nx, ny, nz, *r, owner))
    return tuple(out)


@st.composite
def arm_scenes(draw: st.DrawFn, n_arms: int, coord: st.SearchStrategy[float] = COORD) -> ArmState:
    """An ArmState, ArmPose or ArmScene, as tasks report them."""
    p = (draw(coord), draw(coord), draw(coord))
    f = (draw(FORCE), draw(FORCE), draw(FORCE))
    kind = draw(st.sampled_from(["state", "pose", "scene", "scene"]))
    if kind == "state":
        return ArmState(eef_pos=p, eef_force=f)
    rot = draw(st.one_of(st.sampled_from(SIGNED_PERMUTATIONS), QUATS.map(rotation)))
    if kind == "pose":
        return ArmPose(eef_pos=p, eef_force=f, eef_rot=rot)
    return ArmScene(eef_pos=p, eef_force=f, eef_rot=rot, near=draw(near_pairs(n_arms)))


def robot_states(n_arms: int, coord: st.SearchStrategy[float] = COORD) -> st.SearchStrategy[RobotState]:
    return st.lists(arm_scenes(n_arms, coord), min_size=n_arms, max_size=n_arms).map(
        lambda arms: RobotState(arms=tuple(arms))
    )


def actions(dim: int) -> st.SearchStrategy[list[float]]:
    return st.lists(COMPONENT, min_size=dim, max_size=dim)


def bits(x: Any) -> Any:
    """A float as (type, its 8 bytes); anything else as is. Tells -0.0 from 0.0."""
    return (type(x), struct.pack("<d", x)) if isinstance(x, float) else (type(x), x)


def same_vector(a: Sequence[Any] | None, b: Sequence[Any] | None) -> bool:
    if a is None or b is None:
        return a is b
    return type(a) is type(b) and len(a) == len(b) and all(bits(x) == bits(y) for x, y in zip(a, b, strict=True))


class Pair:
    """A kernel governor and a Python-checks governor of one Φ, layout and frames."""

    def __init__(
        self,
        phi: Phi,
        layout: ActionLayout,
        *,
        frames: Sequence[Sequence[float]] | None = None,
        enforce: bool = True,
    ) -> None:
        self.kernel = Governor(phi, layout, frames=frames, enforce=enforce)
        self.python = Governor(phi, layout, frames=frames, enforce=enforce, kernel=False)
        assert self.kernel._program is not None, "the kernel did not take this Φ (not built, or a kind not ported)"
        self.calls = 0
        self.handled = 0
        """Calls the kernel decided itself (not a fallback to the Python checks)."""

    def check(self, state: RobotState, action: Any) -> None:
        """Both governors give the same answer for ``(state, action)``, to the bit."""
        self.calls += 1
        if self.kernel._program(state.arms, action, self.kernel.enforce) is not None:
            self.handled += 1
        got, got_ivs = self.kernel(state, action)
        want, want_ivs = self.python(state, action)
        assert (got is action and want is action) or same_vector(got, want), (got, want)
        assert len(got_ivs) == len(want_ivs), (got_ivs, want_ivs)
        for g, w in zip(got_ivs, want_ivs, strict=True):
            assert (g.constraint, g.reason, g.enforced) == (w.constraint, w.reason, w.enforced), (g, w)
            assert same_vector(g.original, w.original), (g.original, w.original)
            assert same_vector(g.result, w.result), (g.result, w.result)
        assert self.kernel.stats() == self.python.stats()
