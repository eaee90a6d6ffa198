"""reach_limit: keep each end effector within its arm's reach and out of the column around its base.

Two failure modes the workspace box cannot see, because both happen inside it: an arm driven
past its reach flails (OSC near a singular configuration: the Panda droops into the table or
folds up over its own base), and an arm driven back towards its base runs the hand into its
own links (the Panda base of the single-arm tasks sits at x = −0.56 m, inside the box).

Per arm, with ``c`` its centre (the shoulder: the point the reach is measured from; the base
column is the vertical line through it):

* outer: ``v = w − c`` with ``w = p + R · point`` (``point`` in the site frame, e.g. the
  wrist; ``R`` the arm's orientation), ``u = v / r``, ``r = |v|``, ``d = max_radius − r``. While
  ``d < margin + brake`` the translational components moving away from ``c`` (``a_k · v_k > 0``)
  are shrunk so that the outward speed ``Σ_{a_k v_k > 0} a_k · u_k`` is at most
  ``q = max(0, (d − margin) / brake)`` (raised to ``creep`` inside the reach), by the least change
  (:func:`~capevo.runtime.governance.brake.brake_along`): the outward part is removed along ``u``
  and motion along the sphere keeps its speed. So a hand at full stretch with the wrist below the
  shoulder can still be lowered (mostly along the sphere there) while a push straight out is
  held to ``q``. Beyond the radius (``r > max_radius``) and with
  ``restore > 0``, each component is set to at least ``restore · |v_k| / r`` towards ``c`` and
  all six pose components are clamped to ``[−restore, restore]``.
* inner (``min_radius > 0``): in the horizontal plane, axis by axis, with ``h = (p − c)`` in x and y,
  ``ρ = |h|`` and ``d = ρ − min_radius``: components moving towards the column
  (``a_k · h_k < 0``) are limited to ``max(0, (d − margin) / brake) · ρ / (|h_x| + |h_y|)``, and inside the
  column the arm is pushed out along ``h`` (along +x when exactly on the axis).

Invariants (after the check, per arm, with the quantities above):
1. Outer: ``d < margin + brake`` implies ``Σ_{k: a_k v_k > 0} a_k · u_k <= s`` with
   ``s = max(0, (d − margin) / brake)`` (``brake == 0``: 0 once ``d <= margin``), raised to
   ``creep`` where ``0 < d``; only components with ``a_k · v_k > 0`` are changed for it, towards
   0 and never past it.
2. Inner: ``d < margin + brake`` implies, for x and y with ``a_k · h_k < 0``,
   ``|a_k| <= max(0, (d − margin) / brake) · ρ / (|h_x| + |h_y|)``.
3. With ``restore > 0``: outside the reach (``r > max_radius``) every axis has
   ``a_k · sign(v_k) <= −restore · |v_k| / r``; inside the column (``ρ < min_radius``) x and y
   have ``a_k · sign(h_k) >= restore · |h_k| / ρ``; in either case all six pose components lie
   in ``[−restore, restore]``.
4. The outer rules are applied first and the inner ones second, so where both apply (an end
   effector far below or above its shoulder, near the column) the column wins: the outer
   claims of 1 and 3 are made only for arms with ``ρ >= min_radius + margin + brake`` (or no
   column).
5. A component no rule applies to is unchanged; an action no rule touches is allowed (None)
   and never copied.
6. A non-finite end-effector position is ⊥ with a reason.
7. No hard limit of its own (:meth:`ReachLimit.unsafe` is None).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from capevo.errors import Invalid
from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.brake import brake_along
from capevo.runtime.governance.guard import MAX_RESTORE
from capevo.runtime.governance.pose import DOWN, finite_rotation_or_down, rotation_of
from capevo.runtime.state import ActionLayout, ArmState


def polar(v: tuple[float, float, float]) -> tuple[float, tuple[float, float, float] | None]:
    """``(|v|, v / |v|)`` for a finite ``v``, or ``(0.0, None)`` for the zero vector.

    Scales by the largest component first, so the direction is exact even where ``|v|``
    overflows (it is then inf) or its squares underflow.
    """
    mx = max(abs(v[0]), abs(v[1]), abs(v[2]))
    if mx == 0.0:
        return 0.0, None
    x, y, z = v[0] / mx, v[1] / mx, v[2] / mx
    n = math.sqrt(x * x + y * y + z * z)
    return mx * n, (x / n, y / n, z / n)


@register("reach_limit")
@dataclass(frozen=True, slots=True, kw_only=True)
class ReachLimit(ConstraintBase):
    """Outer reach sphere and inner base column per arm, with braking and restoring.

    Args:
        centres: One shoulder point (x, y, z) per arm in the layout's arm order, world frame, metres.
        max_radius: Reach: largest distance of the end effector from its centre, metres; > 0.
        min_radius: Radius in metres of the column around each centre's vertical axis that the
            end effector must stay out of; 0 (off) or below ``max_radius``.
        margin: Distance in metres from either limit at which motion towards it reaches 0; >= 0.
        brake: Width in metres of the band beyond the margin over which that motion is limited; >= 0.
        restore: Speed in action units back inside the limits; 0 (off) to 0.6.
        creep: Outward speed in action units still allowed between the margin and the reach
            itself (``0 < d``), so a hand can be placed slowly at the very edge; 0 (off) to 1.
        point: The point whose distance from the centre the reach limits, in the end-effector
            site frame (a Panda's wrist sits about 0.2 m behind its grip site: ``[0, 0, -0.2]``),
            turned by the arm's orientation (``ArmPose.eef_rot``; :data:`~capevo.runtime.governance.pose.DOWN`
            when the state has none). The column always uses the site itself.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value, no centres, a
            non-positive ``max_radius``, ``min_radius`` not in ``[0, max_radius)``, a negative
            margin or brake, or ``restore`` outside [0, 0.6].
    """

    centres: tuple[tuple[float, float, float], ...]
    max_radius: float
    min_radius: float = 0.0
    margin: float = 0.03
    brake: float = 0.1
    restore: float = 0.1
    creep: float = 0.0
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if not self.centres:
            raise invalid("centres", "at least one centre (one per arm) is required")
        if not self.max_radius > 0:
            raise invalid("max_radius", f"must be > 0, got {self.max_radius}")
        if not 0 <= self.min_radius < self.max_radius:
            raise invalid("min_radius", f"must be in [0, max_radius = {self.max_radius}), got {self.min_radius}")
        if self.margin < 0:
            raise invalid("margin", f"must be >= 0, got {self.margin}")
        if self.brake < 0:
            raise invalid("brake", f"must be >= 0, got {self.brake}")
        if not 0 <= self.restore <= MAX_RESTORE:
            raise invalid("restore", f"must be in [0, {MAX_RESTORE}], got {self.restore}")
        if not 0 <= self.creep <= 1:
            raise invalid("creep", f"must be in [0, 1], got {self.creep}")

    def compile(self, layout: ActionLayout) -> Check:
        if len(self.centres) != len(layout.arms):
            raise Invalid(
                f"centres: {len(self.centres)} given; the layout has {len(layout.arms)} arm(s)",
                details={"field": "centres"},
            )
        m, br, rs, creep = self.margin, self.brake, self.restore, self.creep
        band = m + br
        r_out = self.max_radius
        r_in = self.min_radius
        # Squared radii bounding the region where no rule applies: the fast path.
        pt = self.point
        lever = math.sqrt(pt[0] * pt[0] + pt[1] * pt[1] + pt[2] * pt[2])
        # The limited point is within `lever` of the site, so the site being this close is enough.
        far_out2 = (r_out - band - lever) ** 2 if r_out > band + lever else -1.0
        near_in2 = (r_in + band) ** 2 if r_in > 0.0 else -1.0
        arms_info = tuple((arm.offset, c) for arm, c in zip(layout.arms, self.centres, strict=True))
        reasons = tuple(
            (
                f"arm {i}: near the edge of its reach ({r_out} m): outward motion braked",
                f"arm {i}: beyond its reach ({r_out} m): steered back at {rs}",
                f"arm {i}: near the column around its base ({r_in} m): motion towards it braked",
                f"arm {i}: inside the column around its base ({r_in} m): steered out at {rs}",
            )
            for i in range(len(arms_info))
        )
        isfinite = math.isfinite

        def limit(d: float) -> float:
            if br > 0.0:
                q = (d - m) / br
                return q if q > 0.0 else 0.0
            return 0.0

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            b: list[float] | None = None
            notes: list[str] = []
            for i, (o, c) in enumerate(arms_info):
                p = arms[i].eef_pos
                if not (isfinite(p[0]) and isfinite(p[1]) and isfinite(p[2])):
                    return None, f"arm {i}: end-effector position {p} is not finite"  # rare: format here
                src = a if b is None else b
                arm = [src[o + j] for j in range(6)]
                why: list[str] = []
                # Outer sphere: u the unit vector from the centre to the limited point, r the distance.
                w = p
                if lever > 0.0:
                    rot = finite_rotation_or_down(arms[i])
                    if rot is None:
                        return None, f"arm {i}: end-effector orientation {rotation_of(arms[i])} is not finite"
                    w = tuple(
                        p[k] + rot[3 * k] * pt[0] + rot[3 * k + 1] * pt[1] + rot[3 * k + 2] * pt[2] for k in range(3)
                    )
                r, u = polar((w[0] * 0.5 - c[0] * 0.5, w[1] * 0.5 - c[1] * 0.5, w[2] * 0.5 - c[2] * 0.5))
                r *= 2.0
                d = r_out - r
                if (d < band or d <= m) and u is not None:
                    # The outward speed is bounded, not each axis: motion along the sphere (a
                    # stretched arm lowering its hand) is left as it is.
                    q = limit(d)
                    if d > 0.0 and q < creep:
                        q = creep  # inside the reach a gentle creep is left (see ``creep``)
                    before = (arm[0], arm[1], arm[2])
                    brake_along(arm, ((0, u[0]), (1, u[1]), (2, u[2])), q)
                    hit = (arm[0], arm[1], arm[2]) != before
                    if d < 0.0 and rs > 0.0:
                        for j in range(6):
                            arm[j] = min(max(arm[j], -rs), rs)
                        for k in (0, 1, 2):
                            back = rs * abs(u[k])
                            if u[k] > 0.0 and arm[k] > -back:
                                arm[k] = -back
                            elif u[k] < 0.0 and arm[k] < back:
                                arm[k] = back
                        why.append(reasons[i][1])
                    elif hit:
                        why.append(reasons[i][0])
                # Inner column: the same in the horizontal plane (along +x when exactly on the axis).
                if r_in > 0.0:
                    rho, h = polar((p[0] * 0.5 - c[0] * 0.5, p[1] * 0.5 - c[1] * 0.5, 0.0))
                    rho *= 2.0
                    d = rho - r_in
                    if d < band or d <= m:
                        hit = False
                        if h is not None:
                            cap_k = limit(d) / (abs(h[0]) + abs(h[1]))
                            for k in (0, 1):
                                if arm[k] * h[k] < 0.0 and abs(arm[k]) > cap_k:
                                    arm[k] = cap_k if arm[k] > 0.0 else -cap_k
                                    hit = True
                        ux, uy = (h[0], h[1]) if h is not None else (1.0, 0.0)
                        if d < 0.0 and rs > 0.0:
                            for j in range(6):
                                arm[j] = min(max(arm[j], -rs), rs)
                            for k, w in ((0, ux), (1, uy)):
                                out = rs * abs(w)
                                if w > 0.0 and arm[k] < out:
                                    arm[k] = out
                                elif w < 0.0 and arm[k] > -out:
                                    arm[k] = -out
                            why.append(reasons[i][3])
                        elif hit:
                            why.append(reasons[i][2])
                if any(arm[j] != src[o + j] for j in range(6)):
                    if b is None:
                        b = list(a)
                    b[o : o + 6] = arm
                    notes.extend(why)
            return edited(b, notes)

        # The site's test gives up `lever` (0.2 m for a wrist) before the limited point can be
        # near the reach, so most states of a stretched-out task fail it. Then the point itself is
        # tested, computed as slow() computes it, with a relative margin (1e-9, far above the few
        # ulps by which slow()'s polar() can differ) so that passing proves slow() would do nothing.
        safe = 1e-9
        far_w2 = ((r_out - band) * (1.0 - safe)) ** 2 if r_out > band else -1.0
        near_in2_safe = ((r_in + band) * (1.0 + safe)) ** 2 if r_in > 0.0 else -1.0
        pt0, pt1, pt2 = pt

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for i, (_, c) in enumerate(arms_info):
                arm = arms[i]
                x, y, z = arm.eef_pos
                dx, dy, dz = x - c[0], y - c[1], z - c[2]
                h2 = dx * dx + dy * dy
                # "Provably clear" comparisons, so NaN falls through to the slow path.
                if h2 + dz * dz < far_out2 and h2 > near_in2:
                    continue
                if lever > 0.0 and h2 > near_in2_safe:
                    rot = rotation_of(arm)
                    if rot is None:
                        rot = DOWN
                    # A non-finite orientation makes these NaN or inf, and so fails the test too.
                    wx = x + rot[0] * pt0 + rot[1] * pt1 + rot[2] * pt2 - c[0]
                    wy = y + rot[3] * pt0 + rot[4] * pt1 + rot[5] * pt2 - c[1]
                    wz = z + rot[6] * pt0 + rot[7] * pt1 + rot[8] * pt2 - c[2]
                    if wx * wx + wy * wy + wz * wz < far_w2:
                        continue
                return slow(arms, a)
            return None

        return check
