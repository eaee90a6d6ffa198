"""R(a, Φ): apply every constraint of Φ, in order, to each proposed action.

``governor(state, action)`` returns ``(governed, interventions)``:

* allow:  ``(action, ())``: the very object passed in, nothing allocated but the pair;
* modify: ``(a_prime, records)``: ``a_prime`` a new tuple (a numpy action gives plain floats);
* reject: ``(None, records)``: ⊥, the last record names the constraint and the reason.

On ⊥ the executor must not send the proposed action. It holds still by sending
:func:`hold_action` (zero OSC pose deltas: the controller keeps the current pose; the
gripper keeps its last command) or safe-aborts the episode, and records the intervention
in the trace either way. A ⊥ from any constraint short-circuits: later constraints do not run.

Governance-off (``enforce=False``, evaluation only): every action passes through unchanged
(``governed is action``), but the same checks run and the interventions R would have made
are returned with ``enforced=False`` and counted in :meth:`Governor.stats`.

Action frames: robosuite's OSC_POSE takes pose deltas in each robot's *base* frame, while Φ
is written in the world frame (positions, forces, box faces). A governor built with
``frames`` (one base-to-world rotation per arm; identity when omitted) rotates each arm's
three translational components into the world frame before the checks and rotates a
modified action back, so "outward through the +x face" means world +x whatever way the
robot is mounted (the two Pandas of TwoArmPegInHole are turned ±90° about z). For the
identity and for right-angle rotations with exact entries the round trip is exact.

Before Φ runs, the governor itself (label ``governor``) rejects an action of the wrong
length, with a non-numeric or non-finite (NaN/inf) component, or a state with the wrong
number of arms.

Invariants:
1. Allow path: when no constraint intervenes, the returned action ``is`` the argument and
   the interventions are the shared empty tuple; no records are built.
2. Enforcing: the returned action is None exactly when the last intervention is a reject;
   otherwise it equals the last intervention's ``result`` (or the input if there is none).
3. Every built-in edit that is not a restoring one only shrinks components towards 0 without
   flipping their sign (zeroing, clamping to a bound, scaling down; see
   :mod:`capevo.runtime.governance.base`), so wherever no restoring edit fires the governed
   action satisfies every constraint of Φ at once, whatever their order. Restoring edits
   (``workspace_guard``, ``force_ramp`` back-off, ``reach_limit``) fire only in states already
   past a limit (outside the box or the reach, inside a base column, above the force limit);
   they are applied in Φ order, a later shrinking edit keeps their sign, and where two limits
   conflict the later constraint wins.
4. Not enforcing: the returned action ``is`` the argument, always; the interventions and
   counters are exactly those an enforcing governor would produce for the same inputs.
5. ``stats().steps`` counts calls; ``modified + rejected`` counts calls with interventions.
6. With ``frames``, invariant 3 holds for the translational components rotated into the world
   frame (exactly for signed-permutation rotations, to rounding otherwise); the returned
   action and the records are always in the action's own frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from numpy import ndarray

from capevo.errors import Invalid
from capevo.runtime.governance.layouts import check_layout
from capevo.runtime.governance.records import GovernanceStats, Intervention, new_intervention
from capevo.runtime.state import ActionLayout, ArmState, RobotState

if TYPE_CHECKING:
    from capevo.runtime.governance.phi import Phi

GUARD = "governor"
"""Label of the governor's own input checks in interventions."""
NO_INTERVENTIONS: tuple[Intervention, ...] = ()
_isfinite = math.isfinite


def _floats_or_empty(values: Any) -> tuple[float, ...]:
    try:
        return tuple(map(float, values))
    except (TypeError, ValueError):
        return ()


class Governor:
    """R for one Φ and one action layout. Build it once per run: it precompiles every check.

    Args:
        phi: The envelope.
        layout: Where each arm's commands sit in the action vector.
        enforce: False for the evaluation-only governance-off mode (count, never change).
        frames: Per arm, the rotation from the arm's action (base) frame to the world frame as
            9 floats, row-major; None means the identity for every arm.

    Raises:
        Invalid: if the layout's indices do not fit its dimension, or a frame is not a rotation.
    """

    __slots__ = (
        "_checks",
        "_counts",
        "_dim",
        "_labels",
        "_modified",
        "_n_arms",
        "_rejected",
        "_rot",
        "_steps",
        "enforce",
        "frames",
        "layout",
        "phi",
    )

    def __init__(
        self,
        phi: Phi,
        layout: ActionLayout,
        *,
        enforce: bool = True,
        frames: Sequence[Sequence[float]] | None = None,
    ) -> None:
        self.phi = phi
        self.layout = check_layout(layout)
        self.enforce = enforce
        self.frames = check_frames(frames, len(layout.arms))
        # Only arms whose frame is not the identity pay for a rotation.
        self._rot = tuple((arm.offset, r) for arm, r in zip(layout.arms, self.frames, strict=True) if r != IDENTITY)
        if not self._rot:
            self._rot = None
        self._checks = tuple(c.compile(layout) for c in phi.constraints)
        self._labels = tuple(c.label for c in phi.constraints)
        self._dim = layout.dim
        self._n_arms = len(layout.arms)
        self.reset_stats()

    def new_episode(self) -> None:
        """Start an episode: forget what a stateful check remembers (the force ramp's latch).

        Checks are compiled afresh, which is what the constructor does; counters are kept.
        """
        self._checks = tuple(c.compile(self.layout) for c in self.phi.constraints)

    def reset_stats(self) -> None:
        """Zero the counters."""
        self._steps = 0
        self._modified = 0
        self._rejected = 0
        # Interventions per constraint, by index in Φ, with the governor's own guard last.
        self._counts = [0] * (len(self._labels) + 1)

    def stats(self) -> GovernanceStats:
        """Counters since construction or :meth:`reset_stats`."""
        return GovernanceStats(
            enforced=self.enforce,
            steps=self._steps,
            modified=self._modified,
            rejected=self._rejected,
            by_constraint={
                k: v for k, v in zip((GUARD, *self._labels), (self._counts[-1], *self._counts[:-1]), strict=True) if v
            },
        )

    def __call__(self, state: RobotState, action: Sequence[float]) -> tuple[Any, tuple[Intervention, ...]]:
        """Govern one proposed action.

        Args:
            state: The robot now; ``state.arms`` in the layout's arm order.
            action: A list, tuple or 1-D numpy array of the layout's length.

        Returns:
            ``(governed, interventions)``; see the module docstring.
        """
        self._steps += 1
        t = type(action)
        if t is ndarray:
            a = action.tolist() if action.ndim == 1 else None
        elif t is list or t is tuple:
            a = action
        else:
            a = self._as_list(action)
        arms = state.arms
        if a is None or len(a) != self._dim or len(arms) != self._n_arms:
            return self._guard(action, a, arms)
        try:
            s = sum(a)
        except TypeError:
            return self._guard(action, a, arms)
        # inf - inf and nan - x are nan; a finite sum proves every component finite.
        if s - s != 0.0 and not all(map(_isfinite, a)):
            return self._guard(action, a, arms)
        if self._rot is not None:
            a = _rotate(a, self._rot, to_world=True)
        checks = self._checks
        try:
            for i in range(len(checks)):
                r = checks[i](arms, a)
                if r is not None:
                    return self._intervene(action, a, arms, i, r)
        except TypeError:  # e.g. complex components, which the finiteness test lets through
            return self._guard(action, a, arms)
        return action, NO_INTERVENTIONS

    @staticmethod
    def _as_list(action: Any) -> list[Any] | None:
        tolist = getattr(action, "tolist", None)
        try:
            out = tolist() if tolist is not None else list(action)
        except (TypeError, ValueError):
            return None
        return out if isinstance(out, list) and not any(isinstance(x, list) for x in out) else None

    def _intervene(
        self, action: Any, a: Sequence[float], arms: Sequence[ArmState], i: int, r: tuple[Any, str]
    ) -> tuple[Any, tuple[Intervention, ...]]:
        checks, labels, enforce, counts = self._checks, self._labels, self.enforce, self._counts
        n = len(checks)
        rot = self._rot
        # Components keep the caller's number types (a tuple of ints stays ints where untouched);
        # converting every record to floats would cost more than the rest of this path.
        original = tuple(a if rot is None else _rotate(a, rot, to_world=False))
        records: list[Intervention] = []
        while True:
            new, reason = r
            if new is None:
                records.append(new_intervention(labels[i], original, None, reason, enforce))
                counts[i] += 1
                self._rejected += 1
                return (None if enforce else action), tuple(records)
            result = tuple(new if rot is None else _rotate(new, rot, to_world=False))
            records.append(new_intervention(labels[i], original, result, reason, enforce))
            original = result
            counts[i] += 1
            i += 1
            while i < n:
                r = checks[i](arms, new)
                if r is not None:
                    break
                i += 1
            else:
                self._modified += 1
                return (original if enforce else action), tuple(records)

    def _guard(self, action: Any, a: Any, arms: Sequence[ArmState]) -> tuple[Any, tuple[Intervention, ...]]:
        if a is None:
            reason = f"action of type {type(action).__name__} is not a flat sequence of numbers"
        elif len(a) != self._dim:
            reason = f"action has {len(a)} components; the layout expects {self._dim}"
        elif len(arms) != self._n_arms:
            reason = f"state has {len(arms)} arm(s); the layout expects {self._n_arms}"
        else:
            bad = [k for k, v in enumerate(a) if not isinstance(v, (int, float)) or not math.isfinite(v)]
            reason = f"action components {bad} are not finite numbers" if bad else "action is not numeric"
        original = _floats_or_empty(a) if a is not None else ()
        record = new_intervention(GUARD, original, None, reason, self.enforce)
        self._counts[-1] += 1
        self._rejected += 1
        return (None if self.enforce else action), (record,)


IDENTITY: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def check_frames(frames: Sequence[Sequence[float]] | None, n_arms: int) -> tuple[tuple[float, ...], ...]:
    """``frames`` as tuples of 9 floats, one per arm; the identity for each arm when None.

    Raises:
        Invalid: on the wrong count, or a matrix that is not a proper rotation (to 1e-6).
    """
    if frames is None:
        return (IDENTITY,) * n_arms
    out = tuple(tuple(float(x) for x in f) for f in frames)
    if len(out) != n_arms:
        raise Invalid(f"frames: {len(out)} given; the layout has {n_arms} arm(s)", details={"field": "frames"})
    for i, r in enumerate(out):
        if len(r) != 9 or not all(math.isfinite(x) for x in r):
            raise Invalid(f"frames[{i}]: expected 9 finite floats (row-major 3x3)", details={"field": f"frames[{i}]"})
        rows = (r[0:3], r[3:6], r[6:9])
        gram_ok = all(
            abs(sum(p * q for p, q in zip(rows[j], rows[k], strict=True)) - (1.0 if j == k else 0.0)) <= 1e-6
            for j in range(3)
            for k in range(3)
        )
        det = (
            r[0] * (r[4] * r[8] - r[5] * r[7]) - r[1] * (r[3] * r[8] - r[5] * r[6]) + r[2] * (r[3] * r[7] - r[4] * r[6])
        )
        if not gram_ok or abs(det - 1.0) > 1e-6:
            raise Invalid(f"frames[{i}]: not a rotation matrix", details={"field": f"frames[{i}]"})
    return out


def _rotate(a: Sequence[float], rot: tuple[tuple[int, tuple[float, ...]], ...], *, to_world: bool) -> list[float]:
    # world = R @ local for the translation of each listed arm; local = R.T @ world back.
    b = list(a)
    for o, r in rot:
        x, y, z = b[o], b[o + 1], b[o + 2]
        if to_world:
            b[o] = r[0] * x + r[1] * y + r[2] * z
            b[o + 1] = r[3] * x + r[4] * y + r[5] * z
            b[o + 2] = r[6] * x + r[7] * y + r[8] * z
        else:
            b[o] = r[0] * x + r[3] * y + r[6] * z
            b[o + 1] = r[1] * x + r[4] * y + r[7] * z
            b[o + 2] = r[2] * x + r[5] * y + r[8] * z
    return b


def hold_action(layout: ActionLayout, last: Sequence[float] | None = None) -> tuple[float, ...]:
    """The action an executor sends after ⊥: zero pose deltas, each gripper at its last command.

    Args:
        layout: The task's action layout.
        last: The previously executed action, if any; a non-finite or missing gripper value becomes 0.0.

    Returns:
        A tuple of ``layout.dim`` floats.
    """
    out = [0.0] * layout.dim
    if last is not None and len(last) == layout.dim:
        for arm in layout.arms:
            g = arm.gripper
            if g is not None and isinstance(last[g], (int, float)) and math.isfinite(last[g]):
                out[g] = float(last[g])
    return tuple(out)
