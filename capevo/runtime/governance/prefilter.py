"""Prefilters: a check's first, cheap test, which lets most actions through before the rule runs.

Each wraps a rule's full check (``slow``) in a test that passes only states the rule provably
leaves alone. The tests are written so that a NaN reading fails them, so a broken reading always
reaches the rule, which rejects it.

Invariants:
1. A prefiltered check returns None without calling ``slow`` only when every arm passes the
   test; otherwise it returns what ``slow`` returns for the same arguments.
2. A non-finite reading never passes the test.
"""

from __future__ import annotations

from collections.abc import Sequence

from capevo.runtime.governance.base import Check, Result
from capevo.runtime.state import ArmState


def unless_all_inside(low: Sequence[float], high: Sequence[float], slow: Check) -> Check:
    """``slow`` for a state with some end effector not strictly inside the box ``[low, high]``; else None."""
    lx, ly, lz = low
    hx, hy, hz = high

    def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
        for arm in arms:
            x, y, z = arm.eef_pos
            if not (lx < x < hx and ly < y < hy and lz < z < hz):
                return slow(arms, a)
        return None

    return check


def unless_all_forces_within(limit2: float, slow: Check) -> Check:
    """``slow`` for a state with some contact force whose squared magnitude is above ``limit2``; else None."""

    def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
        for arm in arms:
            fx, fy, fz = arm.eef_force
            if not fx * fx + fy * fy + fz * fz <= limit2:
                return slow(arms, a)
        return None

    return check
