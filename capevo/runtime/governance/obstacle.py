"""obstacle_approach: speed-and-separation between the hand and known fixed obstacles (bin walls, pegs).

A rigid obstacle struck at speed reads hundreds of newtons within one control step, before the
reactive force limit can do anything. This rule slows the hand down as it nears each obstacle,
so a contact, if it happens, starts slowly enough for the force ramp to hold it under the limit.

The hand is boxes in the end-effector site frame (``hand``, as for ``surface_approach``),
each turned by the arm's orientation (:attr:`ArmPose.eef_rot`; an arm state without one is
taken as :data:`~capevo.runtime.governance.pose.DOWN`) and bounded by its own world-frame
axis-aligned box ``[hl, hh]`` (boxes kept apart, so the wide hand body above the narrow fingers
does not make one wide box reaching down to the fingertips). Per arm, hand box and obstacle
box ``[lo, hi]`` (world frame):

* separation per axis: ``s_k = lo_k − hh_k`` with side ``+1`` when the hand is entirely below
  the obstacle on axis ``k``, ``s_k = hl_k − hi_k`` with side ``−1`` when entirely above, else
  ``s_k = 0`` (side 0); ``dist = |s|``, the distance between the two boxes.
* while ``dist < clearance + brake``, with ``q = max(0, dist − clearance) / brake``: each
  component moving towards the obstacle (``a_k · side_k > 0``) is limited in magnitude to
  ``q · dist / (s_x + s_y + s_z)``, so the closing speed ``Σ a_k · side_k · s_k / dist`` is at
  most ``q`` (one bound for all axes, so moving over a wall is not blocked by the wall's tiny
  horizontal separation);
  with ``rotation`` every rotation component is limited to ``q`` too (turning swings the hand's
  far corners).
* if the boxes overlap (``dist == 0``: touching, or the bounding box is loose for a tilted
  hand), components towards the obstacle's centre are zeroed (the hand can only leave) and, with
  ``rotation``, so is rotation.

With ``arm`` set, the rule applies to that arm only (arms holding different things have
different hands: one constraint per arm).

Invariants (per governed arm, hand box and obstacle, after the check, with the quantities above):
1. ``0 < dist < clearance + brake`` implies ``|a_k| <= q · dist / (s_x + s_y + s_z)`` for every
   axis with ``a_k · side_k > 0`` (``brake == 0``: 0 once ``dist <= clearance``).
2. ``dist == 0`` implies ``a_k == 0`` or ``a_k`` points away from the obstacle's centre on each axis.
3. With ``rotation``, ``dist < clearance + brake`` implies ``|ω_k| <= q`` (0 when ``dist == 0``).
4. Only those components change (clamped); an action no rule touches is allowed (None) and
   never copied.
5. A non-finite end-effector position or orientation of an arm near an obstacle is ⊥ with a reason.
6. No hard limit of its own (:meth:`ObstacleApproach.unsafe` is None).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from capevo.errors import Invalid
from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.hand import box_gap, hand_reach
from capevo.runtime.governance.pose import finite_rotation_or_down, rotation_of
from capevo.runtime.governance.zone import Aabb
from capevo.runtime.state import ActionLayout, ArmState

Vec3 = tuple[float, float, float]


def extent_of(hand: Sequence[Aabb]) -> Callable[[Sequence[float]], tuple[Vec3, Vec3]]:
    """:func:`~capevo.runtime.governance.hand.hand_extent` of ``hand`` as a function of the rotation.

    The boxes' centres and half sizes are computed once; per call the operations are
    ``hand_extent``'s, in its order (``x < lo`` where it takes ``min(lo, x)``), so the result is
    the same to the bit, NaN included.
    """
    shapes = tuple(
        (
            tuple((box.low[j] + box.high[j]) / 2 for j in range(3)),
            tuple((box.high[j] - box.low[j]) / 2 for j in range(3)),
        )
        for box in hand
    )
    if not shapes:
        zero: tuple[Vec3, Vec3] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        return lambda rot: zero
    inf = math.inf

    def extent(rot: Sequence[float]) -> tuple[Vec3, Vec3]:
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = rot[:9]
        a0, a1, a2, a3, a4, a5, a6, a7, a8 = map(abs, rot[:9])
        lo0 = lo1 = lo2 = inf
        hi0 = hi1 = hi2 = -inf
        for (c0, c1, c2), (h0, h1, h2) in shapes:
            m, e = r0 * c0 + r1 * c1 + r2 * c2, a0 * h0 + a1 * h1 + a2 * h2
            if m - e < lo0:
                lo0 = m - e
            if m + e > hi0:
                hi0 = m + e
            m, e = r3 * c0 + r4 * c1 + r5 * c2, a3 * h0 + a4 * h1 + a5 * h2
            if m - e < lo1:
                lo1 = m - e
            if m + e > hi1:
                hi1 = m + e
            m, e = r6 * c0 + r7 * c1 + r8 * c2, a6 * h0 + a7 * h1 + a8 * h2
            if m - e < lo2:
                lo2 = m - e
            if m + e > hi2:
                hi2 = m + e
        return (lo0, lo1, lo2), (hi0, hi1, hi2)

    return extent


@register("obstacle_approach")
@dataclass(frozen=True, slots=True, kw_only=True)
class ObstacleApproach(ConstraintBase):
    """Motion towards fixed world-frame boxes limited in proportion to the hand's distance from them.

    Args:
        boxes: The obstacles, each ``{low: [x, y, z], high: [x, y, z]}``, world frame, metres.
        hand: Boxes covering the hand in the end-effector site frame; none means the site point.
        clearance: Distance in metres at which motion towards an obstacle reaches 0; >= 0.
        brake: Width in metres of the band beyond the clearance over which it is limited; >= 0.
        rotation: Also limit the rotation components near an obstacle.
        arm: Index of the one arm (in the layout's order) this applies to, e.g. the arm whose
            hand holds what ``hand`` describes; None for every arm.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on no boxes, a bad box, a negative arm index, clearance or
            brake; and, when compiled, an arm index the layout does not have.
    """

    boxes: tuple[Aabb, ...]
    hand: tuple[Aabb, ...] = ()
    clearance: float = 0.01
    brake: float = 0.1
    rotation: bool = True
    arm: int | None = None
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if self.arm is not None and self.arm < 0:
            raise invalid("arm", f"must be >= 0, got {self.arm}")
        if not self.boxes:
            raise invalid("boxes", "at least one box is required")
        if self.clearance < 0:
            raise invalid("clearance", f"must be >= 0, got {self.clearance}")
        if self.brake < 0:
            raise invalid("brake", f"must be >= 0, got {self.brake}")

    def compile(self, layout: ActionLayout) -> Check:
        hand, cl, br, turn = self.hand, self.clearance, self.brake, self.rotation
        grow = hand_reach(hand) + cl + br
        # Per obstacle: its box, its centre, and the box the site must be in for the rule to apply.
        obstacles = tuple(
            (
                o.low,
                o.high,
                tuple((lo + hi) / 2 for lo, hi in zip(o.low, o.high, strict=True)),
                tuple(v - grow for v in o.low),
                tuple(v + grow for v in o.high),
            )
            for o in self.boxes
        )
        gl = tuple(min(o[3][k] for o in obstacles) for k in range(3))
        gh = tuple(max(o[4][k] for o in obstacles) for k in range(3))
        if self.arm is not None and self.arm >= len(layout.arms):
            raise Invalid(
                f"arm: {self.arm} is not an arm of a layout with {len(layout.arms)} arm(s)", details={"field": "arm"}
            )
        which = range(len(layout.arms)) if self.arm is None else (self.arm,)
        offsets = tuple((i, layout.arms[i].offset) for i in which)
        reasons = tuple(
            tuple(f"arm {i}: hand near obstacle {j}: motion towards it braked" for j in range(len(obstacles)))
            for i in range(len(layout.arms))
        )
        isfinite, inf = math.isfinite, math.inf
        band = cl + br
        flat = tuple((j, *o[3], *o[4]) for j, o in enumerate(obstacles))
        # Each hand box separately: a wide hand body above narrow fingers is not one big box.
        parts = tuple(extent_of((box,)) for box in hand) or (extent_of(()),)

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, o in offsets:
                arm = arms[i]
                p = arm.eef_pos
                px, py, pz = p[0], p[1], p[2]
                if not (isfinite(px) and isfinite(py) and isfinite(pz)):
                    return None, f"arm {i}: end-effector position {p} is not finite"  # rare: format here
                near = [j for j, lx, ly, lz, hx, hy, hz in flat if lx <= px <= hx and ly <= py <= hy and lz <= pz <= hz]
                if not near:
                    continue
                rot = finite_rotation_or_down(arm)
                if rot is None:
                    return None, f"arm {i}: end-effector orientation {rotation_of(arm)} is not finite"
                hulls = []
                for extent in parts:
                    (l0, l1, l2), (h0, h1, h2) = extent(rot)
                    hulls.append(((px + l0, py + l1, pz + l2), (px + h0, py + h1, pz + h2)))
                src = a if b is None else b
                arm_a = list(src[o : o + 6])
                q_rot = inf
                hit: list[str] = []
                for j in near:
                    lo, hi, centre, _, _ = obstacles[j]
                    for hl, hh in hulls:
                        dist, s, sides = box_gap(hl, hh, lo, hi)
                        if dist >= band and dist > cl:
                            continue
                        q = (dist - cl) / br if br > 0.0 and dist > cl else 0.0
                        changed = False
                        if dist > 0.0:
                            # One bound for every approaching axis: the closing speed sum(a_k * s_k / dist)
                            # is then at most q, and an axis with little separation is not starved.
                            bound = q * dist / (s[0] + s[1] + s[2])
                            for k in (0, 1, 2):
                                v, side = arm_a[k], sides[k]
                                if side and v * side > 0.0 and abs(v) > bound:
                                    arm_a[k] = bound * side
                                    changed = True
                        else:
                            for k in (0, 1, 2):
                                v = arm_a[k]
                                mid = (hl[k] + hh[k]) / 2
                                if (v > 0.0 and mid < centre[k]) or (v < 0.0 and mid > centre[k]):
                                    arm_a[k] = 0.0
                                    changed = True
                        if turn and q < q_rot:
                            q_rot = q
                        if changed and reasons[i][j] not in hit:
                            hit.append(reasons[i][j])
                if turn and q_rot < inf:
                    for k in (3, 4, 5):
                        v = arm_a[k]
                        if abs(v) > q_rot:
                            arm_a[k] = q_rot if v > 0.0 else -q_rot
                            if not hit:
                                hit.append(reasons[i][near[0]])
                if any(arm_a[j] != src[o + j] for j in range(6)):
                    if b is None:
                        b = list(a)
                    b[o : o + 6] = arm_a
                    notes.extend(hit)
            return edited(b, notes)

        glx, gly, glz = gl
        ghx, ghy, ghz = gh

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for i, _ in offsets:
                x, y, z = arms[i].eef_pos
                # "Provably clear of every obstacle", so NaN falls through to the slow path.
                if not (x < glx or x > ghx or y < gly or y > ghy or z < glz or z > ghz):
                    return slow(arms, a)
            return None

        return check
