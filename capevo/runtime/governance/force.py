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
from typing import Any, ClassVar

from capevo.runtime.governance.base import Check, KernelSpec, Result, config_of, invalid, normalize, register
from capevo.runtime.state import ActionLayout, ArmState

AXES = ("x", "y", "z")
INF = math.inf


@register("contact_force")
@dataclass(frozen=True, slots=True, kw_only=True)
class ContactForce:
    """Contact-force limit at each end effector.

    Args:
        max_force: Limit on the magnitude of the contact force in newtons; > 0.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type or a non-positive or non-finite limit.
    """

    kind: ClassVar[str]
    max_force: float = 20.0
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not self.max_force > 0:
            raise invalid("max_force", f"must be > 0, got {self.max_force}")

    @property
    def label(self) -> str:
        return self.name or self.kind

    def to_config(self) -> dict[str, Any]:
        return config_of(self)

    def _prepared(self, layout: ActionLayout) -> tuple[float, tuple[tuple[int, tuple[str, ...]], ...]]:
        # The numbers and strings compile() and kernel_spec() share: lim2, and per arm
        # (offset, reasons for x, y, z).
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
        return lim2, per_arm

    def compile(self, layout: ActionLayout) -> Check:
        lim2, per_arm = self._prepared(layout)

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            reason: str | None = None
            for i, arm in enumerate(arms):
                fx, fy, fz = f = arm.eef_force
                n2 = fx * fx + fy * fy + fz * fz
                if n2 <= lim2:
                    continue  # at or below the limit, hence also finite
                # A non-finite reading makes n2 NaN or inf; finite ones can overflow to inf too.
                if not n2 < INF and (fx - fx != 0.0 or fy - fy != 0.0 or fz - fz != 0.0):
                    return None, f"arm {i}: force reading {f} is not finite"  # rare: format here
                o, reasons = per_arm[i]
                ax, ay, az = a[o : o + 3]
                # Compare signs, not products: a * f can underflow to -0.0.
                zx = (ax > 0.0 and fx < 0.0) or (ax < 0.0 and fx > 0.0)
                zy = (ay > 0.0 and fy < 0.0) or (ay < 0.0 and fy > 0.0)
                zz = (az > 0.0 and fz < 0.0) or (az < 0.0 and fz > 0.0)
                if not (zx or zy or zz):
                    continue
                if b is None:
                    b = list(a)
                # Reasons join as "; ".join would, without building a list for the usual single one.
                if zx:
                    b[o] = 0.0
                    reason = reasons[0] if reason is None else f"{reason}; {reasons[0]}"
                if zy:
                    b[o + 1] = 0.0
                    reason = reasons[1] if reason is None else f"{reason}; {reasons[1]}"
                if zz:
                    b[o + 2] = 0.0
                    reason = reasons[2] if reason is None else f"{reason}; {reasons[2]}"
            if b is None:
                return None
            return b, reason  # type: ignore[return-value]

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for arm in arms:
                fx, fy, fz = arm.eef_force
                if not fx * fx + fy * fy + fz * fz <= lim2:
                    return slow(arms, a)
            return None

        return check

    def kernel_spec(self, layout: ActionLayout) -> KernelSpec:
        """This check for the fused kernel (``csrc/contact_force.c``); the same numbers as :meth:`compile`."""
        lim2, per_arm = self._prepared(layout)
        return KernelSpec(
            self.kind,
            (float(lim2),),
            tuple(o for o, _ in per_arm),
            tuple(note for _, notes in per_arm for note in notes),
        )

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        lim2 = self.max_force * self.max_force
        for i, arm in enumerate(arms):
            fx, fy, fz = arm.eef_force
            if not fx * fx + fy * fy + fz * fz <= lim2:
                return f"arm {i}: contact force {math.hypot(fx, fy, fz)} N is above {self.max_force} N"
        return None
