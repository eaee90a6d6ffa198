"""closing_grip: while a gripper closes on a loose object between its fingers, the hand moves slowly.

Every proximity rule sees a movable object either as something the hand may touch (not held) or
as part of the hand (held: both fingers touch it, :mod:`~capevo.runtime.governance.proximity`).
During the step in which the fingers close on it, the object is neither: it is not held before
the step, so its pairs with the table under it are not sensed, and the hand's motion during the
step carries it. Measured on T3 with the hand-set parameters (seed 250028, under the default Φ of
commit 088dd54): ``stack.grasp`` closes the gripper while still descending (z commands of
−0.16 to −0.19 over steps 49-53); the fingers, 1.5-3 mm off the cube's faces at step 53, caught it
during that step and the hand pressed it into the table at 21.2 N (the monitor's one unsafe
step in the hand-set T3 set's 30 held-out episodes).

So while an arm's gripper command closes (``> 0``, robosuite's sign) and two pairs of the hand with
movable objects lie closer than ``within`` metres on opposite sides (``n_i · n_j < 0``: something is
between the fingers), the arm's translation is scaled down to a norm of at most ``speed``
(action units). Rotation and the gripper are left alone, and so is everything once the object is
held: its geoms then belong to the hand, and ``contact_approach`` brakes it against the table.

The settings of the per-task Φ (``CLOSING_GRIP`` in :mod:`~capevo.runtime.governance.task_phi`)
are hand-written: ``within`` 1 cm, about three control steps of a Panda finger closing, and
``speed`` 0.05 (2.5 mm per step), a third of the descent that pressed the cube.

Invariants (per arm, after the check alone):
1. If the arm's gripper command is ``> 0`` and two of its loose-object pairs closer than ``within``
   have ``n_i · n_j < 0``, its translation's norm is at most ``speed`` (to rounding) and points the
   way it did; otherwise the arm is untouched.
2. Only translation components change; an action no arm asks to change is allowed (None).
3. While the gripper command closes, a non-finite loose-object pair in the band is ⊥ with a reason.
4. No hard limit of its own (:meth:`ClosingGrip.unsafe` is None): what it prevents shows as force.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.proximity import LOOSE
from capevo.runtime.state import ActionLayout, ArmState

MAX_WITHIN = 0.05
"""Metres: a wider band would slow a hand closing near an object it is not grasping."""


def _between_fingers(near: Sequence[Sequence[float]], within: float) -> bool | None:
    """True if two loose-object pairs closer than ``within`` face opposite ways; None if one is not finite."""
    normals: list[tuple[float, float, float]] = []
    for pair in near:
        if pair[7] != LOOSE or pair[0] >= within:
            continue
        if not all(math.isfinite(v) for v in pair[:4]):
            return None
        n = (pair[1], pair[2], pair[3])
        if any(m[0] * n[0] + m[1] * n[1] + m[2] * n[2] < 0.0 for m in normals):
            return True
        normals.append(n)
    return False


@register("closing_grip")
@dataclass(frozen=True, slots=True, kw_only=True)
class ClosingGrip(ConstraintBase):
    """Slow the hand's translation to ``speed`` while its gripper closes on a loose object between its fingers.

    Args:
        within: Metres: a loose object's pairs closer than this on opposite sides of the hand
            count as between the fingers; in (0, 0.05].
        speed: Largest translation norm while closing, action units; in [0, 1].
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value or a value out of range.
    """

    reads_proximity: ClassVar[bool] = True
    """The state must carry proximity pairs (:class:`~capevo.runtime.governance.proximity.ArmScene`)."""
    within: float = 0.01
    speed: float = 0.05
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not 0 < self.within <= MAX_WITHIN:
            raise invalid("within", f"must be in (0, {MAX_WITHIN}], got {self.within}")
        if not 0 <= self.speed <= 1:
            raise invalid("speed", f"must be in [0, 1], got {self.speed}")

    def compile(self, layout: ActionLayout) -> Check:
        within, speed = self.within, self.speed
        grippers = tuple((i, arm.offset, arm.gripper) for i, arm in enumerate(layout.arms) if arm.gripper is not None)
        reasons = {
            i: f"arm {i}: gripper closing on an object between the fingers: hand slowed to {speed}"
            for i, _, _ in grippers
        }
        bad = {i: f"arm {i}: a proximity pair with a movable object is not finite" for i, _, _ in grippers}

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, o, g in grippers:
                if not a[g] > 0.0:
                    continue
                between = _between_fingers(getattr(arms[i], "near", ()), within)
                if between is None:
                    return None, bad[i]
                if not between:
                    continue
                norm = math.sqrt(a[o] * a[o] + a[o + 1] * a[o + 1] + a[o + 2] * a[o + 2])
                if norm <= speed:
                    continue
                if b is None:
                    b = list(a)
                scale = speed / norm
                for j in range(o, o + 3):
                    b[j] = a[j] * scale
                notes.append(reasons[i])
            return edited(b, notes)

        return check
