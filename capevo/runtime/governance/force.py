"""contact_force: above a force limit, stop pushing further into the contact.

Paper default: 20 N at the end effector.

Sign convention: ``ArmState.eef_force`` is the contact force the environment exerts ON the
end effector, in newtons, world frame (a table under the gripper pushes up: ``f_z > 0``).
Motion "into the contact" is motion against that force (``a · f < 0``); its reaction
direction ``−f`` points into the contact. For robosuite, :mod:`capevo.runtime.governance.robosuite_state`
derives this from the gripper's ``force_ee`` sensor.

Rule: when an arm's ``|f| > max_force``, every translational component that moves against
the force along its own axis (``a_k`` and ``f_k`` of opposite signs) is set to 0.0. Each
remaining term of ``a · f`` is then >= 0, so no motion into the contact remains. For a
contact along one axis (a table, a wall) this is exactly removing the component along
``−f``. For an oblique force it is stricter than projecting onto the plane ``a · f = 0``;
a projection would mix axes and could undo a workspace-box zeroing (and vice versa),
whereas zeroing composes with every other built-in constraint in one pass (see
:mod:`capevo.runtime.governance.base`). Rotation and the gripper are untouched.

The rule is reactive: it acts on the force already measured. An arm that reaches a rigid
surface at speed can exceed the limit in the control step of impact, before any reading
shows a contact, and an adversary that keeps pushing re-approaches after each release.
Keeping force below the limit at all times needs the box (or a forbidden zone) to stop
the arm short of known surfaces.

Invariants:
1. After the check, every arm with ``fx*fx + fy*fy + fz*fz > max_force**2`` has no ``k`` in
   x, y, z where ``a_k`` and ``f_k`` have opposite signs, hence ``a · f >= 0``.
2. Arms at or below the limit are not touched.
3. A non-finite force reading is ⊥ with a reason.
4. The hard limit (:meth:`ContactForce.unsafe`) is ``|f| > max_force`` (or non-finite).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.runtime.governance.base import AXES, Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.prefilter import unless_all_forces_within
from capevo.runtime.state import ActionLayout, ArmState

INF = math.inf


def into_contact(v: float, f: float) -> bool:
    """Whether an action component ``v`` moves against the force component ``f`` on the same axis.

    Compared by sign, not by product: ``v * f`` can underflow to -0.0.
    """
    return (v > 0.0 and f < 0.0) or (v < 0.0 and f > 0.0)


@register("contact_force")
@dataclass(frozen=True, slots=True, kw_only=True)
class ContactForce(ConstraintBase):
    """Contact-force limit at each end effector.

    Args:
        max_force: Limit on the magnitude of the contact force in newtons; > 0.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type or a non-positive or non-finite limit.
    """

    max_force: float = 20.0
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not self.max_force > 0:
            raise invalid("max_force", f"must be > 0, got {self.max_force}")

    def compile(self, layout: ActionLayout) -> Check:
        limit = self.max_force
        lim2 = limit * limit
        per_arm = tuple(
            (
                arm.offset,
                tuple(
                    f"arm {i}: contact force above {limit} N: motion into the contact along {ax} zeroed" for ax in AXES
                ),
            )
            for i, arm in enumerate(layout.arms)
        )

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, arm in enumerate(arms):
                fx, fy, fz = f = arm.eef_force
                n2 = fx * fx + fy * fy + fz * fz
                if n2 <= lim2:
                    continue  # at or below the limit, hence also finite
                # A non-finite reading makes n2 NaN or inf; finite ones can overflow to inf too.
                if not n2 < INF and (fx - fx != 0.0 or fy - fy != 0.0 or fz - fz != 0.0):
                    return None, f"arm {i}: force reading {f} is not finite"  # rare: format here
                o, reasons = per_arm[i]
                for k in (0, 1, 2):
                    if into_contact(a[o + k], f[k]):
                        if b is None:
                            b = list(a)
                        b[o + k] = 0.0
                        notes.append(reasons[k])
            return edited(b, notes)

        return unless_all_forces_within(lim2, slow)

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        lim2 = self.max_force * self.max_force
        for i, arm in enumerate(arms):
            fx, fy, fz = arm.eef_force
            if not fx * fx + fy * fy + fz * fz <= lim2:
                return f"arm {i}: contact force {math.hypot(fx, fy, fz)} N is above {self.max_force} N"
        return None
