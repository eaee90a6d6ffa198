"""Shared strategies and an independent statement of every constraint's invariant, for the governance tests.

The checks here restate the rules from the spec, not from the implementation, so a test
that compares the two can fail.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from hypothesis import strategies as st

from capevo.runtime.governance import ContactForce, ForbiddenZone, Phi, VelocityCap, WorkspaceBox
from capevo.runtime.state import ActionLayout, ArmState, RobotState

FINITE = st.floats(allow_nan=False, allow_infinity=False)
"""Every finite float, including ±1.8e308 and subnormals."""
SMALL = st.floats(min_value=-3.0, max_value=3.0, allow_nan=False)
ANY_FLOAT = st.floats()
"""Every float, NaN and ±inf included."""

# Coordinates near the default box's faces and margins, so hypothesis probes the edges.
_EDGES = [-0.6, -0.52, 0.52, 0.6, 0.6 + 0.08, 1.3 - 0.08, 1.3, 0.0, 1.0]
POS = st.one_of(st.floats(min_value=-1.5, max_value=2.5, allow_nan=False), st.sampled_from(_EDGES), FINITE)
FORCE = st.one_of(
    st.floats(min_value=-60.0, max_value=60.0, allow_nan=False),
    st.sampled_from([0.0, 20.0, -20.0, 11.547005383792516, 25.0]),
    FINITE,
)
ACTION_COMPONENT = st.one_of(SMALL, FINITE, st.sampled_from([0.0, 1.0, -1.0, 1.5, -0.0]))


def vec3(elem: st.SearchStrategy[float]) -> st.SearchStrategy[tuple[float, float, float]]:
    return st.tuples(elem, elem, elem)


def arm_states(pos: st.SearchStrategy[float] = POS, force: st.SearchStrategy[float] = FORCE) -> st.SearchStrategy:
    return st.builds(lambda p, f: ArmState(eef_pos=p, eef_force=f), vec3(pos), vec3(force))


def robot_states(n_arms: int, **kw: st.SearchStrategy[float]) -> st.SearchStrategy[RobotState]:
    return st.lists(arm_states(**kw), min_size=n_arms, max_size=n_arms).map(lambda arms: RobotState(arms=tuple(arms)))


def actions(dim: int, elem: st.SearchStrategy[float] = ACTION_COMPONENT) -> st.SearchStrategy[list[float]]:
    return st.lists(elem, min_size=dim, max_size=dim)


def state_of(*arms: tuple[Sequence[float], Sequence[float]]) -> RobotState:
    """A RobotState from ``(pos, force)`` pairs."""
    return RobotState(arms=tuple(ArmState(eef_pos=tuple(p), eef_force=tuple(f)) for p, f in arms))


def to_world(action: Sequence[float], layout: ActionLayout, frames: Sequence[Sequence[float]] | None) -> list[float]:
    """The action with each arm's translation rotated by its frame (world = R @ local)."""
    out = list(action)
    if frames is None:
        return out
    for arm, r in zip(layout.arms, frames, strict=True):
        o = arm.offset
        x, y, z = action[o : o + 3]
        out[o : o + 3] = [
            r[0] * x + r[1] * y + r[2] * z,
            r[3] * x + r[4] * y + r[5] * z,
            r[6] * x + r[7] * y + r[8] * z,
        ]
    return out


def violations(
    phi: Phi,
    layout: ActionLayout,
    state: RobotState,
    action: Sequence[float],
    *,
    frames: Sequence[Sequence[float]] | None = None,
    tol: float = 0.0,
) -> list[str]:
    """Every way ``action`` breaks a rule of ``phi`` in ``state`` (signs judged in the world frame)."""
    a = to_world(action, layout, frames)
    out: list[str] = []
    for c in phi.constraints:
        for i, (arm, lay) in enumerate(zip(state.arms, layout.arms, strict=True)):
            o = lay.offset
            p, f = arm.eef_pos, arm.eef_force
            if isinstance(c, WorkspaceBox):
                for k in range(3):
                    if p[k] >= c.high[k] - c.margin and a[o + k] > tol:
                        out.append(f"{c.label}: arm {i} moves out through +{k} at {p[k]}")
                    if p[k] <= c.low[k] + c.margin and a[o + k] < -tol:
                        out.append(f"{c.label}: arm {i} moves out through -{k} at {p[k]}")
            elif isinstance(c, VelocityCap):
                n2 = sum(x * x for x in action[o : o + 6])
                if not n2 <= c.max_norm**2:
                    out.append(f"{c.label}: arm {i} norm² {n2} above {c.max_norm**2}")
            elif isinstance(c, ContactForce):
                if sum(x * x for x in f) > c.max_force**2:
                    for k in range(3):
                        if f[k] != 0.0 and a[o + k] * math.copysign(1.0, f[k]) < -tol:
                            out.append(f"{c.label}: arm {i} pushes into the contact along {k}")
                    if sum(a[o + k] * f[k] for k in range(3)) < -tol * (1 + math.hypot(*f)):
                        out.append(f"{c.label}: arm {i} a·f < 0")
            elif isinstance(c, ForbiddenZone):
                for z in c.boxes:
                    lo = [v - c.margin for v in z.low]
                    hi = [v + c.margin for v in z.high]
                    if not all(lo[k] <= p[k] <= hi[k] for k in range(3)):
                        continue
                    inside = all(z.low[k] <= p[k] <= z.high[k] for k in range(3))
                    for k in range(3):
                        centre = (z.low[k] + z.high[k]) / 2
                        below = p[k] < centre if inside else p[k] < z.low[k]
                        above = p[k] > centre if inside else p[k] > z.high[k]
                        if (below and a[o + k] > tol) or (above and a[o + k] < -tol):
                            out.append(f"{c.label}: arm {i} moves into a zone along {k}")
    return out


def finite_state(state: RobotState) -> bool:
    return all(math.isfinite(v) for arm in state.arms for v in (*arm.eef_pos, *arm.eef_force))
