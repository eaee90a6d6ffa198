"""stopping_distance: push back a hand or wrist link that closes on the fixed scene too fast to stop.

Every other proximity rule bounds what the action *asks*; none reads how fast the arm already
moves. Under robosuite's OSC (goal mode ``achieved``) a zero action does not hold the arm: it only
damps it, so an arm keeps what speed it has, and OSC's null-space posture term turns the elbow and
wrist with no action at all. Measured on the AM baseline's T1 policies of ``results/h2-t1``
(iteration 2, seed 2000042006 of the seed-42 cell; ``benchmarks/bench_policy_recheck.py``):

* the forearm (link 5) closed on bin 1's rim at 14, 13, 12 and 9 mm per step from 57 mm while its
  link row said the executed actions moved it *away* (``g · a`` −0.09 to +0.02), and struck it at
  207 N; once in contact, the surface rule's sideways 0.2 pressed it there at 45-80 N for 28 steps;
* the hand (iteration 3, the same seed) sank onto the bin's wall at 3-4 mm per step for six steps
  with every executed component along the pair 0 (joints 5 and 7 turning in OSC's null space) and
  struck it at 181 N.

So for each pair of a hand or a wrist link with the fixed scene (``owner`` -1), with ``v`` its
measured closing speed (:attr:`~capevo.runtime.governance.proximity.ArmScene.closing`, m/s) and
``dist`` its gap, the rule compares ``v`` with the fastest speed from which the point could still
stop before the pair's ``clearance`` at a deceleration ``decel``, and never less than ``touch``
(``contact_approach``'s touch speed: a grasp or a place needs it):

    v_stop = max(touch, sqrt(2 · decel · max(0, dist − clearance)))

and where ``v > v_stop`` asks for a motion away from the pair of ``p = min(1, gain · (v − v_stop))``
action units, the least change that gives ``g · a <= −p``
(:func:`~capevo.runtime.governance.keep_clear.steering_check`, as ``keep_clear``) for the pair's row:

* the hand: its point's rigid motion, ``g = (n, (r × n) · turn)`` (``r`` the point from the site,
  ``turn`` the controller's radians over metres per action unit);
* a wrist link: the translation part of its row (:mod:`~capevo.runtime.governance.link_motion`).
  The full row asks mostly for a turn, which the rules after this one limit near any pair
  (``contact_approach``, ``surface_approach``, ``obstacle_approach``): they cut the push back to
  a few hundredths, and the forearm strike above, replayed open loop, still reached 105 N.

Pairs with a movable object or another arm are left alone: the other side moves too, and the
measured speed is only this side's (``results/safety-keep-clear``: steering a link by its own
speed did not keep T6's two arms apart).

It is the second rule of the per-task Φ of the single-arm tasks, after ``keep_clear``: it adds
motion, and every rule after it still holds on what it leaves. T6's Φ leaves it out: there its push
let an oscillating adversary's two wrists meet at 118 N (``benchmarks/bench_governance_rates.py``,
T6, ``oscillate``, seed 49), which without it they do not; the push sees the fixed scene, not the
other arm it may carry this one towards. Placed last (after every shrinking rule) it prevented a little
more, but its push then broke the other rules' bounds (on T6's −x and −z constant adversaries and
both random ones of ``tests/runtime/governance/test_gov_robosuite.py``).

The settings of the single-arm tasks' Φ (``STOPPING`` in :mod:`~capevo.runtime.governance.task_phi`) are
hand-written. ``decel`` 0.2 m/s² (0.01 action units per step per step), ``clearance`` 3 mm (as
``keep_clear``'s band) and ``gain`` 3 action units per m/s were chosen on a prototype over the 120
held-out episodes of the six AM and AM-bc T1 cells of ``results/h2-t1`` (iterations 2 and 3; 23
unsafe under the default Φ without the rule); a larger deceleration (0.4, 0.8 m/s²) or gain (8)
let more through. ``touch`` 0.04 m/s is ``contact_approach``'s touch speed (0.04 action units a
step). The rule as shipped: 3 unsafe of those 120, and 13 of 240 episodes on seeds none of this
was chosen on (2000000100-119) against 39 without it; 8 of the 13 are still the forearm on the
bin. ``results/safety-stopping`` has every run, the variants tried, and the regression on the
skill sets capevo ships.

Invariants (per arm, after the check alone):
1. If the arm has exactly one fixed-scene pair with ``v > v_stop`` (and, for a link pair, a row
   whose translation part has ``g_t · g_t >= MIN_ROW2``), that pair meets its target ``g · a <= −p``
   for its row ``g`` as above, to rounding, unless every component it moves is at the bound it
   moved towards.
2. Only the arm's pose components change (for a link pair, its translation only); an action no
   pair asks to change is allowed (None) and never copied; every changed component is in [−1, 1].
3. A state without closing speeds (``closing`` empty) is left alone.
4. A non-finite pair, row or speed of a fixed-scene pair is ⊥ with a reason.
5. No hard limit of its own (:meth:`StoppingDistance.unsafe` is None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from capevo.runtime.governance.base import Check, ConstraintBase, invalid, normalize, register
from capevo.runtime.governance.keep_clear import MIN_ROW2, Goals, steering_check
from capevo.runtime.governance.proximity import FIXED
from capevo.runtime.state import ActionLayout, ArmState

MAX_CLEARANCE = 0.05
"""Metres: a larger clearance would keep the hand from what it is meant to reach."""
MAX_TURN = 100.0
"""Radians over metres per action unit: far above any arm controller's ratio."""
MAX_TOUCH = 0.5
"""m/s: faster than this is no touch (a tenth of OSC's full-scale 1 m/s)."""
MAX_GAIN = 10.0
"""Action units per m/s: above it a small error in the measured speed becomes a full-scale push."""


@register("stopping_distance")
@dataclass(frozen=True, slots=True, kw_only=True)
class StoppingDistance(ConstraintBase):
    """A push away from each fixed-scene pair the hand or a wrist link closes on too fast to stop.

    Args:
        decel: Deceleration in m/s² the arm is assumed to manage; > 0 and finite.
        clearance: Gap in metres at which the point should have stopped; in [0, 0.05].
        gain: Push away, action units per m/s of speed above the stopping speed; in (0, 10].
        touch: Closing speed in m/s that is always allowed, however close: what a touch needs
            (grasping, placing); in [0, 0.5].
        turn: Radians per action unit of the rotation components over metres per action unit of
            the translation ones (robosuite's OSC: 0.5 / 0.05); the hand's pairs are steered
            along their rigid motion ``(n, (r × n) · turn)``; in [0, 100].
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value or a value out of range.
    """

    reads_proximity: ClassVar[bool] = True
    """The state must carry proximity pairs with their closing speeds."""
    decel: float = 0.2
    clearance: float = 0.003
    gain: float = 3.0
    touch: float = 0.04
    turn: float = 10.0
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not (0 < self.decel < math.inf):
            raise invalid("decel", f"must be positive and finite, got {self.decel}")
        if not 0 <= self.clearance <= MAX_CLEARANCE:
            raise invalid("clearance", f"must be in [0, {MAX_CLEARANCE}], got {self.clearance}")
        if not 0 <= self.touch <= MAX_TOUCH:
            raise invalid("touch", f"must be in [0, {MAX_TOUCH}], got {self.touch}")
        if not 0 < self.gain <= MAX_GAIN:
            raise invalid("gain", f"must be in (0, {MAX_GAIN}], got {self.gain}")
        if not 0 <= self.turn <= MAX_TURN:
            raise invalid("turn", f"must be in [0, {MAX_TURN}], got {self.turn}")

    def stopping_speed(self, dist: float) -> float:
        """The fastest closing speed (m/s) allowed ``dist`` metres off: one it still stops from in
        time, and never less than ``touch``."""
        return max(self.touch, math.sqrt(2.0 * self.decel * max(0.0, dist - self.clearance)))

    def push(self, dist: float, speed: float) -> float:
        """The speed away (action units) asked of a pair ``dist`` off closing at ``speed`` m/s; 0 if none."""
        excess = speed - self.stopping_speed(dist)
        return min(1.0, self.gain * excess) if excess > 0.0 else 0.0

    def compile(self, layout: ActionLayout) -> Check:
        push, turn = self.push, self.turn
        isfinite = math.isfinite

        def goals_of(i: int, arm: ArmState) -> Goals | str:
            near = getattr(arm, "near", ())
            closing = getattr(arm, "closing", ())
            goals: Goals = []
            if not near or len(closing) != len(near):
                return goals
            rows = None
            for k, pair in enumerate(near):
                if pair[7] != FIXED:
                    continue
                speed = closing[k]
                if not (isfinite(speed) and all(isfinite(v) for v in pair[:4])):
                    return f"arm {i}: proximity pair {pair} or its closing speed {speed} is not finite"
                p = push(pair[0], speed)
                if p <= 0.0:
                    continue
                if rows is None:
                    rows = dict(getattr(arm, "link_rows", ()))
                g = rows.get(k)
                if g is None:
                    # The hand's point moves rigidly with the site: n · (v + ω × r) = n · v + ω · (r × n).
                    nx, ny, nz, rx, ry, rz = pair[1], pair[2], pair[3], pair[4], pair[5], pair[6]
                    rn = ((ry * nz - rz * ny) * turn, (rz * nx - rx * nz) * turn, (rx * ny - ry * nx) * turn)
                    goals.append(((nx, ny, nz, *rn), p))
                elif not all(isfinite(v) for v in g):
                    return f"arm {i}: link row {g} of proximity pair {pair} is not finite"
                elif g[0] * g[0] + g[1] * g[1] + g[2] * g[2] >= MIN_ROW2:
                    goals.append(((g[0], g[1], g[2], 0.0, 0.0, 0.0), p))
            return goals

        return steering_check(layout, "closing on the fixed scene faster than it can stop: pushed back", goals_of)
