"""Hand-written reference controllers: pure functions of a task's raw observation dict.

Each reference reads ``TaskEnv.obs_dict`` (noisy when observation noise is on) and returns one
action; it keeps no memory, so its phase (approach, descend, close, lift, carry, release) is
read off the observation every step. There are references for T1 pick, T2 place and T3
stack (:data:`REFERENCES`); they show those success criteria are reachable and serve as
baselines and code-ECM seeds.

They are written to hold up under the per-task Φ too (``Phi.for_task``, which brakes motion near
contacts and at the arm's reach), where motions are slower: a slowed motion leaves a noisy
position reading near a threshold for many steps, so the phase decisions lean on what is observed
without noise where they can (the finger gap as the grasp's memory, joint speeds for a blocked
lowering), and the grasp is made at grasp height, in place and without pushing down hard.

Invariants:
1. A reference returns a float32 action of the task's action dimension with values in [-1, 1].
2. A reference is a pure function: equal observation dicts give equal actions.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from capevo.runtime.tasks.hand_pose import DOWN, clear_of_walls, held_down, rot_error

Obs = Mapping[str, np.ndarray]
Policy = Callable[[Obs], np.ndarray]

POS_GAIN = 10.0
"""Action per metre of position error (1.0 saturates at 10 cm; one full step moves ~1 cm)."""
ROT_GAIN = 2.0
"""Action per radian of orientation error."""
TRAVEL_XY = 0.04
"""Horizontal distance above which the gripper travels at hover height."""
DESCEND_XY = 0.03
"""Horizontal distance below which the open gripper descends onto the object."""
CLOSE_AT = 0.005
"""Height above the grasp point below which an open gripper starts to close: at grasp height, not
on the way down. A slowed final descent (a per-task Φ brakes it near the object) would otherwise
close the fingers on the object's top edge."""
CLOSE_ABOVE = 0.035
"""Height above the grasp point below which a gripper that is already closing keeps closing (still
descending): the wider band keeps 1 cm observation noise from re-opening it."""
CLOSE_DESCENT = 0.1
"""Largest downward action while the fingers close (about 1 mm per step)."""
GRIPPER_READY = 0.065
"""Finger gap above which the gripper is open enough to descend over an object."""
GRIPPER_OPEN = 0.075
"""Finger gap above which the gripper is fully open (its full gap is about 0.08): below it, it has
started to close."""
MISSED = 0.03
"""Finger gap below which a closing gripper that is not holding anything missed the object."""
DIG = 0.01
"""The descent aims this far below the grasp point, so the hand settles on it despite noise."""
NEAR_XY, NEAR_Z = 0.045, 0.045
"""Gripper-to-grasp-point offsets within which a closed gripper counts as holding: about 3 sigma
of the observed offset (1 cm noise on each position), so a gripper settled on the object is not
taken for empty (and opened) on a noisy step while it carries or lowers it slowly."""
FINGER_CLOSED = 0.005
"""Finger gap below which the gripper is fully closed (on nothing)."""
FINGER_SETTLED = 0.02
"""Finger speed (m/s) below which a closing gripper counts as settled on the object."""
PLACE_XY = 0.08
"""Horizontal object-to-goal offset below which a carried object is lowered into its bin
(the goal quadrants are about 0.2 x 0.24 m; the far one is at the edge of the Panda's reach)."""
DROP_DZ = 0.07
"""A carried object whose lowering is blocked is released from at most this far above its target."""
STALLED = 0.1
"""Joint speed (rad/s) below which every joint counts as nearly still: a lowering blocked, or
braked to a crawl (about 2 mm per step and less), rather than one under way."""
STACK_XY, STACK_XY_LOW = 0.02, 0.035
"""Horizontal cube A to cube B offset below which cube A is lowered (from carry height, once low)."""
STACK_RELEASE_DZ = 0.015
"""Cube A this close above its stacked height: open the gripper."""
STACKED_DZ = 0.045
"""Cube A's origin above cube B's when stacked (half sizes 0.02 + 0.025)."""
GRIP_OPEN, GRIP_CLOSE = -1.0, 1.0
CAN_GRASP_DZ = 0.015
"""Grasp height above the can's origin for the pick and place references. The Panda's palm starts
2.6 cm above the grip site and spans 21 cm along the fingers' travel, so for a can standing near a
bin wall it reaches over the rim: the can's origin is 4 cm above the bin floor and the rim 8 cm, so
grasping at the origin would press the palm onto the rim, while 1.5 cm higher it passes just
above it (the fingers still hold the can's upper half; higher still, a fast carry lets it slip)."""

SOURCE_BIN_WALLS = (-0.09, 0.29, -0.49, -0.01)
"""Inner faces (x_low, x_high, y_low, y_high) of the walls of PickPlace's source bin (bin1 at
(0.1, -0.25), 0.4 x 0.5 m inside), world frame: the pick and place references turn the hand
parallel to the nearest of them (:func:`~capevo.runtime.tasks.hand_pose.clear_of_walls`)."""


def _action(move: np.ndarray, rot: np.ndarray, grip: float) -> np.ndarray:
    a = np.empty(7, dtype=np.float32)
    a[:3] = np.clip(move * POS_GAIN, -1.0, 1.0)
    a[3:6] = np.clip(rot * ROT_GAIN, -1.0, 1.0)
    a[6] = grip
    return a


def _opening(obs: Obs) -> tuple[float, float]:
    q = obs["robot0_gripper_qpos"]
    v = obs["robot0_gripper_qvel"]
    return float(q[0] - q[1]), float(abs(v[0]) + abs(v[1]))


def _stalled(obs: Obs) -> bool:
    """The arm is (nearly) not moving; joint speeds are observed without noise."""
    return bool(np.max(np.abs(obs["robot0_joint_vel"])) < STALLED)


def _holding(eef: np.ndarray, obj: np.ndarray, obs: Obs, grasp_dz: float) -> bool:
    """Closed, settled fingers around the object: read from geometry alone."""
    opening, finger_speed = _opening(obs)
    near = np.linalg.norm(eef[:2] - obj[:2]) < NEAR_XY and abs(eef[2] - obj[2] - grasp_dz) < NEAR_Z
    closing_done = FINGER_CLOSED < opening < 0.07 and finger_speed < FINGER_SETTLED
    return bool(near and closing_done)


def _approach(
    eef: np.ndarray, obj: np.ndarray, obs: Obs, *, hover: float, grasp_dz: float, rot: np.ndarray
) -> np.ndarray:
    """Hover over the object, descend with the gripper open, close around the grasp point.

    Memoryless and tolerant of 1 cm observation noise: it descends only with an open gripper
    and re-opens (rising) when the fingers closed on nothing, so a wrong branch for one step
    only pauses the motion.
    """
    opening, _ = _opening(obs)
    xy_err = obj[:2] - eef[:2]
    xy = float(np.linalg.norm(xy_err))
    grasp_z = obj[2] + grasp_dz
    above = eef[2] - grasp_z
    if xy > TRAVEL_XY:
        # travel at hover height; climb first when low so the fingers don't sweep the object
        move = np.array([xy_err[0], xy_err[1], grasp_z + hover - eef[2]])
        if above < hover - 0.02:
            move[:2] *= 0.2
        return _action(move, rot, GRIP_OPEN)
    # The finger gap is the phase's memory: a fully open gripper starts closing only at grasp
    # height; once it is closing, the looser band keeps it closing.
    if above > (CLOSE_AT if opening > GRIPPER_OPEN else CLOSE_ABOVE):
        descend = xy < DESCEND_XY and opening > GRIPPER_READY
        return _action(np.array([xy_err[0], xy_err[1], grasp_z - DIG - eef[2] if descend else 0.0]), rot, GRIP_OPEN)
    if opening < MISSED:
        # the fingers closed on nothing: rise while opening, then come down again
        return _action(np.array([xy_err[0], xy_err[1], 0.3]), rot, GRIP_OPEN)
    # Close in place: the closing fingers centre the object themselves, while chasing the noisy
    # offset would drag it, clamped and resting on its support, sideways; and settle only slowly,
    # since the hand still moving down when the fingers clamp pushes the object into its support.
    settle = max(grasp_z - DIG - eef[2], -CLOSE_DESCENT / POS_GAIN)
    return _action(np.array([0.0, 0.0, settle]), rot, GRIP_CLOSE)


def _down_rot(obs: Obs, obj: np.ndarray | None = None) -> np.ndarray:
    """Orientation error to pointing down: clear of the source bin's walls around ``obj`` while
    approaching it, at the hand's current yaw otherwise (``obj`` None)."""
    quat = obs["robot0_eef_quat"]
    target = held_down(quat) if obj is None else clear_of_walls(obj, quat, SOURCE_BIN_WALLS)
    return rot_error(quat, target)


def pick(obs: Obs, *, object_key: str = "Can", lift_speed: float = 0.15, grasp_dz: float = CAN_GRASP_DZ) -> np.ndarray:
    """T1 reference: hover over the object, descend, close, then lift while holding.

    Args:
        obs: ``TaskEnv.obs_dict`` of a single-Panda task.
        object_key: Prefix of the object's ``<key>_pos`` observation.
        lift_speed: Upward command while holding, in metres of error (0.1 and above saturate).
        grasp_dz: Grasp height above the object origin.

    Returns:
        A 7-vector action.
    """
    eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
    obj = np.asarray(obs[f"{object_key}_pos"], dtype=np.float64)
    if _holding(eef, obj, obs, grasp_dz):
        return _action(np.array([0.0, 0.0, lift_speed]), _down_rot(obs), GRIP_CLOSE)
    rot = _down_rot(obs, obj)
    return _approach(eef, obj, obs, hover=0.08, grasp_dz=grasp_dz, rot=rot)


def place(
    obs: Obs,
    *,
    object_key: str = "Can",
    target: np.ndarray | None = None,
    carry_z: float = 1.0,
    release_dz: float = 0.03,
    grasp_dz: float = CAN_GRASP_DZ,
) -> np.ndarray:
    """T2 reference: pick the object, carry it at ``carry_z`` over its target, lower, release, retreat.

    Args:
        obs: ``TaskEnv.obs_dict``.
        object_key: Object prefix; its goal is ``<key>_target_pos`` unless ``target`` is given.
        target: Where the object's origin should end up (world frame).
        carry_z: Height of the object origin while carrying (clears the bin rims).
        release_dz: Open the gripper once the object is this close above its target height.
        grasp_dz: Grasp height above the object origin.

    Returns:
        A 7-vector action.
    """
    eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
    obj = np.asarray(obs[f"{object_key}_pos"], dtype=np.float64)
    goal = np.asarray(obs[f"{object_key}_target_pos"] if target is None else target, dtype=np.float64)
    rot = _down_rot(obs)
    to_goal = goal[:2] - obj[:2]
    placed = np.linalg.norm(to_goal) < PLACE_XY + 0.02 and obj[2] < goal[2] + release_dz + 0.02
    if _holding(eef, obj, obs, grasp_dz):
        if np.linalg.norm(to_goal) > PLACE_XY:
            if obj[2] < carry_z - 0.05:
                # climb before travelling sideways so the object clears the rims
                return _action(np.array([0.1 * to_goal[0], 0.1 * to_goal[1], carry_z - obj[2]]), rot, GRIP_CLOSE)
            return _action(np.array([to_goal[0], to_goal[1], carry_z - obj[2]]), rot, GRIP_CLOSE)
        # Release once low over the target, or, if the lowering is blocked or crawls (the arm at
        # full stretch, a divider under the object's edge), from a little higher: it drops in.
        blocked = obj[2] < goal[2] + DROP_DZ and _stalled(obs)
        if obj[2] > goal[2] + release_dz and not blocked:
            return _action(np.array([to_goal[0], to_goal[1], goal[2] + release_dz * 0.5 - obj[2]]), rot, GRIP_CLOSE)
        return _action(np.zeros(3), rot, GRIP_OPEN)
    if placed:
        # released: open fully and back off upward
        return _action(np.array([0.0, 0.0, 0.1]), rot, GRIP_OPEN)
    return _approach(eef, obj, obs, hover=0.08, grasp_dz=grasp_dz, rot=_down_rot(obs, obj))


def stack(obs: Obs) -> np.ndarray:
    """T3 reference: pick cube A and place it on cube B, then let go and back off.

    Returns:
        A 7-vector action.
    """
    b = np.asarray(obs["cubeB_pos"], dtype=np.float64)
    goal = b + np.array([0.0, 0.0, STACKED_DZ])
    eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
    a = np.asarray(obs["cubeA_pos"], dtype=np.float64)
    rot = rot_error(obs["robot0_eef_quat"], DOWN)  # on a table: no walls, square to the world
    to_goal = goal[:2] - a[:2]
    off = float(np.linalg.norm(to_goal))
    low = a[2] < goal[2] + 0.03
    if _holding(eef, a, obs, 0.0):
        # once low over cube B, tolerate more (noisy) offset before climbing back
        if off > (STACK_XY_LOW if low else STACK_XY):
            carry = goal[2] + 0.04
            if a[2] < carry - 0.02:
                return _action(np.array([0.1 * to_goal[0], 0.1 * to_goal[1], carry - a[2]]), rot, GRIP_CLOSE)
            return _action(np.array([to_goal[0], to_goal[1], carry - a[2]]), rot, GRIP_CLOSE)
        if a[2] > goal[2] + STACK_RELEASE_DZ:
            return _action(np.array([to_goal[0], to_goal[1], goal[2] - DIG - a[2]]), rot, GRIP_CLOSE)
        return _action(np.zeros(3), rot, GRIP_OPEN)
    if off < STACK_XY_LOW + 0.005 and a[2] < goal[2] + 0.03:
        # released on cube B: open fully and back off upward
        return _action(np.array([0.0, 0.0, 0.1]), rot, GRIP_OPEN)
    return _approach(eef, a, obs, hover=0.06, grasp_dz=0.0, rot=rot)


REFERENCES: Mapping[str, Policy] = {"pick": pick, "place": place, "stack": stack}
"""Scripted reference policy by task name."""
