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
from typing import Any, ClassVar

from capevo.runtime.governance.base import Check, KernelSpec, Result, config_of, invalid, normalize, register
from capevo.runtime.state import ActionLayout, ArmState

AXES = ("x", "y", "z")


@register("workspace_box")
@dataclass(frozen=True, slots=True, kw_only=True)
class WorkspaceBox:
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

    kind: ClassVar[str]
    low: tuple[float, float, float] = (-0.6, -0.6, 0.6)
    high: tuple[float, float, float] = (0.6, 0.6, 1.3)
    margin: float = 0.08
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        for k, axis in enumerate(AXES):
            if not self.low[k] < self.high[k]:
                raise invalid("high", f"high.{axis} ({self.high[k]}) must be above low.{axis} ({self.low[k]})")
        if self.margin < 0:
            raise invalid("margin", f"must be >= 0, got {self.margin}")

    @property
    def label(self) -> str:
        return self.name or self.kind

    def to_config(self) -> dict[str, Any]:
        return config_of(self)

    def _prepared(self, layout: ActionLayout) -> tuple[tuple[float, ...], tuple[int, ...], tuple[str, ...]]:
        """The box shrunk by the margin (low x, y, z, high x, y, z), each arm's offset, and per arm
        the six reasons (+x, -x, +y, -y, +z, -z): what :meth:`compile` and :meth:`kernel_spec` share."""
        m = self.margin
        inner = tuple(v + m for v in self.low) + tuple(v - m for v in self.high)
        reasons = tuple(
            f"arm {i}: within {m} m of the {sign}{AXES[k]} face ({face} m) or beyond: motion out through it zeroed"
            for i in range(len(layout.arms))
            for k in range(3)
            for sign, face in (("+", self.high[k]), ("-", self.low[k]))
        )
        return inner, tuple(arm.offset for arm in layout.arms), reasons

    def compile(self, layout: ActionLayout) -> Check:
        (lx, ly, lz, hx, hy, hz), offsets, all_reasons = self._prepared(layout)
        # (index of the x component, reasons for +x, -x, +y, -y, +z, -z) per arm, built once:
        # the slow path only picks strings, it never formats.
        per_arm = tuple((o, all_reasons[6 * i : 6 * i + 6]) for i, o in enumerate(offsets))

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            reason: str | None = None
            for i, arm in enumerate(arms):
                x, y, z = p = arm.eef_pos
                if lx < x < hx and ly < y < hy and lz < z < hz:
                    continue
                if x - x != 0.0 or y - y != 0.0 or z - z != 0.0:  # NaN or ±inf
                    return None, f"arm {i}: end-effector position {p} is not finite"  # rare: format here
                o, reasons = per_arm[i]
                ax, ay, az = a[o : o + 3]
                zx = (ax > 0.0 and x >= hx) or (ax < 0.0 and x <= lx)
                zy = (ay > 0.0 and y >= hy) or (ay < 0.0 and y <= ly)
                zz = (az > 0.0 and z >= hz) or (az < 0.0 and z <= lz)
                if not (zx or zy or zz):
                    continue
                if b is None:
                    b = list(a)
                # Reasons join as "; ".join would, without a list for the usual single one.
                if zx:
                    b[o] = 0.0
                    note = reasons[0 if ax > 0.0 else 1]
                    reason = note if reason is None else f"{reason}; {note}"
                if zy:
                    b[o + 1] = 0.0
                    note = reasons[2 if ay > 0.0 else 3]
                    reason = note if reason is None else f"{reason}; {note}"
                if zz:
                    b[o + 2] = 0.0
                    note = reasons[4 if az > 0.0 else 5]
                    reason = note if reason is None else f"{reason}; {note}"
            if b is None:
                return None
            return b, reason  # type: ignore[return-value]

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for arm in arms:
                x, y, z = arm.eef_pos
                if not (lx < x < hx and ly < y < hy and lz < z < hz):
                    return slow(arms, a)
            return None

        return check

    def kernel_spec(self, layout: ActionLayout) -> KernelSpec:
        """This check for the fused kernel (``csrc/workspace_box.c``)."""
        return KernelSpec(self.kind, *self._prepared(layout))

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        for i, arm in enumerate(arms):
            p = arm.eef_pos
            for k in range(3):
                if not self.low[k] <= p[k] <= self.high[k]:
                    return f"arm {i}: end effector {AXES[k]}={p[k]} m is outside [{self.low[k]}, {self.high[k]}]"
        return None
