"""An arm state that also carries the end effector's orientation.

:class:`~capevo.runtime.state.ArmState` holds position and force only. Rules about the hand's
extent (how low its lowest point is when the gripper is tilted) need the orientation too, so
environments that can report it return :class:`ArmPose`, a subclass: every consumer of
``ArmState`` keeps working, and constraints read ``eef_rot`` where present (see
:func:`rotation_of`) and fall back to a documented assumption where not.

Invariants:
1. ``ArmPose`` is an ``ArmState``; it adds only ``eef_rot``.
2. :func:`rotation_of` returns the 9-tuple of an ``ArmPose`` and None for any other arm state.
3. :data:`DOWN` is a proper rotation.
4. :func:`finite_rotation_or_down` returns :data:`DOWN` for an arm state without a rotation,
   the rotation itself when all nine entries are finite, and None otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from capevo.runtime.state import ArmState


@dataclass(frozen=True, slots=True, kw_only=True)
class ArmPose(ArmState):
    """One arm's end effector: position, force and orientation, world frame."""

    eef_rot: tuple[float, float, float, float, float, float, float, float, float]
    """Rotation from the end-effector site frame to the world frame, row-major 3x3. For the
    robosuite Panda gripper the site's +z points from the hand out through the fingertips."""


DOWN: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
"""The orientation assumed for an arm state without one: site +z along world −z (a Panda gripper
pointing down, as at rest), site +x along world +x."""


def rotation_of(arm: ArmState) -> tuple[float, ...] | None:
    """The end-effector rotation of ``arm`` if it carries one, else None."""
    return arm.eef_rot if type(arm) is ArmPose else getattr(arm, "eef_rot", None)


def finite_rotation_or_down(arm: ArmState) -> tuple[float, ...] | None:
    """The end-effector rotation rules about the hand's extent use: ``arm``'s own, :data:`DOWN` when
    it carries none, or None when some entry is not finite (the rule rejects the action then)."""
    rot = rotation_of(arm)
    if rot is None:
        return DOWN
    # A finite sum proves every entry finite; an overflowing one takes the exact test.
    s = sum(rot)
    if s - s != 0.0 and not all(math.isfinite(v) for v in rot):
        return None
    return rot
