"""workspace_box: keep every end effector inside an axis-aligned box in the world frame.

Paper default: x, y in [−0.6, 0.6] m, z in [0.6, 1.3] m, margin 0.08 m.

Rule: for each arm and each axis, when the end effector is within ``margin`` of a face
(or beyond it), a translational action component directed outward through that face is
set to 0.0. Components directed inward, along the face, and rotation are left alone.

Invariants:
1. After the check, for every arm and axis ``k``: ``p_k >= high_k - margin`` implies
   ``a_k <= 0`` and ``p_k <= low_k + margin`` implies ``a_k >= 0``.
2. An action is changed only by zeroing such components; an action the rule does not
   touch is allowed (the check returns None) and never copied.
3. A non-finite end-effector position is ⊥ with a reason: the envelope cannot be
   certified from a broken reading.
4. The hard limit (:meth:`WorkspaceBox.unsafe`) is "an end effector strictly outside
   ``[low, high]`` on some axis" (or a non-finite position).
"""

from __future__ import annotations

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


@register("workspace_box")
@dataclass(frozen=True, slots=True, kw_only=True)
class WorkspaceBox(ConstraintBase):
    """Workspace envelope for end effectors.

    Args:
        low: Lower corner (x, y, z) in metres, world frame.
        high: Upper corner (x, y, z) in metres, world frame; above ``low`` on every axis.
        margin: Distance from a face in metres within which outward motion is zeroed; >= 0.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value, ``low >= high`` or a
            negative margin.
    """

    low: tuple[float, float, float] = (-0.6, -0.6, 0.6)
    high: tuple[float, float, float] = (0.6, 0.6, 1.3)
    margin: float = 0.08
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        check_corners(self.low, self.high)
        if self.margin < 0:
            raise invalid("margin", f"must be >= 0, got {self.margin}")

    def compile(self, layout: ActionLayout) -> Check:
        m = self.margin
        low = tuple(v + m for v in self.low)
        high = tuple(v - m for v in self.high)
        lx, ly, lz = low
        hx, hy, hz = high
        # (index of the x component, reasons for +x, -x, +y, -y, +z, -z) per arm, built once:
        # the slow path only picks strings, it never formats.
        per_arm = tuple(
            (
                arm.offset,
                tuple(
                    f"arm {i}: within {m} m of the {sign}{AXES[k]} face ({face} m) or beyond: "
                    f"motion out through it zeroed"
                    for k in range(3)
                    for sign, face in (("+", self.high[k]), ("-", self.low[k]))
                ),
            )
            for i, arm in enumerate(layout.arms)
        )

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, arm in enumerate(arms):
                x, y, z = p = arm.eef_pos
                if lx < x < hx and ly < y < hy and lz < z < hz:
                    continue
                if x - x != 0.0 or y - y != 0.0 or z - z != 0.0:  # NaN or ±inf
                    return None, f"arm {i}: end-effector position {p} is not finite"  # rare: format here
                o, reasons = per_arm[i]
                for k in (0, 1, 2):
                    v = a[o + k]
                    if (v > 0.0 and p[k] >= high[k]) or (v < 0.0 and p[k] <= low[k]):
                        if b is None:
                            b = list(a)
                        b[o + k] = 0.0
                        notes.append(reasons[2 * k if v > 0.0 else 2 * k + 1])
            return edited(b, notes)

        return unless_all_inside(low, high, slow)

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        for i, arm in enumerate(arms):
            p = arm.eef_pos
            for k in range(3):
                if not self.low[k] <= p[k] <= self.high[k]:
                    return f"arm {i}: end effector {AXES[k]}={p[k]} m is outside [{self.low[k]}, {self.high[k]}]"
        return None
