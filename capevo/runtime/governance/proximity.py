"""Proximity: how close each hand, and whatever it touches, is to everything else in the scene, per step.

A fixed Φ knows the fixed scene (tables, bin walls, pegs) but not where the movable objects are
(cans, cubes, nuts, the object in the hand), and a rigid contact struck at speed reads hundreds
of newtons within one control step. So the state governance reads can carry, per arm, the
nearest points between the hand and its surroundings, measured by MuJoCo on the live
simulator: :class:`ArmScene` is an :class:`~capevo.runtime.governance.pose.ArmPose` plus a
tuple of :data:`Near` pairs, and ``contact_approach``
(:mod:`capevo.runtime.governance.contact_approach`) slows the hand down along each pair's
direction as the gap closes.

:class:`ProximitySensor` is built once per MuJoCo model. Per arm it finds:

* the hand: every collidable geom in the subtree of the arm's end-effector body (gripper
  fingers and pads, a peg or a plate fixed to the hand);
* the held set, per step: every movable object (a body on a free joint) that the hand grasps,
  with all its geoms; it moves with the hand, so it counts as part of it. Grasped is robosuite's
  own test (``_check_grasp``) with its finger groups: the object touches a geom of the left finger
  and one of the right (``important_geoms["left_finger"]``, ``["right_finger"]``, pads included).
  The independent safety monitor decides what is held the same way
  (:mod:`capevo.runtime.safety_monitor`). An object that only one finger or the palm touches is
  not held: it stays among the others, so the hand's motion towards it is still slowed.
  (Counting every touching object as held let a finger that brushed the placed milk carton drop
  the can-to-milk pair in a T5 episode, seed 250022, and the freed hand drove the held can into
  the milk at 32 N.) Without finger groups
  (a sensor built without ``fingers``), every touching object counts as held;
* the others: every collidable geom that is neither the hand, nor held, nor a link of the
  arm's own kinematic chain (those cannot be reached by the hand in a way the reach limit
  does not already cover, and MuJoCo filters parent-child contacts anyway), nor a plane (the
  ground lies far below the workspace box's floor).

Each step, a broad phase keeps the pairs for which two lower bounds on their distance are both
below ``reach`` metres: the gap between the two geoms' world-aligned bounding boxes (of their
``geom_aabb`` boxes), and the gap from a sphere around the hand geom's box to the other's world
box. It is a fixed number of array operations over every candidate pair at once (numpy's cost
is per call, not per pair; the fixed scene's boxes are computed once). In the T1 episodes of
``benchmarks/bench_worker.py``, 11.0 pairs per step pass it and 9.9 of them are reported, so a
finer cull would have little left to save.
``mujoco.mj_geomDistance`` gives each kept pair's signed distance and nearest points. A pair is
reported when its distance is below ``reach``.

Invariants:
1. Every reported pair ``(dist, nx, ny, nz, rx, ry, rz, owner)`` has ``dist < reach``,
   ``(nx, ny, nz)`` a unit vector pointing from the hand towards the other geom (for a
   penetrating pair: the direction that deepens the penetration), ``(rx, ry, rz)`` the hand's
   nearest point relative to the end-effector site, metres, world frame, and ``owner`` the
   index of the arm whose motion moves the other geom (its hand or a link of its chain),
   :data:`LOOSE` (-2) for a movable object (a free body), or :data:`FIXED` (-1) for the rest
   of the scene. For two boxes (MuJoCo's own box-box distance is unreliable at this margin)
   ``dist`` is a lower bound on the distance instead, and ``n`` the direction it is measured
   along: the larger of a sphere around the hand's box and the separation along a face normal
   of either box (:meth:`ProximitySensor._box_to_box`).
2. Pairs of a hand geom with a geom of its own hand, of what it holds, or of its own arm's
   kinematic chain are never reported.
3. ``near(i)`` reads the simulator's current ``MjData`` only (positions, contacts); it does not
   step or modify the simulator.
4. :meth:`ProximitySensor.sense` gives one closing speed per pair, in the pairs' order: ``nᵀ J_p q̇``
   for the pair's hand-side point ``p`` on its body (m/s, positive towards the other geom; MuJoCo's
   ``mj_jac`` and the current joint velocities). For two boxes, whose ``dist`` is a lower bound,
   it is still the point's speed, not the bound's rate of change.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from capevo.runtime.governance.link_motion import ArmJoints, LinkMotion, LinkRow
from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.state import ArmState

Near = tuple[float, float, float, float, float, float, float, int]
"""One hand-to-scene pair: ``(dist, nx, ny, nz, rx, ry, rz, owner)``, see invariant 1."""

_LinkPair = tuple[int, int, tuple[float, float, float], tuple[float, float, float]]
"""A link pair found by :meth:`ProximitySensor._near`: index in its pairs, link body, nearest point, direction."""

Frame = tuple[list[float], tuple[float, float, float]]
"""A geom's rotation (row-major, 9 floats) and the world centre of its bounding box."""

FIXED = -1
"""``owner`` of a pair whose other geom is part of the fixed scene (table, bin, peg, a robot's mount)."""
LOOSE = -2
"""``owner`` of a pair whose other geom belongs to a movable object (a body on a free joint)."""

RETRY_MARGINS = (0.003, 0.01, 0.025, 0.05, 0.08)
"""Margins (metres) of the follow-up queries for a pair whose first distance query failed."""

DEFAULT_REACH = 0.11
"""Metres: pairs farther apart than this are not reported (``contact_approach``'s default band is 0.105)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ArmScene(ArmPose):
    """An arm pose plus the hand's nearest points to its surroundings."""

    near: tuple[Near, ...] = ()
    """Hand-to-scene pairs closer than the sensor's reach; see :mod:`capevo.runtime.governance.proximity`."""
    link_rows: tuple[tuple[int, LinkRow], ...] = ()
    """For the pairs in ``near`` whose hand side is a wrist link, not the hand: ``(index, row)``,
    how the action moves that link point along the pair (:mod:`~capevo.runtime.governance.link_motion`)."""
    closing: tuple[float, ...] = ()
    """For each pair in ``near``, in order: how fast its hand-side point moves along the pair's
    direction now, m/s (positive: towards the other geom), measured from the joint velocities.
    The other side's own motion is not counted. Empty when not measured."""


def near_of(arm: ArmState) -> tuple[Near, ...]:
    """The proximity pairs of ``arm`` if it carries them (an :class:`ArmScene`), else ``()``."""
    return getattr(arm, "near", ())


def _subtree(model: Any, root: int) -> set[int]:
    out = {root}
    for b in range(root + 1, model.nbody):
        if int(model.body_parentid[b]) in out:
            out.add(b)
    return out


def _ancestors(model: Any, body: int) -> set[int]:
    out: set[int] = set()
    b = int(model.body_parentid[body])
    while b > 0:
        out.add(b)
        b = int(model.body_parentid[b])
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class _Candidates:
    """One arm's broad-phase inputs while it holds one set of objects: built once, reused each step.

    The boxes of the others are kept in ``low`` and ``high``: the fixed scene's rows are written
    once, the moving geoms' rows (``low_moving``, ``high_moving``, views) every call.
    """

    hand: np.ndarray
    """Hand geoms: the hand's own, then those of what it holds."""
    others: np.ndarray
    """Other geoms: the fixed scene's, then the moving ones (less what the hand holds)."""
    ids: np.ndarray
    """The geoms whose world boxes are computed per call: ``hand``, then the moving others."""
    centre: np.ndarray
    """``ids``' local bounding-box centres, shaped ``(n, 1, 3)`` to broadcast against rotations."""
    half: np.ndarray
    """``ids``' local bounding-box half sizes, ``(n, 1, 3)``."""
    radius: np.ndarray
    """The hand geoms' bounding-sphere radii, ``(n_hand, 1)``."""
    low: np.ndarray
    """``(1, n_others, 3)``: the others' world boxes' low corners."""
    high: np.ndarray
    """``(1, n_others, 3)``: their high corners."""
    low_moving: np.ndarray
    """The moving others' rows of ``low`` (a view)."""
    high_moving: np.ndarray
    """The moving others' rows of ``high`` (a view)."""


class ProximitySensor:
    """Nearest hand-to-scene pairs per arm from a live MuJoCo model and data.

    Geoms welded to the world (tables, bin walls, pegs, robot mounts) have their world boxes
    computed once, on the first call of :meth:`near`.

    Args:
        model: ``MjModel``.
        data: ``MjData`` of the model (read each call; keep the same object).
        hand_bodies: Per arm, in action-layout order, the id of its end-effector body
            (the root of the hand's subtree).
        eef_sites: Per arm, the id of its end-effector site (where the action's rotation acts).
        reach: Pairs farther apart than this many metres are not reported.
        eef_bodies: Per arm, the end-effector body when ``hand_bodies`` are links above it
            (``wrist_links``): hand geoms outside its subtree are the arm's links, and with
            ``link_motion`` :meth:`sense` gives how the action moves their pairs. None: every
            hand geom moves with the end effector.
        link_motion: Rows for link pairs (:mod:`capevo.runtime.governance.link_motion`).
        fingers: Per arm, the geom ids of its two fingers ``(left, right)``; an object is held
            when it touches both. None: when it touches any hand geom.
    """

    def __init__(
        self,
        model: Any,
        data: Any,
        hand_bodies: Sequence[int],
        eef_sites: Sequence[int],
        *,
        reach: float = DEFAULT_REACH,
        eef_bodies: Sequence[int] | None = None,
        link_motion: LinkMotion | None = None,
        fingers: Sequence[tuple[Sequence[int], Sequence[int]]] | None = None,
    ) -> None:
        import mujoco  # here, not at module level: governance itself does not need MuJoCo

        self._mj = mujoco
        self.model, self.data, self.reach = model, data, float(reach)
        self._sites = tuple(int(s) for s in eef_sites)
        ct, ca = model.geom_contype, model.geom_conaffinity
        collidable = [g for g in range(model.ngeom) if ct[g] or ca[g]]
        # Movable objects: bodies on a free joint, with every collidable geom of their subtree.
        free = mujoco.mjtJoint.mjJNT_FREE
        free_roots = sorted({int(model.jnt_bodyid[j]) for j in range(model.njnt) if model.jnt_type[j] == free})
        self._object_of: dict[int, int] = {}
        self._object_geoms: dict[int, tuple[int, ...]] = {}
        for root in free_roots:
            bodies = _subtree(model, root)
            geoms = tuple(g for g in collidable if int(model.geom_bodyid[g]) in bodies)
            self._object_geoms[root] = geoms
            for g in geoms:
                self._object_of[g] = root
        aabb = np.asarray(model.geom_aabb, dtype=np.float64).reshape(-1, 6)
        self._centre = aabb[:, :3].copy()
        self._half = aabb[:, 3:].copy()
        self._radius = np.linalg.norm(self._half, axis=1)
        self._centre_l = self._centre.tolist()
        self._half_l = self._half.tolist()
        self._radius_l = self._radius.tolist()
        self._is_box = [int(t) == mujoco.mjtGeom.mjGEOM_BOX for t in model.geom_type]
        # Which arm moves each geom: its hand's subtree and its kinematic chain.
        owner_of_body: dict[int, int] = {}
        for i, body in enumerate(hand_bodies):
            for b in _subtree(model, int(body)) | _ancestors(model, int(body)):
                if int(model.body_weldid[b]) != 0:
                    owner_of_body.setdefault(b, i)
        self._owner = {
            g: owner_of_body.get(int(model.geom_bodyid[g]), LOOSE if g in self._object_of else FIXED)
            for g in collidable
        }
        arms = []
        for body in hand_bodies:
            hand_b = _subtree(model, int(body))
            chain = _ancestors(model, int(body))
            hand = tuple(g for g in collidable if int(model.geom_bodyid[g]) in hand_b)
            others = [
                g
                for g in collidable
                if int(model.geom_bodyid[g]) not in hand_b
                and int(model.geom_bodyid[g]) not in chain
                and int(model.geom_type[g]) != mujoco.mjtGeom.mjGEOM_PLANE
            ]
            static = [g for g in others if int(model.body_weldid[int(model.geom_bodyid[g])]) == 0]
            moving = [g for g in others if g not in static]
            arms.append((hand, np.asarray(static, dtype=np.int64), np.asarray(moving, dtype=np.int64)))
        self._arms = tuple(arms)
        # World boxes of the geoms welded to the world, per arm: filled on the first call, when
        # the data has surely been through a forward pass.
        self._static_boxes: list[tuple[np.ndarray, np.ndarray]] | None = None
        # Per arm and held set, the broad phase's index arrays and buffers (built on first use).
        self._candidates: dict[tuple[int, tuple[int, ...]], _Candidates | None] = {}
        self._hand_sets = tuple(frozenset(a[0]) for a in arms)
        # Per arm, {finger geom: 0 left or 1 right}; empty: any hand geom grasps.
        self._finger_of: tuple[dict[int, int], ...] = tuple(
            {} if fingers is None else {g: side for side, group in enumerate(fingers[i]) for g in group}
            for i in range(len(arms))
        )
        self._fromto = np.zeros(6)
        # Hand geoms on links above the end-effector body, with their bodies (empty: none sensed).
        self._link_body: tuple[dict[int, int], ...] = tuple({} for _ in arms)
        if eef_bodies is not None and link_motion is not None:
            for i, (hand, _, _) in enumerate(arms):
                eef = _subtree(model, int(eef_bodies[i]))
                self._link_body[i].update(
                    {g: int(model.geom_bodyid[g]) for g in hand if int(model.geom_bodyid[g]) not in eef}
                )
        self._link_motion = link_motion
        self._body_of = [int(b) for b in model.geom_bodyid]
        self._jacp: np.ndarray | None = None

    @classmethod
    def for_robots(
        cls, model: Any, data: Any, robots: Sequence[Any], *, reach: float = DEFAULT_REACH, wrist_links: int = 0
    ) -> ProximitySensor:
        """A sensor for every arm of robosuite ``robots`` (``env.robots``), in action-layout order.

        ``wrist_links`` > 0 senses from that many links above the hand (the Panda's link 7, then
        link 6, ...), so the wrist's own geoms are part of what is sensed: two arms working face to
        face (TwoArmPegInHole) can touch wrist to wrist or wrist to plate with both hands clear.
        """
        import mujoco

        bodies, sites, eef_bodies, joints = [], [], [], []
        fingers: list[tuple[list[int], list[int]]] = []
        for robot in robots:
            for arm in robot.arms:
                groups = robot.gripper[arm].important_geoms
                fingers.append(
                    tuple(  # type: ignore[arg-type]
                        [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for name in groups[side]]
                        for side in ("left_finger", "right_finger")
                    )
                )
                body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.robot_model.eef_name[arm])
                eef_bodies.append(body)
                for _ in range(wrist_links):
                    parent = int(model.body_parentid[body])
                    if int(model.body_weldid[parent]) == 0:
                        break  # never climb onto the fixed world
                    body = parent
                bodies.append(body)
                sites.append(int(robot.eef_site_id[arm]))
                scale = tuple(float(v) for v in robot.part_controllers[arm].output_max)
                joints.append(ArmJoints(site=sites[-1], dofs=tuple(robot._ref_joint_vel_indexes), scale=scale))
        motion = LinkMotion(model, data, joints) if wrist_links else None
        return cls(model, data, bodies, sites, reach=reach, eef_bodies=eef_bodies, link_motion=motion, fingers=fingers)

    def _boxes(self, geoms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned boxes ``(low, high)`` of ``geoms``' bounding boxes, now."""
        if geoms.size == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        d = self.data
        rot = d.geom_xmat[geoms].reshape(-1, 3, 3)
        centre = d.geom_xpos[geoms] + (rot * self._centre[geoms][:, None, :]).sum(axis=2)
        half = (np.abs(rot) * self._half[geoms][:, None, :]).sum(axis=2)
        return centre - half, centre + half

    def _frame(self, g: int) -> Frame:
        """Geom ``g``'s rotation (row-major, 9 floats) and the world centre of its bounding box, now."""
        d = self.data
        # Plain floats: for one 3x3 rotation, numpy's per-call cost dominates.
        return self._frame_of(g, d.geom_xmat[g].tolist(), d.geom_xpos[g].tolist())

    def _frame_of(self, g: int, r: list[float], p: list[float]) -> Frame:
        cx, cy, cz = self._centre_l[g]
        return r, (
            p[0] + r[0] * cx + r[1] * cy + r[2] * cz,
            p[1] + r[3] * cx + r[4] * cy + r[5] * cz,
            p[2] + r[6] * cx + r[7] * cy + r[8] * cz,
        )

    def _frames(self, geoms: Sequence[int]) -> dict[int, Frame]:
        """:meth:`_frame` of each of ``geoms``, read from the data in one go."""
        ids = sorted(set(geoms))
        if not ids:
            return {}
        d = self.data
        rots, pos = d.geom_xmat[ids].tolist(), d.geom_xpos[ids].tolist()
        return {g: self._frame_of(g, r, p) for g, r, p in zip(ids, rots, pos, strict=True)}

    def _sphere_to_box(
        self, h: int, o: int, fh: Frame | None = None, fo: Frame | None = None
    ) -> tuple[float, float, float, float, float, float, float] | None:
        """``(dist, p1, p2)`` from a sphere around box ``h`` to box ``o``: a lower bound on their distance.

        ``fh`` and ``fo``: the two geoms' :meth:`_frame` if already read.
        """
        c = (fh or self._frame(h))[1]
        ro, q = fo or self._frame(o)
        cx, cy, cz = c
        qx, qy, qz = q
        vx, vy, vz = cx - qx, cy - qy, cz - qz
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = ro
        hx, hy, hz = self._half_l[o]
        # The sphere's centre in the other box's frame, clamped into the box, back to the world.
        x = r0 * vx + r3 * vy + r6 * vz
        ix = -hx if x < -hx else hx if x > hx else x
        x = r1 * vx + r4 * vy + r7 * vz
        iy = -hy if x < -hy else hy if x > hy else x
        x = r2 * vx + r5 * vy + r8 * vz
        iz = -hz if x < -hz else hz if x > hz else x
        p2x = qx + r0 * ix + r1 * iy + r2 * iz
        p2y = qy + r3 * ix + r4 * iy + r5 * iz
        p2z = qz + r6 * ix + r7 * iy + r8 * iz
        wx, wy, wz = p2x - cx, p2y - cy, p2z - cz
        gap = math.sqrt(wx * wx + wy * wy + wz * wz)
        radius = self._radius_l[h]
        if gap < 1e-9:
            # The sphere's centre is inside the box: point at the box's centre instead.
            wx, wy, wz = qx - cx, qy - cy, qz - cz
            n = math.sqrt(wx * wx + wy * wy + wz * wz)
            if n < 1e-9:
                return None
            return (-radius, cx + wx / n * radius, cy + wy / n * radius, cz + wz / n * radius, cx, cy, cz)
        t = (gap if gap < radius else radius) / gap  # min(radius, gap)
        return (gap - radius, cx + wx * t, cy + wy * t, cz + wz * t, p2x, p2y, p2z)

    def _box_to_box(
        self, h: int, o: int, fh: Frame | None = None, fo: Frame | None = None
    ) -> tuple[float, float, float, float, float, float, float] | None:
        """``(dist, p1, p2)`` for boxes ``h`` and ``o``: the larger of two lower bounds on their distance.

        One is :meth:`_sphere_to_box`; the other is the separating-axis bound: along each face
        normal ``s`` of either box the two are at least ``|(c_o − c_h)·s| − e_h(s) − e_o(s)``
        apart (``e(s)`` a box's half extent along ``s``), exactly so for faces that face each
        other. The sphere is up to ``√3`` times a thin box's half size fatter than the box, and
        beside a box's edge it points diagonally across it; the face bound is exact for a finger
        pad beside a cube's face or a held cube above another, and points along the face normal,
        so motion parallel to that face does not count as closing on it. ``p1`` is the hand
        box's corner farthest along the direction (for the rotation lever) and ``p2 − p1`` the
        bound along it. ``fh`` and ``fo``: the two geoms' :meth:`_frame` if already read.
        """
        fh = fh or self._frame(h)
        fo = fo or self._frame(o)
        sphere = self._sphere_to_box(h, o, fh, fo)
        (rh, c1), (ro, c2) = fh, fo
        hx, hy, hz = self._half_l[h]
        ox, oy, oz = self._half_l[o]
        gx, gy, gz = c2[0] - c1[0], c2[1] - c1[1], c2[2] - c1[2]
        # Box axes are the columns of the row-major rotations: u_i for the hand, w_j for the other.
        u0, u1, u2 = (rh[0], rh[3], rh[6]), (rh[1], rh[4], rh[7]), (rh[2], rh[5], rh[8])
        w0, w1, w2 = (ro[0], ro[3], ro[6]), (ro[1], ro[4], ro[7]), (ro[2], ro[5], ro[8])
        # c_ij = |u_i . w_j|, written out (without a generator's per-item overhead)
        (a0, a1, a2), (b0, b1, b2), (e0, e1, e2) = w0, w1, w2
        x0, x1, x2 = u0
        c00, c01, c02 = (
            abs(x0 * a0 + x1 * a1 + x2 * a2),
            abs(x0 * b0 + x1 * b1 + x2 * b2),
            abs(x0 * e0 + x1 * e1 + x2 * e2),
        )
        x0, x1, x2 = u1
        c10, c11, c12 = (
            abs(x0 * a0 + x1 * a1 + x2 * a2),
            abs(x0 * b0 + x1 * b1 + x2 * b2),
            abs(x0 * e0 + x1 * e1 + x2 * e2),
        )
        x0, x1, x2 = u2
        c20, c21, c22 = (
            abs(x0 * a0 + x1 * a1 + x2 * a2),
            abs(x0 * b0 + x1 * b1 + x2 * b2),
            abs(x0 * e0 + x1 * e1 + x2 * e2),
        )
        best, axis, sign = -math.inf, None, 1.0
        # Each face normal's separation: the hand box's three, then the other box's.
        for n, half, extent in (
            (u0, hx, c00 * ox + c01 * oy + c02 * oz),
            (u1, hy, c10 * ox + c11 * oy + c12 * oz),
            (u2, hz, c20 * ox + c21 * oy + c22 * oz),
            (w0, ox, c00 * hx + c10 * hy + c20 * hz),
            (w1, oy, c01 * hx + c11 * hy + c21 * hz),
            (w2, oz, c02 * hx + c12 * hy + c22 * hz),
        ):
            along = gx * n[0] + gy * n[1] + gz * n[2]
            sep = abs(along) - half - extent
            if sep > best:
                best, axis, sign = sep, n, along
        hh = (hx, hy, hz)
        ah = (u0, u1, u2)
        if axis is None or not best > 0.0 or (sphere is not None and sphere[0] >= best):
            return sphere
        nx, ny, nz = axis if sign >= 0.0 else (-axis[0], -axis[1], -axis[2])
        # The hand box's corner farthest along n, and a point the bound beyond it.
        px, py, pz = c1
        for i in range(3):
            a0, a1, a2 = ah[i]
            e = hh[i] if nx * a0 + ny * a1 + nz * a2 >= 0.0 else -hh[i]
            px += e * a0
            py += e * a1
            pz += e * a2
        return (best, px, py, pz, px + best * nx, py + best * ny, pz + best * nz)

    def _touching(self, h: int, o: int) -> bool:
        """Whether MuJoCo's own collision step found a contact between geoms ``h`` and ``o``."""
        d = self.data
        n = int(d.ncon)
        if n == 0:
            return False
        return any((g1 == h and g2 == o) or (g1 == o and g2 == h) for g1, g2 in d.contact.geom[:n].tolist())

    def _retry(self, h: int, o: int) -> tuple[float, float, float, float, float, float, float] | None:
        """``(dist, p1, p2)`` for a pair whose full-margin query failed: the first clean answer
        of queries with growing margins, or the largest margin known to be clear (a lower bound)."""
        m, d, ft = self.model, self.data, self._fromto
        clear = 0.0
        for margin in RETRY_MARGINS:
            if margin > self.reach:
                break
            dist = self._mj.mj_geomDistance(m, d, h, o, margin, ft)
            if 0.0 < dist < margin:
                return (dist, *ft.tolist())
            if dist < margin:
                break  # another zero: take what is known
            clear = margin
        if clear >= self.reach:
            return None
        # Direction: from the hand geom's centre towards the nearest point of the other's box.
        box = self._sphere_to_box(h, o)
        if box is None:
            return None
        _, p1x, p1y, p1z, p2x, p2y, p2z = box
        return (clear, p1x, p1y, p1z, p2x, p2y, p2z)

    def sensed(self, arm: int) -> tuple[int, ...]:
        """The geoms sensed as arm ``arm``'s hand (without what it holds)."""
        return tuple(self._arms[arm][0])

    def held(self, arm: int) -> tuple[int, ...]:
        """Movable objects (free-body ids) ``arm``'s hand grasps now: touched by both fingers
        (by any hand geom when the sensor has no finger groups)."""
        d = self.data
        n = int(d.ncon)
        if n == 0 or not self._object_of:
            return ()
        hand, fingers = self._hand_sets[arm], self._finger_of[arm]
        touched: dict[int, set[int]] = {}  # object -> the finger sides touching it (0 for any geom)
        for g1, g2 in d.contact.geom[:n].tolist():
            if g1 in hand and g2 in self._object_of:
                g, obj = g1, self._object_of[g2]
            elif g2 in hand and g1 in self._object_of:
                g, obj = g2, self._object_of[g1]
            else:
                continue
            if not fingers:
                touched.setdefault(obj, set()).add(0)
            elif g in fingers:
                touched.setdefault(obj, set()).add(fingers[g])
        need = 2 if fingers else 1
        return tuple(obj for obj, sides in touched.items() if len(sides) >= need)

    def _candidates_of(self, arm: int, held: tuple[int, ...]) -> _Candidates | None:
        """:class:`_Candidates` of ``arm`` holding ``held`` (None: no hand or nothing else)."""
        if self._static_boxes is None:
            self._static_boxes = [self._boxes(static) for _, static, _ in self._arms]
        hand, static, moving = self._arms[arm]
        s_lo, s_hi = self._static_boxes[arm]
        if held:
            extra = [g for obj in held for g in self._object_geoms[obj]]
            hand = hand + tuple(extra)
            moving = moving[~np.isin(moving, extra)]
        others = np.concatenate((static, moving))
        if not hand or others.size == 0:
            return None
        hand_ids = np.asarray(hand, dtype=np.int64)
        ids = np.concatenate((hand_ids, moving))
        n_static = static.size
        low = np.zeros((1, others.size, 3))
        high = np.zeros((1, others.size, 3))
        low[0, :n_static], high[0, :n_static] = s_lo, s_hi
        return _Candidates(
            hand=hand_ids,
            others=others,
            ids=ids,
            centre=self._centre[ids][:, None, :],
            half=self._half[ids][:, None, :],
            radius=self._radius[hand_ids][:, None],
            low=low,
            high=high,
            low_moving=low[0, n_static:],
            high_moving=high[0, n_static:],
        )

    def near(self, arm: int) -> tuple[Near, ...]:
        """Pairs of ``arm``'s hand (and what it holds) with the rest of the scene closer than ``reach``."""
        return self._near(arm, None)

    def sense(self, arm: int) -> tuple[tuple[Near, ...], tuple[tuple[int, LinkRow], ...], tuple[float, ...]]:
        """:meth:`near`; for its pairs whose hand side is a link above the end effector
        ``(index into the pairs, row)``, the row from
        :meth:`~capevo.runtime.governance.link_motion.LinkMotion.row` (none without link sensing);
        and each pair's closing speed (:attr:`ArmScene.closing`)."""
        motion = self._link_motion
        closing: list[float] = []
        if motion is None:
            return self._near(arm, None, closing), (), tuple(closing)
        links: list[_LinkPair] = []
        pairs = self._near(arm, links, closing)
        return pairs, tuple((k, motion.row(arm, body, p, n)) for k, body, p, n in links), tuple(closing)

    def _closing(self, body: int, point: tuple[float, float, float], n: tuple[float, float, float]) -> float:
        """How fast ``point`` on ``body`` moves along ``n`` now, m/s: ``nᵀ J_p(point) q̇``."""
        m, d = self.model, self.data
        if self._jacp is None:
            self._jacp = np.zeros((3, m.nv))
        self._mj.mj_jac(m, d, self._jacp, None, np.asarray(point, dtype=np.float64), body)
        v = self._jacp @ d.qvel
        return float(n[0] * v[0] + n[1] * v[1] + n[2] * v[2])

    def _near(self, arm: int, links: list[_LinkPair] | None, closing: list[float] | None = None) -> tuple[Near, ...]:
        """:meth:`near`; with ``links``, each link pair's index, body, nearest point and direction
        is appended to it; with ``closing``, each pair's closing speed."""
        m, d, reach = self.model, self.data, self.reach
        link_body = self._link_body[arm]
        held = self.held(arm)
        key = (arm, held)
        if key in self._candidates:
            cand = self._candidates[key]
        else:
            cand = self._candidates[key] = self._candidates_of(arm, held)
        if cand is None:
            return ()
        # The hand's and the moving geoms' world boxes in one pass. numpy's cost here is per
        # call, not per row, so the broad phase is a fixed number of array operations on index
        # arrays and buffers built once per arm and held set. Sums over the last axis (3 terms)
        # are written out: the same additions in the same order, without a reduction's overhead.
        rot = d.geom_xmat[cand.ids].reshape(-1, 3, 3)
        t = rot * cand.centre
        centre = d.geom_xpos[cand.ids] + (t[..., 0] + t[..., 1] + t[..., 2])
        t = np.abs(rot) * cand.half
        half = t[..., 0] + t[..., 1] + t[..., 2]
        n_hand = cand.hand.size
        m_centre, m_half = centre[n_hand:], half[n_hand:]
        np.subtract(m_centre, m_half, out=cand.low_moving)
        np.add(m_centre, m_half, out=cand.high_moving)
        lo, hi = cand.low, cand.high
        # Broad phase, per hand geom and other geom: the larger of two lower bounds on their
        # distance, a sphere around the hand geom's box and its world box, each against the other's world box.
        c = centre[:n_hand, None, :]
        h = half[:n_hand, None, :]
        t = np.maximum(lo - c - h, c - h - hi)
        np.maximum(t, 0.0, out=t)
        t *= t
        box_gap = np.sqrt(t[..., 0] + t[..., 1] + t[..., 2])
        t = np.minimum(np.maximum(c, lo), hi) - c  # from the hand box's centre to the other's box
        t *= t
        sphere_gap = np.sqrt(t[..., 0] + t[..., 1] + t[..., 2]) - cand.radius
        hi_idx, oi_idx = np.nonzero(np.maximum(box_gap, sphere_gap) < reach)
        if hi_idx.size == 0:
            return ()
        site = d.site_xpos[self._sites[arm]].tolist()
        ft = self._fromto
        out: list[Near] = []
        geom_distance = self._mj.mj_geomDistance
        xpos = d.geom_xpos
        owner = self._owner
        boxes = self._is_box
        body_of = self._body_of
        hs, os_ = cand.hand[hi_idx].tolist(), cand.others[oi_idx].tolist()
        # A box pair's geoms are read once per call, however many pairs they are in.
        frames = self._frames([g for h, o in zip(hs, os_, strict=True) if boxes[h] and boxes[o] for g in (h, o)])
        for h, o in zip(hs, os_, strict=True):
            if boxes[h] and boxes[o]:
                # MuJoCo's box-box distance is unreliable with a margin this large (it reports 0
                # for boxes centimetres apart), so bound it from below: a sphere around the hand's
                # box, or the boxes' separation along a face normal where that is larger.
                pair = self._box_to_box(h, o, frames[h], frames[o])
                if pair is None:
                    continue
                dist, p1x, p1y, p1z, p2x, p2y, p2z = pair
            else:
                dist = geom_distance(m, d, h, o, reach, ft)
                if dist <= 0.0 and not self._touching(h, o):
                    # A zero with no contact between the two: MuJoCo's convex distance with a
                    # large margin can return 0 on failure. Re-ask with growing margins.
                    pair = self._retry(h, o)
                    if pair is None:
                        continue
                    dist, p1x, p1y, p1z, p2x, p2y, p2z = pair
                else:
                    p1x, p1y, p1z, p2x, p2y, p2z = ft.tolist()
            if not dist < reach:
                continue
            vx, vy, vz = p2x - p1x, p2y - p1y, p2z - p1z
            norm = math.sqrt(vx * vx + vy * vy + vz * vz)
            if norm < 1e-9:
                # Touching exactly: the nearest points coincide; point from the hand geom's centre.
                cx, cy, cz = xpos[h].tolist()
                vx, vy, vz = p2x - cx, p2y - cy, p2z - cz
                norm = math.sqrt(vx * vx + vy * vy + vz * vz)
                if norm < 1e-9:
                    continue
            elif dist < 0.0:
                # Penetrating: the nearest points are swapped; deeper is from p2 towards p1.
                vx, vy, vz = -vx, -vy, -vz
            if links is not None and h in link_body:
                links.append((len(out), link_body[h], (p1x, p1y, p1z), (vx / norm, vy / norm, vz / norm)))
            if closing is not None:
                closing.append(self._closing(body_of[h], (p1x, p1y, p1z), (vx / norm, vy / norm, vz / norm)))
            out.append((dist, vx / norm, vy / norm, vz / norm, p1x - site[0], p1y - site[1], p1z - site[2], owner[o]))
        return tuple(out)
