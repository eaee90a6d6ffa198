"""The hand as boxes in its end-effector site frame: how low it reaches and how far it extends, turned.

Invariants:
1. :func:`lowest_offset` is the minimum over every corner of every box of the world-z offset
   ``(R · corner)_z``; :func:`hand_extent` is the axis-aligned box of all turned corners.
2. :func:`hand_reach` bounds the distance of every corner from the site, so for any rotation
   every offset from the two functions above lies within ``[−hand_reach, hand_reach]``.
3. No boxes: the site point itself (offsets 0, reach 0).
4. :func:`box_gap` gives, per axis, 0 and side 0 where two boxes overlap on that axis (or touch,
   or a bound is NaN), else their positive distance along it; ``dist`` is the Euclidean norm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from capevo.runtime.governance.zone import Aabb

Vec3 = tuple[float, float, float]


def hand_reach(hand: Sequence[Aabb]) -> float:
    """Largest distance of any corner of ``hand`` from the site, metres."""
    return max(
        (math.sqrt(sum(max(abs(lo), abs(hi)) ** 2 for lo, hi in zip(b.low, b.high, strict=True))) for b in hand),
        default=0.0,
    )


def lowest_offset(hand: Sequence[Aabb], rot: Sequence[float]) -> float:
    """Smallest world-z offset from the site of any corner of ``hand``'s boxes, for rotation ``rot``.

    Returns:
        0.0 for no boxes (the site itself).
    """
    r6, r7, r8 = rot[6], rot[7], rot[8]
    best = 0.0 if not hand else math.inf
    for box in hand:
        lo, hi = box.low, box.high
        # Per axis, the corner that lowers z most: the low side where the row entry is positive.
        v = (
            (r6 * lo[0] if r6 > 0.0 else r6 * hi[0])
            + (r7 * lo[1] if r7 > 0.0 else r7 * hi[1])
            + (r8 * lo[2] if r8 > 0.0 else r8 * hi[2])
        )
        if v < best:
            best = v
    return best


def hand_extent(hand: Sequence[Aabb], rot: Sequence[float]) -> tuple[Vec3, Vec3]:
    """World-frame offsets ``(low, high)`` from the site of the box bounding ``hand`` turned by ``rot``.

    Returns:
        Zero offsets for no boxes (the site point itself).
    """
    if not hand:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    lo = [math.inf] * 3
    hi = [-math.inf] * 3
    for box in hand:
        c = [(box.low[j] + box.high[j]) / 2 for j in range(3)]
        h = [(box.high[j] - box.low[j]) / 2 for j in range(3)]
        for k in range(3):
            r0, r1, r2 = rot[3 * k], rot[3 * k + 1], rot[3 * k + 2]
            mid = r0 * c[0] + r1 * c[1] + r2 * c[2]
            half = abs(r0) * h[0] + abs(r1) * h[1] + abs(r2) * h[2]
            lo[k] = min(lo[k], mid - half)
            hi[k] = max(hi[k], mid + half)
    return (lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2])


def box_gap(
    low: Sequence[float], high: Sequence[float], other_low: Sequence[float], other_high: Sequence[float]
) -> tuple[float, list[float], list[int]]:
    """How far the box ``[other_low, other_high]`` lies from the box ``[low, high]``, world frame.

    Returns:
        ``(dist, gaps, sides)``: per axis the gap between the two boxes and the side the other
        box lies on (+1: towards +k from the first, -1: towards -k, 0: they overlap along k),
        and ``dist``, the distance between the boxes.
    """
    gaps = [0.0, 0.0, 0.0]
    sides = [0, 0, 0]
    for k in (0, 1, 2):
        if high[k] < other_low[k]:
            gaps[k], sides[k] = other_low[k] - high[k], 1
        elif other_high[k] < low[k]:
            gaps[k], sides[k] = low[k] - other_high[k], -1
    return math.sqrt(gaps[0] * gaps[0] + gaps[1] * gaps[1] + gaps[2] * gaps[2]), gaps, sides
