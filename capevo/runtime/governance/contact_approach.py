"""contact_approach: slow the hand down along every nearby pair the proximity sensor reports.

The predictive half of the force limit for what a fixed Φ cannot know: movable objects (cans,
cubes, nuts), the object in the hand, and the exact, tilted shape of the hand near anything.
It reads the per-arm :data:`~capevo.runtime.governance.proximity.Near` pairs of an
:class:`~capevo.runtime.governance.proximity.ArmScene` (arm states without them are left
alone). A contact struck at speed reads hundreds of newtons within one control step; struck
at the touch speed (0.04 action units, about 2 mm per step) it stays near 10 N, and the force
ramp takes over from there.

Per arm and pair ``(dist, n, r, owner)`` with ``q < 1``, where
``q = t + (1 − t) · clip((dist − clearance) / b, 0, 1)`` (``t``, ``b``: ``touch_loose`` and
``brake_loose`` for a movable object, ``touch_arm`` (when set) and ``brake`` for another arm,
``touch`` and ``brake`` otherwise):

* translation: the approaching components (``a_k · n_k > 0``) are shrunk so that their
  closing speed ``Σ_{a_k n_k > 0} a_k · n_k`` is at most ``q`` (receding components are left
  out of the sum: a later edit may shrink them, never the other way), by the smallest change
  that does it: each approaching component loses ``λ · n_k`` (clamped at 0, never flipped), so
  the motion along ``n`` is what is braked and the motion past the geom (a hand descending
  beside an object, whose pair points mostly sideways) keeps its speed;
  for a movable object below the hand (``n_z < 0``) whose bound is looser than the fixed
  scene's, the sum runs over x and y only, and the downward part ``a_z · n_z`` gets the fixed
  scene's bound (``touch``, ``brake``) on its own: pushed sideways such an object slides,
  pushed down it is pinned against what it rests on;
* rotation (``rotation``): every rotation component is limited to
  ``q_turn · min(1, lever / |r|)`` with ``q_turn = min(q, t_rot + (1 − t_rot) · clip((dist −
  clearance) / brake, 0, 1))`` (``t_rot`` = ``touch_rotation``; unset, ``q_turn = q``): turning
  swings the hand's far points, the more the farther they are from the site, and a hand in
  contact that turns wedges what it touches (measured on T6, the AM-bc baseline of
  ``results/cpu-small``: twisting the peg in the plate's hole at 0.04 read 45-66 N with every
  translation already held);
* a wrist link (the pair's index is in the arm's ``link_rows``: its hand side is link 5, 6 or 7,
  not the hand): the link does not move rigidly with the hand under OSC, so instead of the two
  rules above the pair is braked along its row ``g`` (:mod:`~capevo.runtime.governance.link_motion`,
  the link point's closing speed per action unit of each of the six pose components):
  ``Σ_{g_k a_k > 0} g_k a_k <= q`` by the same least change over all six components (measured
  on the AM baseline's T1 policy, ``results/cpu-small``: a hand twisting clear of everything drove
  the forearm into the bin at 315 N; braked along its row, none of its steps is unsafe);
* another arm (``owner`` another arm of the layout: the pair's other geom is that arm's hand
  or one of its links): the same for that arm with ``−n`` (its components with
  ``a_k · n_k < 0``), and with ``rotation`` its rotation components are limited to ``q_turn``,
  so neither side closes the gap fast.

``touch > 0`` keeps the hand able to close a small gap (to grasp, place or insert) at a gentle
speed; OSC's steady push at that speed stays far below the force limit.

Invariants (per arm, after the check):
1. For every pair with ``q < 1``: ``Σ_{k: a_k n_k > 0} a_k · n_k <= q`` (to rounding); for a
   movable object with ``n_z < 0`` and ``q > q_fixed(dist)`` the sum is over x and y, and
   ``a_z · n_z <= q_fixed(dist)``.
2. With ``rotation``, every rotation component has ``|ω_k| <= min over those pairs of
   q_turn · min(1, lever / |r|)`` (``q`` the smaller of the two bounds for a movable object below).
3. For a pair whose ``owner`` is another arm ``j`` of the layout, arm ``j`` has
   ``Σ_{k: a_k n_k < 0} −a_k · n_k <= q(dist)`` and (with ``rotation``) ``|ω_k| <= q_turn`` for its
   rotation components.
4. Only those components change, by clamping towards 0 (sign kept); arms no pair concerns
   are untouched; an action no rule touches is allowed (None) and never copied. Per pair, each
   approaching component loses ``λ · |n_k|`` or, if that is more, all of itself, one ``λ`` for all.
5. A non-finite pair or link row is ⊥ with a reason.
7. For a pair with a link row ``g``: ``Σ_{k: g_k a_k > 0} g_k a_k <= q`` over the six pose
   components (to rounding) in place of 1 and 2 for that pair; 3 holds for it as for any pair.
6. No hard limit of its own (:meth:`ContactApproach.unsafe` is None).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

from capevo.runtime.governance.base import Check, ConstraintBase, Result, edited, invalid, normalize, register
from capevo.runtime.governance.brake import brake_along
from capevo.runtime.governance.cap import SHRINK
from capevo.runtime.governance.proximity import LOOSE
from capevo.runtime.state import ActionLayout, ArmState


def _brake_other(
    poses: list[list[float]],
    touched: list[bool],
    q_rot: list[float],
    owner: int,
    nx: float,
    ny: float,
    nz: float,
    q: float,
    q_turn: float,
) -> None:
    """Another arm's hand or link is the pair's other side: its motion closes the gap too, along ``−n``."""
    other = poses[owner]
    v0, v1, v2 = -other[0] * nx, -other[1] * ny, -other[2] * nz
    c = v0 if v0 > 0.0 else 0.0
    if v1 > 0.0:
        c += v1
    if v2 > 0.0:
        c += v2
    if c > q:
        brake_along(other, ((0, nx), (1, ny), (2, nz)), q, sign=-1.0)
        touched[owner] = True
    if q_turn < q_rot[owner]:
        q_rot[owner] = q_turn


@register("contact_approach")
@dataclass(frozen=True, slots=True, kw_only=True)
class ContactApproach(ConstraintBase):
    """Closing speed along each sensed hand-to-scene pair limited in proportion to its distance.

    Args:
        clearance: Distance in metres at which the closing speed reaches ``touch``; >= 0.
        brake: Width in metres of the band beyond the clearance over which it is limited; > 0.
        touch: Closing speed allowed at and within the clearance, action units; in [0, 1].
        touch_loose: The same for a pair with a movable object (``owner`` -2), which gives way
            when pushed; in [0, 1].
        brake_loose: ``brake`` for a pair with a movable object; None: ``brake``; > 0.
        touch_arm: ``touch`` for a pair with another arm (its hand, what it holds, or a link);
            None: ``touch``; in [0, 1].
        rotation: Also limit the rotation components near a pair.
        touch_rotation: The rotation components' own floor at the clearance, ramping to 1 over
            ``brake`` like ``touch``; None: the translation's bound alone; in [0, 1].
        lever: Metres; a pair farther than this from the site limits rotation more; > 0.
        name: Label for interventions; defaults to the kind.

    Raises:
        Invalid: naming the field, on a wrong type, a non-finite value, a negative clearance,
            a non-positive brake or lever, or ``touch`` outside [0, 1].
    """

    reads_proximity: ClassVar[bool] = True
    """The state must carry proximity pairs (:class:`~capevo.runtime.governance.proximity.ArmScene`)."""
    clearance: float = 0.005
    brake: float = 0.1
    touch: float = 0.04
    touch_loose: float = 0.04
    brake_loose: float | None = None
    touch_arm: float | None = None
    rotation: bool = True
    touch_rotation: float | None = None
    lever: float = 0.1
    name: str | None = None

    def __post_init__(self) -> None:
        normalize(self)
        if self.clearance < 0:
            raise invalid("clearance", f"must be >= 0, got {self.clearance}")
        if not self.brake > 0:
            raise invalid("brake", f"must be > 0, got {self.brake}")
        if not 0 <= self.touch <= 1:
            raise invalid("touch", f"must be in [0, 1], got {self.touch}")
        if not 0 <= self.touch_loose <= 1:
            raise invalid("touch_loose", f"must be in [0, 1], got {self.touch_loose}")
        if self.touch_arm is not None and not 0 <= self.touch_arm <= 1:
            raise invalid("touch_arm", f"must be in [0, 1], got {self.touch_arm}")
        if self.touch_rotation is not None and not 0 <= self.touch_rotation <= 1:
            raise invalid("touch_rotation", f"must be in [0, 1], got {self.touch_rotation}")
        if self.brake_loose is not None and not self.brake_loose > 0:
            raise invalid("brake_loose", f"must be > 0, got {self.brake_loose}")
        if not self.lever > 0:
            raise invalid("lever", f"must be > 0, got {self.lever}")

    def bound(self, dist: float, owner: int = -1) -> float:
        """Largest closing speed ``q`` allowed at ``dist`` metres (1.0 beyond the band)."""
        loose = owner == LOOSE
        brake = self.brake_loose if loose and self.brake_loose is not None else self.brake
        x = (dist - self.clearance) / brake
        x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x
        t = self.touch_loose if loose else self.touch_arm if owner >= 0 and self.touch_arm is not None else self.touch
        return t + (1.0 - t) * x

    def rotation_bound(self, dist: float) -> float:
        """Largest rotation component ``touch_rotation`` allows at ``dist`` metres (inf when unset)."""
        if self.touch_rotation is None:
            return math.inf
        x = (dist - self.clearance) / self.brake
        x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x
        return self.touch_rotation + (1.0 - self.touch_rotation) * x

    def compile(self, layout: ActionLayout) -> Check:
        band = self.clearance + max(self.brake, self.brake_loose or 0.0)
        turn, lever = self.rotation, self.lever
        # bound()'s terms as locals: the loop inlines it (the same operations, so the same bits),
        # since a method call per pair costs more than the rest of a pair that needs no edit.
        cl = self.clearance
        br_fixed, t_fixed = self.brake, self.touch
        br_loose = self.brake_loose if self.brake_loose is not None else self.brake
        t_loose = self.touch_loose
        u_fixed, u_loose = 1.0 - t_fixed, 1.0 - t_loose
        # Another arm's own floor (None: the fixed scene's touch, bit for bit)
        t_arm = self.touch_arm if self.touch_arm is not None else t_fixed
        u_arm = 1.0 - t_arm
        # Rotation's own floor: None keeps the translation's bound q (bit for bit).
        t_rot = self.touch_rotation
        u_rot = 1.0 - t_rot if t_rot is not None else 0.0
        # With the same settings a movable object's bound is the fixed one, bit for bit, so it
        # needs no second bound (repr, not ==: a touch of -0.0 gives a bound of -0.0 at 0 m).
        split = repr((br_loose, t_loose)) != repr((br_fixed, t_fixed))
        offsets = tuple(arm.offset for arm in layout.arms)
        reasons = tuple(f"arm {i}: hand near a contact: motion towards it braked" for i in range(len(offsets)))
        isfinite, sqrt, inf = math.isfinite, math.sqrt, math.inf
        # Below this |r|^2 the lever factor is 1, rounding included (sqrt is monotone).
        lever2 = lever * lever * (1.0 - 1e-12)

        n_arms = len(offsets)

        def turn_bound(q: float, dist: float) -> float:
            """The rotation bound near a pair: ``q``, or ``touch_rotation``'s ramp where lower."""
            if t_rot is None:
                return q
            xr = (dist - cl) / br_fixed
            xr = t_rot + u_rot * (0.0 if xr < 0.0 else 1.0 if xr > 1.0 else xr)
            return xr if xr < q else q

        def slow(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            poses = [list(a[o : o + 6]) for o in offsets]
            q_rot = [inf] * n_arms
            # Arms an edit may have changed; the others are still their slice of ``a``.
            touched = [False] * n_arms
            for i in range(n_arms):
                arm = poses[i]
                qr_i = q_rot[i]  # only this arm's own pairs change it in this loop (owner != i)
                link_rows = getattr(arms[i], "link_rows", ())
                rows = dict(link_rows) if link_rows else None
                for k_pair, pair in enumerate(getattr(arms[i], "near", ())):
                    dist, nx, ny, nz, rx, ry, rz, owner = pair
                    # A finite sum proves all four finite; an overflowing one takes the exact test.
                    s = dist + nx + ny + nz
                    if s - s != 0.0 and not (isfinite(dist) and isfinite(nx) and isfinite(ny) and isfinite(nz)):
                        return None, f"arm {i}: proximity pair {pair} is not finite"  # rare: format here
                    if dist >= band:
                        continue
                    if split and owner == LOOSE:
                        x = (dist - cl) / br_loose
                        x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x
                        q = t_loose + u_loose * x
                        if nz < 0.0:
                            x = (dist - cl) / br_fixed
                            x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x
                            q_down = t_fixed + u_fixed * x
                        else:
                            q_down = q
                    else:
                        x = (dist - cl) / br_fixed
                        x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x
                        q = q_down = (t_arm + u_arm * x) if owner >= 0 else (t_fixed + u_fixed * x)
                    if q >= 1.0 and q_down >= 1.0:
                        continue  # at the edge of the band: nothing to limit
                    g = rows.get(k_pair) if rows is not None else None
                    if g is not None:
                        # A wrist link, not the hand: it moves as the joints realising the
                        # action move it (link_motion), translation and rotation alike.
                        if not isfinite(sum(g)):
                            return None, f"arm {i}: link row {g} of proximity pair {pair} is not finite"
                        brake_along(arm, tuple(enumerate(g)), q)  # a bound already met changes nothing
                        touched[i] = True  # only asks for the comparison with ``a`` below
                        if 0 <= owner < n_arms and owner != i:
                            q_turn = turn_bound(q, dist) if turn else inf
                            _brake_other(poses, touched, q_rot, owner, nx, ny, nz, q, q_turn)
                        continue
                    # Closing speed of the approaching components alone, summed as brake_along
                    # sums it (later edits only shrink components, which can lower it, never raise
                    # it): most pairs already meet their bound, and then nothing is built or called.
                    v0, v1, v2 = arm[0] * nx, arm[1] * ny, arm[2] * nz
                    c = v0 if v0 > 0.0 else 0.0
                    if v1 > 0.0:
                        c += v1
                    if q_down < q:
                        # A loose object below the hand slides when pushed sideways but is pinned
                        # against its support when pushed down: that part keeps the fixed bound.
                        if v2 > q_down:
                            arm[2] = q_down / nz * SHRINK
                            touched[i] = True
                        if c > q:
                            brake_along(arm, ((0, nx), (1, ny)), q)
                            touched[i] = True
                        q = q_down
                    else:
                        if v2 > 0.0:
                            c += v2
                        if c > q:
                            brake_along(arm, ((0, nx), (1, ny), (2, nz)), q)
                            touched[i] = True
                    if turn:
                        q_turn = turn_bound(q, dist)
                        rr = rx * rx + ry * ry + rz * rz
                        if rr < lever2:
                            qr = q_turn  # |r| < lever for sure: no sqrt needed for a factor of 1
                        else:
                            r = sqrt(rr) if isfinite(rx + ry + rz) else inf
                            qr = q_turn * (lever / r if r > lever else 1.0)
                        if qr < qr_i:
                            qr_i = qr
                    if 0 <= owner < n_arms and owner != i:
                        _brake_other(poses, touched, q_rot, owner, nx, ny, nz, q, q_turn if turn else inf)
                q_rot[i] = qr_i
            b: list[float] | None = None
            notes: list[str] = []
            for i, o in enumerate(offsets):
                arm = poses[i]
                qr = q_rot[i]
                if qr < inf:
                    for k in (3, 4, 5):
                        v = arm[k]
                        if abs(v) > qr:
                            arm[k] = qr if v > 0.0 else -qr
                            touched[i] = True
                if touched[i] and any(arm[j] != a[o + j] for j in range(6)):
                    if b is None:
                        b = list(a)
                    b[o : o + 6] = arm
                    notes.append(reasons[i])
            return edited(b, notes)

        def check(arms: Sequence[ArmState], a: Sequence[float]) -> Result:
            for arm in arms:
                if getattr(arm, "near", ()):
                    return slow(arms, a)
            return None

        return check
