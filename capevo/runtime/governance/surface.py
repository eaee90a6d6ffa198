"""surface_approach: speed-and-separation above a known horizontal surface (a table top, a bin floor).

The paper's box floor (0.6 m) lies below the tables of the manipulation tasks (0.8 m), so the
box never stops an arm driving down into the table, and the force limit only reacts after an
impact has already gone from 0 to hundreds of newtons within one control step (measured: a
Panda pushing down with OSC at action −1 reads about 300 N at the first step in contact;
pushing at −a it settles near 250·a N). This rule acts before the contact: the hand may come
down to the surface, but the closer its lowest point gets the slower it may move towards it,
so it arrives slowly and touches softly, and a gripper can still close on an object resting there.

The hand is described by boxes in the end-effector site frame (``hand``). Its lowest point is
``z + lowest(R)``, where ``R`` is the arm's orientation (:attr:`ArmPose.eef_rot`) and
``lowest(R)`` the smallest world-z offset of any box corner. An arm state without an
orientation is taken to point straight down (site +z along world −z, as a Panda gripper does at
rest). With ``gap = z + lowest(R) − (height + clearance)`` (a slightly negative clearance lets
the fingers settle on the surface), while ``gap < brake``:

* the downward translation component is limited to ``max(0, gap) / brake``: full speed (1.0,
  the controller's saturation) ``brake`` metres above the surface, 0 at it. OSC_POSE
  re-anchors its target at the current position every step, so the hand decelerates in
  proportion to the remaining gap;
* with ``rotation``, each rotation component is limited in magnitude to that same bound, since
  turning a tilted hand swings its far corner (16 cm from the site on a Panda) down as fast as
  translating it would;
* with ``lateral``, the horizontal components are limited to ``max(lateral, q)``, so a hand
  at the surface drags along it slowly instead of catching on it at full speed.

The plane is unbounded in x and y, so an arm beside the table cannot slip under its edge either.

Invariants (per arm after the check; ``gap`` as above, ``q = max(0, gap) / brake``):
1. ``gap < brake`` implies ``a_z >= −q`` (with ``brake == 0``: ``gap <= 0`` implies ``a_z >= 0``).
2. With ``rotation``, ``gap < brake`` implies ``|ω_k| <= q`` for the three rotation components;
   with ``lateral`` set, it implies ``|a_x|, |a_y| <= max(lateral, q)``.
3. Only those components change (clamped to the bound); an action the rule does not touch is
   allowed (None) and never copied.
4. Whenever the rule looks at the arms (some arm's site is below ``stop + hand reach + brake``,
   or its height is not finite), a non-finite height or orientation of any arm is ⊥ with a
   reason (x and y play no part).
5. No hard limit of its own (:meth:`SurfaceApproach.unsafe` is None): what it prevents shows as
   contact force.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.hand import hand_reach, lowest_offset
from capevo.runtime.governance.pose import DOWN, finite_rotation_or_down, rotation_of
from capevo.runtime.governance.zone import Aabb
from capevo.runtime.state import ActionLayout, ArmState


@register("surface_approach")
@dataclass(frozen=True, slots=True, kw_only=True)
class SurfaceApproach(ConstraintBase):
    """Downward (and turning) motion limited in proportion to the hand's height above a horizontal surface.

    Args:
        height: World z of the surface in metres (the task's table top or bin floor).
        clearance: Height of the hand's lowest point above the surface, metres, at which
            downward motion reaches 0; slightly negative lets the fingers settle on it.
        brake: Height in metres over which downward motion is limited; >= 0 (0: only zero it
            at the surface).
        hand: Boxes covering the hand in the end-effector site frame (metres); none means the
            site point itself.
        rotation: Also limit the rotation components within the band.
        lateral: If set, also limit the horizontal components within the band to
            ``max(lateral, q)``: a hand (or a tilted hand's corner) at the surface drags along it
            slowly; ``lateral`` is the speed still allowed there, e.g. for aligning a grasp.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value, a negative brake or a
            ``lateral`` outside [0, 1].
    """

    height: float
    clearance: float = 0.0
    brake: float = 0.1
    hand: tuple[Aabb, ...] = ()
    rotation: bool = True
    lateral: float | None = None
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if self.brake < 0:
            raise invalid("brake", f"must be >= 0, got {self.brake}")
        if self.lateral is not None and not 0 <= self.lateral <= 1:
            raise invalid("lateral", f"must be in [0, 1], got {self.lateral}")

    def gap(self, arm: ArmState) -> float:
        """Height of ``arm``'s lowest hand point above the stop height (negative below it)."""
        rot = rotation_of(arm)
        return arm.eef_pos[2] + lowest_offset(self.hand, DOWN if rot is None else rot) - (self.height + self.clearance)

    def compile(self, layout: ActionLayout) -> Check:
        stop, br, hand, turn = self.height + self.clearance, self.brake, self.hand, self.rotation
        lat = self.lateral
        # No corner is farther from the site than this, whatever the orientation: above
        # stop + reach + brake the rule cannot apply (the fast path).
        top = stop + hand_reach(hand) + br
        offsets = tuple(arm.offset for arm in layout.arms)
        reasons = tuple(
            f"arm {i}: hand near the surface at {self.height} m: motion towards it braked" for i in range(len(offsets))
        )
        isfinite, inf = math.isfinite, math.inf

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, o in enumerate(offsets):
                arm = arms[i]
                z = arm.eef_pos[2]
                if not isfinite(z):
                    return None, f"arm {i}: end-effector height {z} is not finite"  # rare: format here
                rot = finite_rotation_or_down(arm)
                if rot is None:
                    return None, f"arm {i}: end-effector orientation {rotation_of(arm)} is not finite"
                gap = z + lowest_offset(hand, rot) - stop
                if gap >= br and gap > 0.0:
                    continue
                q = (gap / br if br > 0.0 else 0.0) if gap > 0.0 else 0.0
                src = a if b is None else b
                hit = src[o + 2] < -q
                if turn:
                    hit = hit or abs(src[o + 3]) > q or abs(src[o + 4]) > q or abs(src[o + 5]) > q
                ql = (lat if lat > q else q) if lat is not None else math.inf
                hit = hit or abs(src[o]) > ql or abs(src[o + 1]) > ql
                if not hit:
                    continue
                if b is None:
                    b = list(a)
                if b[o + 2] < -q:
                    b[o + 2] = -q
                if turn:
                    for j in (o + 3, o + 4, o + 5):
                        b[j] = min(max(b[j], -q), q)
                if lat is not None:
                    for j in (o, o + 1):
                        b[j] = min(max(b[j], -ql), ql)
                notes.append(reasons[i])
            return edited(b, notes)

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for arm in arms:
                if not top < arm.eef_pos[2] < inf:
                    return slow(arms, a)
            return None

        return check
