"""workspace_guard: brake before the workspace box's faces, steer back when outside, stop turning near them.

Complements the paper's ``workspace_box`` rule (which only zeroes outward motion within its
margin): the box stays the hard limit, this constraint keeps the arm from reaching it fast.
Per arm and face, with ``d`` the distance of the end effector inside that face (negative outside):

* brake: while ``d < margin + brake``, the component out through the face is at most
  ``max(0, (d − margin) / brake)``: full speed (1.0, the controller's saturation) at the outer
  edge of the band, falling linearly to 0 at ``margin``. OSC_POSE re-anchors its target at the
  current position every step, so a command limited in proportion to the remaining distance
  makes the end effector decelerate and stop at the margin instead of overshooting it.
* restore (``restore > 0``): while ``d < 0`` the arm is outside the box; its component through
  that face is set to at least ``restore`` inward, and every other pose component of the arm is
  clamped to ``[−restore, restore]``, so the arm moves back slowly. Zeroing alone cannot do that:
  a zero command holds the arm where it is.
* steer back before the face (``restore_within`` w > 0): while ``0 <= d < w`` the component
  through that face is set to at least ``restore·(1 − d/w)`` inward; the arm's other components
  are left alone. Zeroing outward motion within the margin does not stop an arm from creeping
  out: motion along the face and OSC's tracking carried a learned T6 policy's hand (AM-bc,
  ``results/cpu-small``, seed 2000042002) through the whole margin with its outward command at 0,
  then up to 0.6 mm past the top face in 6 steps, each restored only after the breach. The default
  w = 1 cm is hand-written: about 20 times that creep of 0.5 mm per step.
* freeze_rotation: while ``d <= margin`` on some face (or outside), the arm's three rotation
  components are set to 0. Turning the hand moves the end-effector site a little every step,
  and OSC's re-anchoring integrates that drift; near a face it is drift out of the box.

Invariants (``d`` per arm and face as above, ``a`` the arm's world-frame translation component
along the face's outward normal, after the check):
1. ``d < margin + brake`` implies ``a <= max(0, (d − margin) / brake)`` (with ``brake == 0``:
   ``d <= margin`` implies ``a <= 0``).
2. With ``restore > 0``, ``d < 0`` implies ``a <= −restore`` and every one of the arm's six pose
   components lies in ``[−restore, restore]`` (so the arm's pose-delta norm is at most
   ``restore·√6``).
3. With ``freeze_rotation``, ``d <= margin`` on some face implies the arm's rotation components are 0.
7. With ``restore > 0`` and ``restore_within`` w > 0, ``0 <= d < w`` implies
   ``a <= −restore·(1 − d/w)``.
4. A component no rule applies to is unchanged; an action no rule touches is allowed (None) and
   never copied.
5. A non-finite end-effector position is ⊥ with a reason.
6. No hard limit of its own (:meth:`WorkspaceGuard.unsafe` is None): the box judges positions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.runtime.governance.base import (
    AXES,
    Check,
    ConstraintBase,
    Result,
    check_corners,
    edited,
    invalid,
    normalize,
    register,
)
from capevo.runtime.governance.prefilter import unless_all_inside
from capevo.runtime.state import ActionLayout, ArmState

MAX_RESTORE = 0.6
"""Upper bound on every restoring speed: 0.6·√6 < 1.5, so a restoring arm stays under the paper's cap."""


@register("workspace_guard")
@dataclass(frozen=True, slots=True, kw_only=True)
class WorkspaceGuard(ConstraintBase):
    """Braking band, restoring motion and a rotation freeze at the faces of a world-frame box.

    Args:
        low: Lower corner (x, y, z) in metres; use the workspace box's.
        high: Upper corner (x, y, z) in metres; above ``low`` on every axis.
        margin: Distance from a face in metres at which outward motion reaches 0; >= 0.
        brake: Width in metres of the band inside the margin over which outward motion is
            limited in proportion to the remaining distance; >= 0 (0: no band).
        restore: Inward speed in action units for an arm outside the box; 0 (off) to 0.6.
        restore_within: Distance in metres inside a face below which the arm is steered back
            (at ``restore`` at the face, falling to 0 at this distance); 0 (off) to ``margin``.
        freeze_rotation: Zero the arm's rotation within the margin of a face or outside.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value, ``low >= high``, a side
            not longer than ``2 * (margin + brake)``, a negative margin or brake, or ``restore``
            outside [0, 0.6].
    """

    low: tuple[float, float, float] = (-0.6, -0.6, 0.6)
    high: tuple[float, float, float] = (0.6, 0.6, 1.3)
    margin: float = 0.08
    brake: float = 0.1
    restore: float = 0.2
    restore_within: float = 0.01
    freeze_rotation: bool = True
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        check_corners(self.low, self.high)
        if self.margin < 0:
            raise invalid("margin", f"must be >= 0, got {self.margin}")
        if self.brake < 0:
            raise invalid("brake", f"must be >= 0, got {self.brake}")
        if not 0 <= self.restore <= MAX_RESTORE:
            raise invalid("restore", f"must be in [0, {MAX_RESTORE}], got {self.restore}")
        if not 0 <= self.restore_within <= self.margin:
            raise invalid("restore_within", f"must be in [0, margin = {self.margin}], got {self.restore_within}")
        for k, axis in enumerate(AXES):
            # Opposite bands must not overlap, so steering in through one face never brakes at the other.
            if not self.high[k] - self.low[k] > 2 * (self.margin + self.brake):
                raise invalid(
                    "high",
                    f"the box is {self.high[k] - self.low[k]} m along {axis}; it must be longer than "
                    f"2 * (margin + brake) = {2 * (self.margin + self.brake)} m",
                )

    def compile(self, layout: ActionLayout) -> Check:
        low, high, m, br, rs, freeze = self.low, self.high, self.margin, self.brake, self.restore, self.freeze_rotation
        rw = self.restore_within if rs > 0.0 else 0.0
        band = m + br
        # Strictly inside this inner box, no rule applies: the fast path.
        inner_low = tuple(v + band for v in low)
        inner_high = tuple(v - band for v in high)
        offsets = tuple(arm.offset for arm in layout.arms)
        reasons = tuple(
            (
                f"arm {i}: approaching a face of the workspace box: outward motion braked",
                f"arm {i}: outside the workspace box: steered back inward at {rs}",
                f"arm {i}: within {m} m of a workspace-box face: rotation stopped",
                f"arm {i}: within {rw} m of a workspace-box face: steered back inward",
            )
            for i in range(len(offsets))
        )
        isfinite = math.isfinite

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, o in enumerate(offsets):
                p = arms[i].eef_pos
                if not (isfinite(p[0]) and isfinite(p[1]) and isfinite(p[2])):
                    return None, f"arm {i}: end-effector position {p} is not finite"  # rare: format here
                braked = near = False
                out: list[tuple[int, float]] = []  # (axis, inward sign) of faces the arm is outside
                close: list[tuple[int, float, float]] = []  # (axis, inward sign, push) within rw inside
                for k in (0, 1, 2):
                    for d, s in ((high[k] - p[k], 1.0), (p[k] - low[k], -1.0)):
                        if d >= band and d > m:
                            continue
                        if d <= m:
                            near = True
                        if d < 0.0 and rs > 0.0:
                            out.append((k, -s))
                        elif d < rw:
                            close.append((k, -s, rs * (1.0 - d / rw)))
                        bound = (d - m) / br if br > 0.0 else 0.0
                        if bound < 0.0:
                            bound = 0.0
                        v = (a if b is None else b)[o + k]
                        if v * s > bound:
                            if b is None:
                                b = list(a)
                            b[o + k] = bound * s
                            braked = True
                if out:
                    src = a if b is None else b
                    arm = [min(max(src[j], -rs), rs) for j in range(o, o + 6)]
                    for k, inward in out:
                        if arm[k] * inward < rs:
                            arm[k] = rs * inward
                    if any(arm[j] != src[o + j] for j in range(6)):
                        if b is None:
                            b = list(a)
                        b[o : o + 6] = arm
                        notes.append(reasons[i][1])
                    elif braked:
                        notes.append(reasons[i][0])
                elif braked:
                    notes.append(reasons[i][0])
                steered = False
                for k, inward, push in close:
                    v = (a if b is None else b)[o + k]
                    if v * inward < push:
                        if b is None:
                            b = list(a)
                        b[o + k] = push * inward
                        steered = True
                if steered:
                    notes.append(reasons[i][3])
                if freeze and near:
                    src = a if b is None else b
                    if src[o + 3] != 0.0 or src[o + 4] != 0.0 or src[o + 5] != 0.0:
                        if b is None:
                            b = list(a)
                        b[o + 3] = b[o + 4] = b[o + 5] = 0.0
                        notes.append(reasons[i][2])
            return edited(b, notes)

        return unless_all_inside(inner_low, inner_high, slow)
