"""keep_clear: steer a wrist link, or the hand near the fixed scene, back out of a thin band.

``contact_approach`` bounds how fast an arm may close on a sensed pair; at the clearance it still
allows the touch speed, and a zero command does not hold an arm still. Both let contacts through
that no task needs, measured on the AM baseline's T1 policy (a fresh cpu-small cell, iteration 3,
seeds 2000042010-049, under the default Φ of commit e90100c):

* the forearm (link 5) closed on the bin's rim at the touch speed along its row (executed
  commands of 0.01-0.09, 0.7 mm per step) and struck it at 82 N, then pressed at 64 N
  (seed 2000042049);
* a fingertip dragged sideways at the surface rule's ``lateral`` 0.2 sank 0.1 mm per step with
  its executed z at 0 (OSC's tracking, not the command) and caught the bin floor at 24-34 N
  (seeds 2000042026, -029, -038).

So within ``within`` metres of such a pair this rule asks for a small motion away from it, like
``workspace_guard``'s ``restore_within`` at the box's faces: ``p = restore · (1 − max(0, dist) /
within)`` (action units, the closing speed's units), and

* a pair whose hand side is a wrist link (its index is in the arm's ``link_rows``), whatever is on
  the other side: no task needs a link to touch anything. With the link's row ``g``
  (:mod:`~capevo.runtime.governance.link_motion`), if ``g · a > −p`` the arm's six pose components
  become ``a − ((g · a + p) / (g · g)) g``, the least change that gives ``g · a = −p``;
* a pair of the hand (or what it holds) with the fixed scene (``owner`` -1: a table, a bin, a peg):
  if ``n · a_t > −p`` for the translation ``a_t``, it becomes ``a_t − (n · a_t + p) n``. Pairs with
  a movable object or another arm are left to ``contact_approach``: grasping, pushing and
  inserting need those contacts.

Each pair is applied in the sensor's order, then the arm's pairs are visited again (at most
``PASSES`` times in all) until every pair in the band meets its target: projecting onto one pair can
undo part of another's (a fingertip between a floor and a wall). A row with ``g · g < MIN_ROW2``
(the action barely moves that link point) is skipped: no small command can steer it. A component
that would leave [−1, 1] stops at the bound and the others take the rest of the step.

The settings of the per-task Φ (``KEEP_CLEAR`` in :mod:`~capevo.runtime.governance.task_phi`) are
hand-written: ``within`` 3 mm, well inside ``contact_approach``'s 5 mm clearance, and ``restore``
0.1 (about 5 mm per step at contact). At 0.01 the AM-bc baseline's T1 fingertips, dragged
sideways at 0.2, stayed on the bin floor and still caught it at 29-37 N (seeds 2000042037 and
-038); at 0.03 they lifted clear, but one fingertip (seed 2000042030) still reached the floor at
39.5 N, and a hand carrying the can at the edge of its reach sagged about 1 mm per step against
the push and caught bin 2's rim at 26.9 N (the hand-set T2 set, seed 250018, once
``closing_grip`` had changed that episode's path). At 0.1 both are clear, and the hand-set sets
of T1-T5 and the evolved T1-T3 sets keep their held-out successes (``results/safety-closing-grip``).
What this rule does not reach: a link whose pair closes because the
*other* side moves or because OSC's null space swings it faster than a small command can undo. On
T6 the AM baseline's peg arm meets the plate with link 5 closing at about 2 cm per step, and
steering the link by its measured closing speed (tried, not kept) cleared at most 1 of 7 such seeds
(``results/safety-keep-clear/README.md``). Against the fixed scene, the measured speed is what
:mod:`~capevo.runtime.governance.stopping` reads, next after this rule.

Invariants (per arm, after the check alone):
1. If the arm has exactly one pair in the band with a target (a link pair with ``g · g >= MIN_ROW2``
   or a fixed-scene hand pair), that pair meets it: ``g · a <= −p`` or ``n · a_t <= −p`` (to
   rounding), unless every component it moves is at the bound it moved towards (−1 where
   ``g_k > 0``, +1 where ``g_k < 0``).
2. Only the arm's pose components change (a hand pair: its translation only); arms with no pair
   in the band are untouched; an action no pair asks to change is allowed (None) and never copied.
3. Every changed component lies in [−1, 1].
4. A non-finite pair or link row in the band is ⊥ with a reason.
5. No hard limit of its own (:meth:`KeepClear.unsafe` is None): what it prevents shows as force.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.guard import MAX_RESTORE
from capevo.runtime.governance.proximity import FIXED
from capevo.runtime.state import ActionLayout, ArmState

PASSES = 4
"""Visits of an arm's pairs at most: enough for the two or three pairs a corner gives."""
MIN_ROW2 = 0.01
"""Smallest ``g · g`` of a link row that is steered: below it (``|g| < 0.1``) a unit of action moves
the link point less than a tenth as much as it moves the hand."""
MAX_WITHIN = 0.05
"""Metres: a wider band would steer the hand away from what it is meant to reach."""


def _project(arm: list[float], g: tuple[float, ...], p: float) -> bool:
    """Move ``arm`` least (within [−1, 1]) so that ``g · arm <= −p``; True if it changed.

    The least-squares step ``−λ g`` over the components still free to move that way: a component
    that reaches ±1 stops there and the others share the rest, until the target is met or no
    component can move (then as close as the bounds allow).
    """
    changed = False
    free = [j for j in range(6) if g[j] != 0.0]
    while free:
        s = sum(g[j] * arm[j] for j in range(6))
        if s <= -p * (1.0 - 1e-12):
            break
        norm2 = sum(g[j] * g[j] for j in free)
        if norm2 == 0.0:
            break  # what is left free moves the point by less than a float can hold (g_j² underflows)
        lam = (s + p) / norm2
        clipped = []
        for j in free:
            v = arm[j] - lam * g[j]
            if v > 1.0 or v < -1.0:
                v = 1.0 if v > 1.0 else -1.0
                clipped.append(j)
            if v != arm[j]:
                arm[j] = v
                changed = True
        if not clipped:
            break
        free = [j for j in free if j not in clipped]
    return changed


def steer_away(arm: list[float], goals: Sequence[tuple[tuple[float, ...], float]]) -> bool:
    """Project ``arm`` (six pose components, in place) onto ``g · arm <= −p`` for each ``(g, p)``
    of ``goals``, in order, visiting them again (at most :data:`PASSES` times in all) while one
    still moves it: projecting onto one pair can undo part of another's. True if it changed."""
    before = list(arm)
    for _ in range(PASSES):
        moved = False
        for g, p in goals:
            moved = _project(arm, g, p) or moved
        if not moved:
            break
    return arm != before


Goals = list[tuple[tuple[float, ...], float]]
"""Per arm, ``(g, p)`` pairs: the six pose components' row ``g`` and the target ``g · a <= −p``."""


def steering_check(layout: ActionLayout, reason: str, goals_of: Callable[[int, ArmState], Goals | str]) -> Check:
    """A check that steers each arm's pose components onto ``goals_of(i, arm)`` (:func:`steer_away`).

    ``goals_of`` returns the arm's goals, or a reason for ⊥ (a non-finite input). Each arm that
    moved is noted with ``reason``; an action no arm's goals change is allowed (None).
    """
    offsets = tuple(arm.offset for arm in layout.arms)
    reasons = tuple(f"arm {i}: {reason}" for i in range(len(offsets)))

    def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
        b: list[float] | None = None
        notes: list[str] = []
        for i, o in enumerate(offsets):
            goals = goals_of(i, arms[i])
            if isinstance(goals, str):
                return None, goals
            if not goals:
                continue
            arm = [(a if b is None else b)[o + j] for j in range(6)]
            if steer_away(arm, goals):
                if b is None:
                    b = list(a)
                b[o : o + 6] = arm
                notes.append(reasons[i])
        return edited(b, notes)

    return check


@register("keep_clear")
@dataclass(frozen=True, slots=True, kw_only=True)
class KeepClear(ConstraintBase):
    """A small motion away from each sensed link pair and fixed-scene hand pair closer than ``within``.

    Args:
        within: Band in metres within which the arm is steered away; in (0, 0.05].
        restore: Speed away from the pair at distance 0, action units (falls to 0 at ``within``);
            in (0, 0.6].
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value or a value out of range.
    """

    reads_proximity: ClassVar[bool] = True
    """The state must carry proximity pairs (:class:`~capevo.runtime.governance.proximity.ArmScene`)."""
    within: float = 0.003
    restore: float = 0.1
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not 0 < self.within <= MAX_WITHIN:
            raise invalid("within", f"must be in (0, {MAX_WITHIN}], got {self.within}")
        if not 0 < self.restore <= MAX_RESTORE:
            raise invalid("restore", f"must be in (0, {MAX_RESTORE}], got {self.restore}")

    def target(self, dist: float) -> float:
        """The speed away from a pair ``dist`` metres off that the rule asks for (0 beyond ``within``)."""
        if dist >= self.within:
            return 0.0
        return self.restore * (1.0 - max(0.0, dist) / self.within)

    def compile(self, layout: ActionLayout) -> Check:
        within, target = self.within, self.target
        isfinite = math.isfinite

        def goals_of(i: int, arm: ArmState) -> Goals | str:
            goals: Goals = []
            rows = None
            for k_pair, pair in enumerate(getattr(arm, "near", ())):
                dist = pair[0]
                if dist >= within:
                    continue
                if not all(isfinite(v) for v in pair[:4]):
                    return f"arm {i}: proximity pair {pair} is not finite"
                if rows is None:
                    rows = dict(getattr(arm, "link_rows", ()))
                g = rows.get(k_pair)
                if g is not None:
                    if not all(isfinite(v) for v in g):
                        return f"arm {i}: link row {g} of proximity pair {pair} is not finite"
                    if sum(v * v for v in g) >= MIN_ROW2:
                        goals.append((tuple(g), target(dist)))
                elif pair[7] == FIXED:
                    goals.append(((pair[1], pair[2], pair[3], 0.0, 0.0, 0.0), target(dist)))
            return goals

        steer = steering_check(layout, f"a link or the hand within {within} m of the scene: steered away", goals_of)

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for arm in arms:
                for pair in getattr(arm, "near", ()):
                    if not pair[0] >= within:  # in the band, or NaN: look closer
                        return steer(arms, a)
            return None

        return check
