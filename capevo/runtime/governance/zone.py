"""forbidden_zone: axis-aligned boxes no end effector may enter (optional; not in the default Φ).

Rule: for each arm and each zone, when the end effector is within ``margin`` of the zone
(inside the zone grown by ``margin`` on every side), then on every axis where it lies
below the zone a positive component is set to 0.0, and where it lies above, a negative one.
Near an edge or corner that blocks each approaching axis, which is conservative. If the end
effector is already inside a zone, components pointing towards the zone's centre are set
to 0.0, so it can only leave.

Invariants:
1. After the check, for every arm and zone whose grown box contains the end effector
   ``p`` (closed), and every axis ``k``: ``p_k < low_k`` implies ``a_k <= 0``;
   ``p_k > high_k`` implies ``a_k >= 0``; and if ``p`` is inside the zone (closed) then
   ``p_k < centre_k`` implies ``a_k <= 0`` and ``p_k > centre_k`` implies ``a_k >= 0``.
2. Only such components are zeroed; anything else is allowed and never copied.
3. A non-finite end-effector position is ⊥ with a reason.
4. The hard limit (:meth:`ForbiddenZone.unsafe`) is an end effector strictly inside a zone.
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
from capevo.runtime.state import ActionLayout, ArmState


@dataclass(frozen=True, slots=True, kw_only=True)
class Aabb:
    """An axis-aligned box in the world frame, metres.

    Raises:
        Invalid: naming the field, if ``low`` is not below ``high`` on every axis.
    """

    low: tuple[float, float, float]
    high: tuple[float, float, float]

    def __post_init__(self) -> None:
        normalize(self)
        check_corners(self.low, self.high)


@register("forbidden_zone")
@dataclass(frozen=True, slots=True, kw_only=True)
class ForbiddenZone(ConstraintBase):
    """Boxes the end effectors must not enter.

    Args:
        boxes: One or more zones, each ``{low: [x, y, z], high: [x, y, z]}``.
        margin: Distance in metres around a zone within which approaching motion is zeroed; >= 0.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on no boxes, a bad box or a negative margin.
    """

    boxes: tuple[Aabb, ...]
    margin: float = 0.08
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not self.boxes:
            raise invalid("boxes", "at least one box is required")
        if self.margin < 0:
            raise invalid("margin", f"must be >= 0, got {self.margin}")

    def compile(self, layout: ActionLayout) -> Check:
        m = self.margin
        # (grown low, grown high, zone low, zone high, centre) per box, flattened for the fast path.
        zones = tuple(
            (
                tuple(v - m for v in z.low),
                tuple(v + m for v in z.high),
                z.low,
                z.high,
                tuple((lo + hi) / 2 for lo, hi in zip(z.low, z.high, strict=True)),
            )
            for z in self.boxes
        )
        grown = tuple((*g_lo, *g_hi) for g_lo, g_hi, _, _, _ in zones)
        offsets = tuple(arm.offset for arm in layout.arms)
        n_arms = len(offsets)
        # reasons[arm][zone][inside][axis], built once so the slow path never formats.
        reasons = tuple(
            tuple(
                tuple(
                    tuple(
                        f"arm {i}: {'inside' if inside else f'within {m} m of'} forbidden zone {zi}: "
                        f"motion {'deeper into' if inside else 'towards'} it along {ax} zeroed"
                        for ax in AXES
                    )
                    for inside in (False, True)
                )
                for zi in range(len(zones))
            )
            for i in range(n_arms)
        )
        isfinite = math.isfinite

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i in range(n_arms):
                p, o = arms[i].eef_pos, offsets[i]
                if not (isfinite(p[0]) and isfinite(p[1]) and isfinite(p[2])):
                    return None, f"arm {i}: end-effector position {p} is not finite"  # rare: format here
                for zi, (g_lo, g_hi, z_lo, z_hi, centre) in enumerate(zones):
                    if not (g_lo[0] <= p[0] <= g_hi[0] and g_lo[1] <= p[1] <= g_hi[1] and g_lo[2] <= p[2] <= g_hi[2]):
                        continue
                    inside = z_lo[0] <= p[0] <= z_hi[0] and z_lo[1] <= p[1] <= z_hi[1] and z_lo[2] <= p[2] <= z_hi[2]
                    lo, hi = (centre, centre) if inside else (z_lo, z_hi)
                    for k in (0, 1, 2):
                        v = (a if b is None else b)[o + k]
                        if (v > 0.0 and p[k] < lo[k]) or (v < 0.0 and p[k] > hi[k]):
                            if b is None:
                                b = list(a)
                            b[o + k] = 0.0
                            notes.append(reasons[i][zi][inside][k])
            return edited(b, notes)

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for arm in arms:
                x, y, z = arm.eef_pos
                for lx, ly, lz, hx, hy, hz in grown:
                    # Written as "provably outside" so a NaN coordinate falls through to the slow path.
                    if not (x < lx or x > hx or y < ly or y > hy or z < lz or z > hz):
                        return slow(arms, a)
            return None

        return check

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        for i, arm in enumerate(arms):
            p = arm.eef_pos
            if not all(math.isfinite(v) for v in p):
                return f"arm {i}: end-effector position {p} is not finite"
            for zi, z in enumerate(self.boxes):
                if all(z.low[k] < p[k] < z.high[k] for k in range(3)):
                    return f"arm {i}: end effector {p} is inside forbidden zone {zi}"
        return None
