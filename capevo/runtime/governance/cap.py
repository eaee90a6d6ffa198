"""velocity_cap: bound the size of each arm's commanded pose delta.

Paper default: 1.5 in action space. Precisely: for each arm, the Euclidean (L2) norm of its
six OSC_POSE components (3 translation + 3 rotation, before the controller's own clipping
to [−1, 1] and scaling to metres/radians) must not exceed ``max_norm``. Above it, those six
components are scaled down by one positive factor so the norm is just under ``max_norm``
(a relative 1e-9 under, so floating-point rounding can never leave it above). The gripper
command is untouched.

Invariants:
1. After the check, every arm's ``sum(a_k**2 for its 6 components) <= max_norm**2``,
   computed in that order in floats, for any finite input (huge values do not overflow).
2. The scaling keeps the direction of the 6-vector: every component keeps its sign (one far
   below the others may underflow to 0.0), zeros stay zero.
3. The hard limit (:meth:`VelocityCap.unsafe`) is that same sum above ``max_norm**2``, or a
   non-finite component anywhere in the executed action.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.runtime.governance.base import Check, ConstraintBase, Result, invalid, normalize, register
from capevo.runtime.state import ActionLayout, ArmState

INF = math.inf
SHRINK = 1.0 - 1e-9
"""Scaled norms land this fraction of the cap, so rounding cannot push them over it."""


def pose_norm2(a: Sequence[float], o: int) -> float:
    """Sum of squares of the six pose components at offset ``o``; the quantity the cap bounds."""
    x0, x1, x2, x3, x4, x5 = a[o], a[o + 1], a[o + 2], a[o + 3], a[o + 4], a[o + 5]
    return x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3 + x4 * x4 + x5 * x5


@register("velocity_cap")
@dataclass(frozen=True, slots=True, kw_only=True)
class VelocityCap(ConstraintBase):
    """Per-arm cap on the L2 norm of the six OSC pose-delta components.

    Args:
        max_norm: The cap, in action units; > 0.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type or a non-positive or non-finite cap.
    """

    max_norm: float = 1.5
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not self.max_norm > 0:
            raise invalid("max_norm", f"must be > 0, got {self.max_norm}")

    def compile(self, layout: ActionLayout) -> Check:
        cap = self.max_norm
        cap2 = cap * cap
        target = cap * SHRINK
        # (offset, reason) per arm: an intervention picks a prepared string, it never formats.
        per_arm = tuple(
            (arm.offset, f"arm {i}: pose-delta norm above the cap {cap}: scaled down to it")
            for i, arm in enumerate(layout.arms)
        )
        sqrt, hypot = math.sqrt, math.hypot

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            reason: str | None = None
            for o, note in per_arm:
                x0, x1, x2, x3, x4, x5 = a[o : o + 6]
                n2 = x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3 + x4 * x4 + x5 * x5
                if n2 <= cap2:
                    continue
                if b is None:
                    b = list(a)
                if n2 == INF:  # the squares overflowed: divide by the largest magnitude first
                    big = max(abs(x0), abs(x1), abs(x2), abs(x3), abs(x4), abs(x5))
                    x0, x1, x2, x3, x4, x5 = x0 / big, x1 / big, x2 / big, x3 / big, x4 / big, x5 / big
                    s = target / hypot(x0, x1, x2, x3, x4, x5)
                else:
                    s = target / sqrt(n2)
                b[o : o + 6] = x0 * s, x1 * s, x2 * s, x3 * s, x4 * s, x5 * s
                # Reasons join as "; ".join would, without building a list for the usual single one.
                reason = note if reason is None else f"{reason}; {note}"
            if b is None:
                return None
            return b, reason  # type: ignore[return-value]

        return check

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        if action is None:
            return None
        cap2 = self.max_norm * self.max_norm
        for i, arm in enumerate(layout.arms):
            n2 = pose_norm2(action, arm.offset)
            if not n2 <= cap2:
                return f"arm {i}: pose-delta norm {math.sqrt(n2)} is above the cap {self.max_norm}"
        return None
