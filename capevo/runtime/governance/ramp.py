"""force_ramp: slow motion into a contact before the force limit, back off once above it.

Complements the paper's ``contact_force`` rule (which zeroes motion into a contact once the
force is above the limit). That rule alone lets an arm keep pushing at full speed up to the
limit and, being reactive, overshoot it; holding still above the limit keeps pressing, because
OSC holds the position it is pressed into. Sign convention as in
:mod:`capevo.runtime.governance.force`: ``f`` is the force on the end effector, and a
translational component ``a_k`` moves into the contact when ``a_k`` and ``f_k`` have opposite signs.

Per arm, with ``|f|`` the force magnitude:

* ramp: for ``soft_from < |f| <= max_force``, each component into the contact is limited in
  magnitude to ``speed · (max_force − |f|) / (max_force − soft_from)``: a slow push that fades
  to nothing at the limit. With OSC, the steady contact force grows with the commanded push
  (about 250 N per action unit for a Panda pressing on a table), so bounding the push bounds
  the force.
* back off (``backoff > 0``): for ``|f| > max_force``, each component along the force is set to
  at least ``backoff · |f_k| / |f|`` in the direction of ``f_k`` (away from the contact) and
  every pose component of the arm is clamped to ``[−backoff, backoff]``.

* hold off (``release > 0``, hysteresis): once the force has been above ``max_force``, motion into
  that contact (``a_k · u_k < 0`` for ``u`` the force's direction at that step) stays zeroed, at
  any force, until the hand has moved ``release`` metres back along ``u`` from where it was. A
  reactive rule alone lets a skill that keeps pressing re-approach as soon as the reading drops
  (issue 18 measured 16-36 single-step impacts an episode that way). The latch is the one piece
  of state in governance: it lives in the compiled check, so each :class:`Governor` (and
  :meth:`Governor.new_episode`) starts unlatched.

Invariants (after the check, per arm):
1. If ``soft_from < |f| <= max_force``: for every axis with ``a_k · f_k < 0``,
   ``|a_k| <= speed · (max_force − |f|) / (max_force − soft_from)``.
2. If ``|f| > max_force``: no component moves into the contact; with ``backoff > 0``, every
   axis has ``a_k · sign(f_k) >= backoff · |f_k| / |f|`` and all six pose components lie in
   ``[−backoff, backoff]``.
3. Arms with ``|f| <= soft_from`` are untouched; a component no rule applies to is unchanged;
   an action no rule touches is allowed (None) and never copied.
4. A non-finite force reading is ⊥ with a reason.
5. No hard limit of its own (:meth:`ForceRamp.unsafe` is None): ``contact_force`` judges forces.
6. With ``release > 0``: from a step whose force is above ``max_force`` until the first step whose
   end-effector position is at least ``release`` further along that step's force direction
   ``u``, no translational component moves into the contact (``a_k · u_k >= 0``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.force import into_contact
from capevo.runtime.governance.guard import MAX_RESTORE
from capevo.runtime.governance.prefilter import unless_all_forces_within
from capevo.runtime.state import ActionLayout, ArmState

MAX_RELEASE = 0.5
"""Largest hysteresis distance, metres: beyond it a latched arm could not back off inside the box."""


def stop_into(
    a: Sequence[float],
    b: list[float] | None,
    offset: int,
    f: Sequence[float],
    notes: list[str],
    reason: str,
) -> list[float] | None:
    """Zero the arm's translational components (from ``offset``) that move against ``f``.

    Edits ``b`` (a copy of ``a`` made on the first edit) and appends ``reason`` once if any changed.
    """
    changed = False
    for k in (0, 1, 2):
        if into_contact((a if b is None else b)[offset + k], f[k]):
            if b is None:
                b = list(a)
            b[offset + k] = 0.0
            changed = True
    if changed:
        notes.append(reason)
    return b


@register("force_ramp")
@dataclass(frozen=True, slots=True, kw_only=True)
class ForceRamp(ConstraintBase):
    """Into-contact speed ramped down between ``soft_from`` and ``max_force``; back-off above it.

    Args:
        max_force: The force limit in newtons (use ``contact_force``'s); > ``soft_from``.
        soft_from: Force in newtons from which motion into the contact is slowed; >= 0.
        speed: Largest into-contact component, in action units, at ``soft_from``; > 0.
        backoff: Speed in action units away from a contact above the limit; 0 (off) to 0.6.
        release: Hysteresis: metres the hand must back off along a contact's force direction,
            after the force was above the limit, before it may move into that contact again;
            0 (off) to 0.5.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value, ``soft_from`` not in
            ``[0, max_force)``, a non-positive speed, ``backoff`` outside [0, 0.6] or
            ``release`` outside [0, 0.5].
    """

    max_force: float = 20.0
    soft_from: float = 10.0
    speed: float = 0.05
    backoff: float = 0.05
    release: float = 0.0
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not 0 <= self.soft_from < self.max_force:
            raise invalid("soft_from", f"must be in [0, max_force = {self.max_force}), got {self.soft_from}")
        if not self.speed > 0:
            raise invalid("speed", f"must be > 0, got {self.speed}")
        if not 0 <= self.backoff <= MAX_RESTORE:
            raise invalid("backoff", f"must be in [0, {MAX_RESTORE}], got {self.backoff}")
        if not 0 <= self.release <= MAX_RELEASE:
            raise invalid("release", f"must be in [0, {MAX_RELEASE}], got {self.release}")

    def ramp_bound(self, magnitude: float) -> float:
        """Largest into-contact component allowed at force ``magnitude`` (<= max_force)."""
        return self.speed * (self.max_force - magnitude) / (self.max_force - self.soft_from)

    def compile(self, layout: ActionLayout) -> Check:
        soft2 = self.soft_from * self.soft_from
        lim2 = self.max_force * self.max_force
        ramp_bound, backoff, release = self.ramp_bound, self.backoff, self.release
        offsets = tuple(arm.offset for arm in layout.arms)
        reasons = tuple(
            (
                f"arm {i}: contact force above {self.soft_from} N: motion into the contact slowed",
                f"arm {i}: contact force above {self.max_force} N: backing off",
                f"arm {i}: contact force was above {self.max_force} N: motion into it held until "
                f"the hand has backed off {release} m",
            )
            for i in range(len(offsets))
        )
        sqrt = math.sqrt
        # Per arm, while latched: the force direction and the hand's position at the spike.
        latched: list[tuple[tuple[float, float, float], tuple[float, float, float]] | None] = [None] * len(offsets)

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, o in enumerate(offsets):
                fx, fy, fz = f = arms[i].eef_force
                if fx - fx != 0.0 or fy - fy != 0.0 or fz - fz != 0.0:  # NaN or ±inf
                    return None, f"arm {i}: force reading {f} is not finite"  # rare: format here
                n2 = fx * fx + fy * fy + fz * fz
                if release > 0.0:
                    pos = arms[i].eef_pos
                    if n2 > lim2:
                        n = sqrt(n2)
                        latched[i] = ((fx / n, fy / n, fz / n), (pos[0], pos[1], pos[2]))
                    elif (held := latched[i]) is not None:
                        u, p = held
                        if (pos[0] - p[0]) * u[0] + (pos[1] - p[1]) * u[1] + (pos[2] - p[2]) * u[2] >= release:
                            latched[i] = None
                        else:
                            b = stop_into(a, b, o, u, notes, reasons[i][2])
                if n2 <= soft2:
                    continue
                n = sqrt(n2)
                if n2 <= lim2:
                    bound = ramp_bound(n)
                    changed = False
                    for k in (0, 1, 2):
                        v = (a if b is None else b)[o + k]
                        if into_contact(v, f[k]) and abs(v) > bound:
                            if b is None:
                                b = list(a)
                            b[o + k] = bound if v > 0.0 else -bound
                            changed = True
                    if changed:
                        notes.append(reasons[i][0])
                    continue
                # Above the limit (contact_force zeroes motion into it); push away if configured.
                if backoff <= 0.0:
                    b = stop_into(a, b, o, f, notes, reasons[i][1])
                    continue
                src = a if b is None else b
                arm = [min(max(src[j], -backoff), backoff) for j in range(o, o + 6)]
                for k in (0, 1, 2):
                    away = backoff * abs(f[k]) / n
                    if f[k] > 0.0 and arm[k] < away:
                        arm[k] = away
                    elif f[k] < 0.0 and arm[k] > -away:
                        arm[k] = -away
                if any(arm[j] != src[o + j] for j in range(6)):
                    if b is None:
                        b = list(a)
                    b[o : o + 6] = arm
                    notes.append(reasons[i][1])
            return edited(b, notes)

        quiet = unless_all_forces_within(soft2, slow)

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            if latched.count(None) != len(latched):
                return slow(arms, a)
            return quiet(arms, a)

        return check if release > 0.0 else quiet
