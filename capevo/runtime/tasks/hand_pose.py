"""Where a single Panda's hand points: quaternion helpers and the wall-aware yaw of a grasp.

Plain Python on ``math`` and ``numpy`` only, because the text of this module (below its
imports) is also pasted into every built-in code skill (``capevo.learner.skills._lib``), whose
contract allows no other imports: the scripted references and the skills share one implementation.

Quaternions are (x, y, z, w), world frame. Hand-written: the hand's size (from the robosuite Panda
gripper model) and the rule that turns it parallel to nearby walls (see :func:`clear_of_walls`).

Invariants:
1. ``rot_error(q, q)`` is zero; ``rot_error`` returns the shortest turn (angle at most pi).
2. ``held_down(down_at(y))`` equals ``down_at(y)`` (up to the sign of the quaternion).
3. ``clear_of_walls`` with ``walls=None`` is ``DOWN``; otherwise it returns ``down_at(y)`` for a yaw
   ``y`` in [0, pi/2] or the current yaw.
"""

import math

import numpy as np

DOWN = (1.0, 0.0, 0.0, 0.0)
"""Gripper pointing down, fingers (and the hand's long side) along world y (quaternion x, y, z, w)."""


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def rot_error(current, target=DOWN):
    """Axis-angle (world frame, radians) that turns quaternion ``current`` into ``target``."""
    cur = np.asarray(current, dtype=np.float64)
    inv = np.array([-cur[0], -cur[1], -cur[2], cur[3]]) / max(float(np.dot(cur, cur)), 1e-12)
    q = quat_mul(np.asarray(target, dtype=np.float64), inv)
    if q[3] < 0:
        q = -q
    s = float(np.linalg.norm(q[:3]))
    if s < 1e-9:
        return np.zeros(3)
    return q[:3] / s * 2.0 * math.atan2(s, q[3])


HAND_HALF_LENGTH = 0.105
"""Half the Panda hand's length along its fingers' travel (metres; hand-written from the model)."""
HAND_HALF_WIDTH = 0.035
"""Half the hand's thickness across the fingers' travel (metres; hand-written from the model)."""


def down_at(yaw):
    """Gripper pointing down, turned ``yaw`` radians about world z from DOWN."""
    return (math.cos(0.5 * yaw), math.sin(0.5 * yaw), 0.0, 0.0)


def yaw_of(current):
    """The yaw (about world z, from DOWN) of a hand pointing roughly down."""
    return 2.0 * math.atan2(float(current[1]), float(current[0]))


def heading(quat):
    """An object's rotation about world z (radians, its own x axis: 0 along world +x)."""
    x, y, z, w = (float(c) for c in quat)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def folded(yaw):
    """``yaw`` folded into [-pi/2, pi/2]: a two-finger grip turned by pi is the same grip."""
    while yaw > 0.5 * math.pi:
        yaw -= math.pi
    while yaw < -0.5 * math.pi:
        yaw += math.pi
    return yaw


def held_down(current):
    """Down at the hand's current yaw: holds the turn a reach chose."""
    return down_at(yaw_of(current))


def clear_of_walls(obj, current, walls, band=0.01):
    """The down orientation whose yaw keeps the hand farthest inside the walls around ``obj``.

    The hand is 0.21 m long along its fingers' travel and 7 cm thin across it, so over an
    object near a wall only a hand turned (about) parallel to that wall gets down without
    touching the rim. ``walls`` = (x_low, x_high, y_low, y_high): the inner faces of the walls
    around the object (hand-written scene knowledge; None: no walls, DOWN). Yaws from 0 to 90
    degrees in 7.5-degree steps are compared by the hand footprint's smallest clearance; the
    current yaw is kept unless another clears ``band`` metres more, so observation noise
    cannot swing the hand back and forth.
    """
    if walls is None:
        return DOWN
    x_low, x_high, y_low, y_high = walls
    to_x = min(obj[0] - x_low, x_high - obj[0])
    to_y = min(obj[1] - y_low, y_high - obj[1])

    def clearance(yaw):
        along_x, along_y = abs(math.sin(yaw)), abs(math.cos(yaw))
        reach_x = HAND_HALF_LENGTH * along_x + HAND_HALF_WIDTH * along_y
        reach_y = HAND_HALF_LENGTH * along_y + HAND_HALF_WIDTH * along_x
        return min(to_x - reach_x, to_y - reach_y)

    held = yaw_of(current)
    best = max((k * math.pi / 24.0 for k in range(13)), key=clearance)
    if clearance(best) <= clearance(held) + band:
        return down_at(held)
    return down_at(best)
