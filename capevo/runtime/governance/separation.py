"""arm_separation: speed-and-separation between the hands (and what they hold) of different arms.

In a two-arm task the hands are each other's obstacles, and they must still be able to meet:
in peg_in_hole the peg has to go through the plate. So this rule never stops the approach, it
slows it: within ``clearance + brake`` of each other, the components moving one hand towards
the other are limited to a bound that falls with the distance but not below ``floor``, a push
gentle enough for the force ramp to keep any contact under the limit (with OSC, about 250 N
per action unit of push: 0.05 gives about 12 N).

Each arm's hand is boxes in its end-effector site frame (``hands``, one entry per arm), turned
by the arm's orientation (:attr:`ArmPose.eef_rot`, else :data:`~capevo.runtime.governance.pose.DOWN`)
and bounded by a world-frame box. Per pair of arms ``i < j``, with the per-axis separations
``s_k`` of the two boxes (0 where they overlap on that axis) and ``dist = |s|``:

* ``0 < dist < clearance + brake``: with ``q = max(0, dist − clearance) / brake`` and
  ``bound = max(floor, q · dist / (s_x + s_y + s_z))``, each component moving arm ``i`` towards
  arm ``j`` along a separated axis (and arm ``j`` towards ``i``) is limited in magnitude to ``bound``.
* ``dist == 0`` (the boxes overlap: touching, interleaved like a peg in its hole, or the boxes
  are loose): every component moving one hand's box centre towards the other's is limited to ``floor``.
* with ``rotation``, both arms' rotation components are limited to ``max(floor, q)`` (``floor``
  when overlapping).

Invariants (per pair within range, after the check):
1. ``0 < dist < clearance + brake``: every approaching component along a separated axis has
   magnitude ``<= max(floor, q · dist / (s_x + s_y + s_z))``.
2. ``dist == 0``: every component towards the other hand's box centre (along axes where the
   centres differ by more than :data:`CENTRE_TIE`) has magnitude ``<= floor``.
3. With ``rotation``, both arms' rotation components have magnitude ``<= max(floor, q)``
   (``floor`` when ``dist == 0``).
4. Only those components change (clamped); an action no rule touches is allowed (None) and
   never copied.
5. A non-finite position or orientation of an arm is ⊥ with a reason.
6. No hard limit of its own (:meth:`ArmSeparation.unsafe` is None).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.errors import Invalid
from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.hand import box_gap, hand_reach
from capevo.runtime.governance.obstacle import extent_of
from capevo.runtime.governance.pose import finite_rotation_or_down, rotation_of
from capevo.runtime.governance.zone import Aabb
from capevo.runtime.state import ActionLayout, ArmState

CENTRE_TIE = 1e-9
"""Overlapping boxes whose centres differ by at most this along an axis (metres) set no direction on it."""


@register("arm_separation")
@dataclass(frozen=True, slots=True, kw_only=True)
class ArmSeparation(ConstraintBase):
    """Approach between the arms' hands slowed with distance, down to a gentle floor speed.

    Args:
        hands: Per arm in the layout's order, boxes covering its hand and what it holds, in its
            end-effector site frame, metres (an empty list: the site point).
        clearance: Distance in metres at which the approach bound reaches ``floor``; >= 0.
        brake: Width in metres of the band beyond the clearance over which it is limited; >= 0.
        floor: The smallest approach bound, in action units; > 0.
        rotation: Also limit both arms' rotation components near each other.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on fewer than two hands, a bad box, a negative clearance or
            brake, or a non-positive floor; and, when compiled, a hand count other than the
            layout's arm count.
    """

    hands: tuple[tuple[Aabb, ...], ...]
    clearance: float = 0.0
    brake: float = 0.15
    floor: float = 0.05
    rotation: bool = True
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if len(self.hands) < 2:
            raise invalid("hands", f"one entry per arm, at least two; got {len(self.hands)}")
        if self.clearance < 0:
            raise invalid("clearance", f"must be >= 0, got {self.clearance}")
        if self.brake < 0:
            raise invalid("brake", f"must be >= 0, got {self.brake}")
        if not self.floor > 0:
            raise invalid("floor", f"must be > 0, got {self.floor}")

    def compile(self, layout: ActionLayout) -> Check:
        n = len(layout.arms)
        if len(self.hands) != n:
            raise Invalid(f"hands: {len(self.hands)} given; the layout has {n} arm(s)", details={"field": "hands"})
        hands, cl, br, fl, turn = self.hands, self.clearance, self.brake, self.floor, self.rotation
        offsets = tuple(arm.offset for arm in layout.arms)
        # A hand's box lies within sqrt(3) * reach of its site, so sites farther apart than this are out of range.
        pairs = tuple(
            (i, j, math.sqrt(3.0) * (hand_reach(hands[i]) + hand_reach(hands[j])) + cl + br)
            for i in range(n)
            for j in range(i + 1, n)
        )
        reasons = {(i, j): f"arms {i} and {j}: hands near each other: approach slowed" for i, j, _ in pairs}
        isfinite = math.isfinite

        extents = tuple(extent_of(h) for h in hands)

        def boxes(arms: Sequence[ArmState]) -> list[tuple[tuple[float, ...], tuple[float, ...]]] | str:
            out = []
            for i in range(n):
                p = arms[i].eef_pos
                px, py, pz = p[0], p[1], p[2]
                if not (isfinite(px) and isfinite(py) and isfinite(pz)):
                    return f"arm {i}: end-effector position {p} is not finite"
                rot = finite_rotation_or_down(arms[i])
                if rot is None:
                    return f"arm {i}: end-effector orientation {rotation_of(arms[i])} is not finite"
                (l0, l1, l2), (h0, h1, h2) = extents[i](rot)
                out.append(((px + l0, py + l1, pz + l2), (px + h0, py + h1, pz + h2)))
            return out

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            hull = boxes(arms)
            if isinstance(hull, str):
                return None, hull
            b: list[float] | None = None
            notes: list[str] = []
            for i, j, _ in pairs:
                (li, hi_), (lj, hj) = hull[i], hull[j]
                dist, s, side = box_gap(li, hi_, lj, hj)  # side +1: arm i approaches j by moving +k
                if dist >= cl + br and dist > cl:
                    continue
                q = (dist - cl) / br if br > 0.0 and dist > cl else 0.0
                if dist > 0.0:
                    bound = max(fl, q * dist / (s[0] + s[1] + s[2]))
                else:
                    for k in (0, 1, 2):
                        ci, cj = (li[k] + hi_[k]) / 2, (lj[k] + hj[k]) / 2
                        # Centres within rounding of each other give no direction to slow.
                        side[k] = 1.0 if cj > ci + CENTRE_TIE else -1.0 if cj < ci - CENTRE_TIE else 0.0
                    bound = fl
                rb = max(fl, q) if dist > 0.0 else fl
                changed = False
                for arm, sign in ((i, 1.0), (j, -1.0)):
                    o = offsets[arm]
                    for k in (0, 1, 2):
                        v = (a if b is None else b)[o + k]
                        if side[k] and v * side[k] * sign > 0.0 and abs(v) > bound:
                            if b is None:
                                b = list(a)
                            b[o + k] = bound if v > 0.0 else -bound
                            changed = True
                    if turn:
                        for k in (3, 4, 5):
                            v = (a if b is None else b)[o + k]
                            if abs(v) > rb:
                                if b is None:
                                    b = list(a)
                                b[o + k] = rb if v > 0.0 else -rb
                                changed = True
                if changed:
                    notes.append(reasons[(i, j)])
            return edited(b, notes)

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for i, j, reach in pairs:
                pi, pj = arms[i].eef_pos, arms[j].eef_pos
                dx, dy, dz = pi[0] - pj[0], pi[1] - pj[1], pi[2] - pj[2]
                # "Provably far apart", so NaN falls through to the slow path.
                if not dx * dx + dy * dy + dz * dz > reach * reach:
                    return slow(arms, a)
            return None

        return check
