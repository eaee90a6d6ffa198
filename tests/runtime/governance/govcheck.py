"""Shared strategies and an independent statement of every constraint's invariant, for the governance tests.

The checks here restate the rules from the spec, not from the implementation, so a test
that compares the two can fail.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from hypothesis import strategies as st

from capevo.runtime.governance import (
    ArmSeparation,
    ContactApproach,
    ContactForce,
    ForbiddenZone,
    ForceRamp,
    ObstacleApproach,
    Phi,
    ReachLimit,
    SurfaceApproach,
    VelocityCap,
    WorkspaceBox,
    WorkspaceGuard,
)
from capevo.runtime.governance.pose import DOWN, ArmPose
from capevo.runtime.governance.separation import CENTRE_TIE
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

QUATS = st.tuples(*[st.floats(-1, 1) for _ in range(4)]).filter(lambda q: sum(c * c for c in q) > 0.1)
"""Unnormalized quaternions far enough from 0 to normalize; :func:`rotation` turns them into matrices."""


def rotation(q: tuple[float, float, float, float]) -> tuple[float, ...]:
    """The row-major rotation matrix of the quaternion ``q`` (w, x, y, z), normalized first."""
    w, x, y, z = (v / math.sqrt(sum(c * c for c in q)) for v in q)
    return (
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    )  # fmt: skip


NEGLIGIBLE = 1e-12
"""A vector component this small relative to the vector's length is rounding, not a direction."""


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
            elif isinstance(c, WorkspaceGuard):
                near = False
                for k in range(3):
                    for d, s in ((c.high[k] - p[k], 1.0), (p[k] - c.low[k], -1.0)):
                        if d <= c.margin:
                            near = True
                        if d < c.margin + c.brake or d <= c.margin:
                            bound = max(0.0, (d - c.margin) / c.brake) if c.brake > 0 else 0.0
                            if a[o + k] * s > bound + tol:
                                out.append(f"{c.label}: arm {i} outward {a[o + k] * s} > {bound} along {k}")
                        if c.restore > 0 and 0.0 <= d < c.restore_within:
                            push = c.restore * (1.0 - d / c.restore_within)
                            if a[o + k] * s > -push + tol:
                                out.append(f"{c.label}: arm {i} {d} m inside a face, not steered back at {push}")
                if c.freeze_rotation and near and any(a[o + j] != 0.0 for j in (3, 4, 5)):
                    out.append(f"{c.label}: arm {i} turns within the margin")
            elif isinstance(c, ForceRamp):
                n = math.hypot(*f)
                if c.soft_from < n <= c.max_force:
                    bound = c.speed * (c.max_force - n) / (c.max_force - c.soft_from)
                    for k in range(3):
                        if a[o + k] * f[k] < 0 and abs(a[o + k]) > bound + tol:
                            out.append(f"{c.label}: arm {i} pushes {a[o + k]} into a {n} N contact along {k}")
                elif n > c.max_force:
                    for k in range(3):
                        if f[k] != 0.0 and a[o + k] * math.copysign(1.0, f[k]) < -tol:
                            out.append(f"{c.label}: arm {i} pushes into a {n} N contact along {k}")
            elif isinstance(c, SurfaceApproach):
                rot = arm_rot(arm)
                low = min(
                    (sum(rot[6 + j] * corner[j] for j in range(3)) for box in c.hand for corner in corners(box)),
                    default=0.0,
                )
                gap = p[2] + low - (c.height + c.clearance)
                if gap < c.brake or gap <= 0:
                    q = max(0.0, gap) / c.brake if c.brake > 0 else 0.0
                    if a[o + 2] < -q - tol:
                        out.append(f"{c.label}: arm {i} descends {a[o + 2]} with bound {q}")
                    if c.rotation and any(abs(action[o + j]) > q + tol for j in (3, 4, 5)):
                        out.append(f"{c.label}: arm {i} turns faster than {q} near the surface")
                    if c.lateral is not None and any(abs(a[o + j]) > max(c.lateral, q) + tol for j in (0, 1)):
                        out.append(
                            f"{c.label}: arm {i} moves sideways faster than {max(c.lateral, q)} near the surface"
                        )
            elif isinstance(c, ReachLimit):
                centre = c.centres[i]
                rot = arm_rot(arm)
                w = [p[k] + sum(rot[3 * k + j] * c.point[j] for j in range(3)) for k in range(3)]
                v = [w[k] - centre[k] for k in range(3)]
                r = math.sqrt(sum(x * x for x in v))
                rho = math.hypot(p[0] - centre[0], p[1] - centre[1])
                column = c.min_radius > 0 and rho < c.min_radius + c.margin + c.brake
                d = c.max_radius - r
                if r > 0 and not column and (d < c.margin + c.brake or d <= c.margin):
                    q = max(0.0, (d - c.margin) / c.brake) if c.brake > 0 else 0.0
                    if d > 0:
                        q = max(q, c.creep)
                    # The outward speed: the components moving away from the centre, along u.
                    # A component that is pure rounding (reach_limit halves v against overflow,
                    # so a subnormal one becomes 0) sets no direction.
                    out_speed = sum(
                        a[o + k] * v[k] / r for k in range(3) if abs(v[k]) > NEGLIGIBLE * r and a[o + k] * v[k] > 0
                    )
                    if out_speed > q + tol:
                        out.append(f"{c.label}: arm {i} moves out at {out_speed} > {q} at r={r}")
                d = rho - c.min_radius
                h = [p[0] - centre[0], p[1] - centre[1]]
                if c.min_radius > 0 and rho > 0 and (d < c.margin + c.brake or d <= c.margin):
                    q = max(0.0, (d - c.margin) / c.brake) if c.brake > 0 else 0.0
                    bound = q * rho / (abs(h[0]) + abs(h[1]))
                    for k in range(2):
                        if abs(h[k]) <= NEGLIGIBLE * rho:
                            continue
                        if a[o + k] * h[k] < 0 and abs(a[o + k]) > bound + tol:
                            out.append(f"{c.label}: arm {i} moves towards its column {a[o + k]} > {bound}")
            elif isinstance(c, ObstacleApproach):
                if c.arm is not None and c.arm != i:
                    continue
                q_rot = math.inf
                for (hl, hh), box in ((hand_box((part,), arm), box) for part in c.hand or [None] for box in c.boxes):
                    s_, side = separation((hl, hh), (box.low, box.high))
                    dist = math.sqrt(sum(x * x for x in s_))
                    if not (dist < c.clearance + c.brake or dist <= c.clearance):
                        continue
                    q = max(0.0, dist - c.clearance) / c.brake if c.brake > 0 else 0.0
                    q_rot = min(q_rot, q)
                    if dist > 0:
                        bound = q * dist / sum(s_)
                        for k in range(3):
                            if side[k] and a[o + k] * side[k] > 0 and abs(a[o + k]) > bound + tol:
                                out.append(f"{c.label}: arm {i} approaches an obstacle {a[o + k]} > {bound}")
                    else:
                        for k in range(3):
                            mid, centre = (hl[k] + hh[k]) / 2, (box.low[k] + box.high[k]) / 2
                            if (a[o + k] > tol and mid < centre) or (a[o + k] < -tol and mid > centre):
                                out.append(f"{c.label}: arm {i} moves into an obstacle along {k}")
                if c.rotation and any(abs(action[o + j]) > q_rot + tol for j in (3, 4, 5)):
                    out.append(f"{c.label}: arm {i} turns faster than {q_rot} near an obstacle")
        if isinstance(c, ArmSeparation):
            out.extend(_separation_violations(c, layout, state, a, action, tol))
        if isinstance(c, ContactApproach):
            out.extend(_contact_violations(c, layout, state, a, action, tol))
    return out


def contact_bound(c: ContactApproach, dist: float, owner: int) -> float:
    """q for one pair, restated from the spec."""
    loose = owner == -2
    arm = owner >= 0 and c.touch_arm is not None
    touch = c.touch_loose if loose else c.touch_arm if arm else c.touch
    brake = c.brake_loose if loose and c.brake_loose is not None else c.brake
    x = min(1.0, max(0.0, (dist - c.clearance) / brake))
    return touch + (1.0 - touch) * x


def contact_turn(c: ContactApproach, q: float, dist: float) -> float:
    """The rotation floor for one pair, restated from the spec: ``touch_rotation`` ramped over the fixed band."""
    if c.touch_rotation is None:
        return q
    x = min(1.0, max(0.0, (dist - c.clearance) / c.brake))
    return min(q, c.touch_rotation + (1.0 - c.touch_rotation) * x)


def _contact_violations(
    c: ContactApproach, layout: ActionLayout, state: RobotState, a: list[float], action: Sequence[float], tol: float
) -> list[str]:
    out: list[str] = []
    for i, arm in enumerate(state.arms):
        rows = dict(getattr(arm, "link_rows", ()))
        for k_pair, (dist, nx, ny, nz, rx, ry, rz, owner) in enumerate(getattr(arm, "near", ())):
            q = contact_bound(c, dist, owner)
            q_down = contact_bound(c, dist, -1) if owner == -2 and nz < 0 else q
            pinned = q_down < q
            if q >= 1.0 and q_down >= 1.0:
                continue
            n = (nx, ny, nz)
            o = layout.arms[i].offset
            if k_pair in rows:
                # A wrist link: its closing speed is the row's, translation and rotation alike.
                g = rows[k_pair]
                closing = sum(a[o + k] * g[k] for k in range(6) if a[o + k] * g[k] > 0)
                if closing > q * (1 + 1e-9) + tol:
                    out.append(f"{c.label}: arm {i}'s link closes at {closing} > {q} on a pair {dist} m away")
                out += _other_arm_violations(c, layout, a, action, (i, owner), n, q, contact_turn(c, q, dist), tol)
                continue
            axes = (0, 1) if pinned else (0, 1, 2)
            closing = sum(a[o + k] * n[k] for k in axes if a[o + k] * n[k] > 0)
            if closing > q * (1 + 1e-9) + tol:
                out.append(f"{c.label}: arm {i} closes at {closing} > {q} on a pair {dist} m away")
            if pinned and a[o + 2] * nz > q_down * (1 + 1e-9) + tol:
                out.append(f"{c.label}: arm {i} pushes a loose object down at {a[o + 2] * nz} > {q_down}")
            q = min(q, q_down)
            qt = contact_turn(c, q, dist)
            if c.rotation:
                r = math.sqrt(rx * rx + ry * ry + rz * rz)
                qr = qt * min(1.0, c.lever / r) if r > 0 else qt
                if any(abs(action[o + j]) > qr + tol for j in (3, 4, 5)):
                    out.append(f"{c.label}: arm {i} turns faster than {qr} near a pair")
            out += _other_arm_violations(c, layout, a, action, (i, owner), n, q, qt, tol)
    return out


def _other_arm_violations(
    c: ContactApproach,
    layout: ActionLayout,
    a: list[float],
    action: Sequence[float],
    arms: tuple[int, int],
    n: tuple[float, float, float],
    q: float,
    qt: float,
    tol: float,
) -> list[str]:
    """Invariant 3: a pair of arm ``i`` whose other side is arm ``owner``'s closes no faster from there."""
    i, owner = arms
    if not 0 <= owner < len(layout.arms) or owner == i:
        return []
    out: list[str] = []
    p = layout.arms[owner].offset
    closing = sum(-a[p + k] * n[k] for k in range(3) if a[p + k] * n[k] < 0)
    if closing > q * (1 + 1e-9) + tol:
        out.append(f"{c.label}: arm {owner} closes at {closing} > {q} on arm {i}'s pair")
    if c.rotation and any(abs(action[p + j]) > qt + tol for j in (3, 4, 5)):
        out.append(f"{c.label}: arm {owner} turns faster than {qt} near arm {i}'s pair")
    return out


def _separation_violations(
    c: ArmSeparation, layout: ActionLayout, state: RobotState, a: list[float], action: Sequence[float], tol: float
) -> list[str]:
    out: list[str] = []
    boxes = [hand_box(c.hands[i], arm) for i, arm in enumerate(state.arms)]
    n = len(state.arms)
    for i in range(n):
        for j in range(i + 1, n):
            s_, side = separation(boxes[i], boxes[j])
            dist = math.sqrt(sum(x * x for x in s_))
            if not (dist < c.clearance + c.brake or dist <= c.clearance):
                continue
            q = max(0.0, dist - c.clearance) / c.brake if c.brake > 0 else 0.0
            if dist > 0:
                bound, rb = max(c.floor, q * dist / sum(s_)), max(c.floor, q)
            else:
                bound = rb = c.floor
                ci = [(lo + hi) / 2 for lo, hi in zip(*boxes[i], strict=True)]
                cj = [(lo + hi) / 2 for lo, hi in zip(*boxes[j], strict=True)]
                tie = CENTRE_TIE
                side = [1 if cj[k] > ci[k] + tie else -1 if cj[k] < ci[k] - tie else 0 for k in range(3)]
            for arm_index, sign in ((i, 1), (j, -1)):
                o = layout.arms[arm_index].offset
                for k in range(3):
                    if side[k] and a[o + k] * side[k] * sign > 0 and abs(a[o + k]) > bound + tol:
                        out.append(f"{c.label}: arm {arm_index} approaches arm {j if arm_index == i else i}")
                if c.rotation and any(abs(action[o + m]) > rb + tol for m in (3, 4, 5)):
                    out.append(f"{c.label}: arm {arm_index} turns faster than {rb} near the other hand")
    return out


def arm_rot(arm: ArmState) -> tuple[float, ...]:
    return arm.eef_rot if isinstance(arm, ArmPose) else DOWN


def corners(box) -> list[tuple[float, float, float]]:
    (x0, y0, z0), (x1, y1, z1) = box.low, box.high
    return [(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]


def hand_box(hand, arm: ArmState) -> tuple[list[float], list[float]]:
    """World box of every turned corner of ``hand`` around ``arm``'s end effector (brute force over corners)."""
    rot, p = arm_rot(arm), arm.eef_pos
    hand = [box for box in hand if box is not None]
    pts = [
        [p[k] + sum(rot[3 * k + j] * corner[j] for j in range(3)) for k in range(3)]
        for box in hand
        for corner in corners(box)
    ] or [list(p)]
    return [min(q[k] for q in pts) for k in range(3)], [max(q[k] for q in pts) for k in range(3)]


def separation(first, second) -> tuple[list[float], list[int]]:
    """Per-axis gap between two boxes and the side (+1: ``first`` is below ``second`` on that axis)."""
    (l1, h1), (l2, h2) = first, second
    s, side = [0.0, 0.0, 0.0], [0, 0, 0]
    for k in range(3):
        if h1[k] < l2[k]:
            s[k], side[k] = l2[k] - h1[k], 1
        elif h2[k] < l1[k]:
            s[k], side[k] = l1[k] - h2[k], -1
    return s, side


def finite_state(state: RobotState) -> bool:
    return all(math.isfinite(v) for arm in state.arms for v in (*arm.eef_pos, *arm.eef_force))
