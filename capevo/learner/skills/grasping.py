"""Reach, grasp and lift: the first three steps of every single-arm task, as code skill templates.

The skills aim at the object's origin (``${obj}_pos``) raised by the task's grasp height
(``grasp_height``, hand-written per object: 0 except T5's milk carton, see
``capevo.runtime.tasks.pick_place.GRASP_HEIGHT``) plus the learned ``grasp_dz``; reach turns the
hand clear of the bin's walls or, for a carton with a ridge (T5's milk, ``RIDGED`` there, added
2026-12-05), along the ridge. Both are hand-written scene knowledge, not learned. The skills are
memoryless: each step's phase is read off the (noisy) observation, and every branch that a
noisy reading can pick wrongly for one step only pauses the motion for that step.

Version 0 is *manual and untuned*: plausible values a person writes before running anything.
Known weaknesses, which the learners are meant to find:

* reach aims ``grasp_dz`` = 3 cm above the object origin (near the top rather than the
  middle), so the step's termination (within 2 cm in height) is rarely reached; its gain is low;
* grasp closes the gripper only when within ``close_above`` = 1 cm of that too-high point
  (on a 4 cm cube the fingers close above it);
* lift rises slowly (0.2 of full speed).

Invariants:
1. Every template renders to source that passes the sandbox validator.
2. Every action has 7 values in [-1, 1]; the gripper command is -1 (open) or +1 (close).
"""

from __future__ import annotations

from capevo.learner.skills._lib import DIG_RANGE, GAIN_RANGE, GRASP_DZ_RANGE, SPEED_RANGE, SkillTemplate

REACH = SkillTemplate(
    doc="""Bring the open gripper around ${what}, fingers straddling its grasp point.

Travels at ``hover`` above the grasp point (``grasp_dz`` above the object origin) until within
``descend_xy`` horizontally, turning the hand's long side parallel to the nearest wall around the
object (hand-written: the walls' inner faces WALLS; the turn keeps the 0.2 m hand off a rim the
envelope would stop it at), or, for a carton with a RIDGE (the milk), turned so the fingers close
along the ridge, waits for the fingers to open, then descends to ``dig`` below the
grasp point. ``done`` when the noisy observation puts the grasp point within DONE_TOL on every
axis with the gripper open (the step's termination predicate usually ends it first).
v0 is untuned (manual): ``grasp_dz`` aims 3 cm above the origin and the gain is low.
""",
    params={
        "gain": 3.0,
        "hover": 0.1,
        "grasp_dz": 0.03,
        "descend_xy": 0.02,
        "dig": 0.0,
    },
    keys={"walls": "None", "grasp_height": "0.0", "ridge": "False"},
    ranges={
        "gain": GAIN_RANGE,
        "hover": (0.03, 0.2),
        "grasp_dz": GRASP_DZ_RANGE,
        "descend_xy": (0.005, 0.05),
        "dig": DIG_RANGE,
    },
    body='''
GRASP_HEIGHT = ${grasp_height}
"""The object's grasp point above its origin, metres (hand-written by the task)."""


def grasp_error(obs, params):
    """Aim point (grasp point raised by grasp_dz) minus end effector (world frame, metres)."""
    goal = vec(obs, "${obj}_pos") + np.array([0.0, 0.0, GRASP_HEIGHT + params["grasp_dz"]])
    return goal - vec(obs, "robot0_eef_pos")


WALLS = ${walls}
"""Inner faces (x_low, x_high, y_low, y_high) of the walls around the object; None: none."""
RIDGE = ${ridge}
"""True for a carton whose top is a ridge along its own y axis (the milk; hand-written from its
collision mesh): above its 5 cm body only its two ends stay vertical, so the fingers close along
the ridge, onto the ends. Closing across the ridge, they met its sloping roof below the finger
pads, and the grasp never held. Its grasp point is above the rim, clear of the walls."""


def grip_orientation(obs, quat):
    """The hand's target orientation: along the ridge (RIDGE) or clear of the walls."""
    if RIDGE:
        return down_at(folded(heading(obs["${obj}_quat"])))
    return clear_of_walls(vec(obs, "${obj}_pos"), quat, WALLS)


def act(obs, params):
    err = grasp_error(obs, params)
    quat = obs["robot0_eef_quat"]
    rot = rot_error(quat, grip_orientation(obs, quat))
    xy = math.hypot(err[0], err[1])
    above = -err[2]
    low = above < 0.5 * params["hover"]
    if xy > params["descend_xy"] and not (low and xy < 2.0 * params["descend_xy"]):
        # travel at hover height; climb first when low so the fingers don't sweep the object
        move = np.array([err[0], err[1], err[2] + params["hover"]])
        if above < params["hover"] - 0.02:
            move[0] *= 0.2
            move[1] *= 0.2
        return pose_action(move, OPEN, params["gain"], rot)
    if opening(obs) < OPEN_WIDTH:
        # let the fingers open before going down around the object
        return pose_action(np.array([err[0], err[1], 0.0]), OPEN, params["gain"], rot)
    return pose_action(np.array([err[0], err[1], err[2] - params["dig"]]), OPEN, params["gain"], rot)


def done(obs, params):
    err = grasp_error(obs, params)
    return bool(np.all(np.abs(err) < DONE_TOL)) and opening(obs) > OPEN_WIDTH
''',
)

GRASP = SkillTemplate(
    doc="""Close the gripper on ${what} without moving it.

Holds the hand at ``dig`` below the grasp point (tracking the object) and closes once within
``close_above`` of it in height. ``done`` when the fingers closed on nothing (gap below
MISSED_WIDTH): the plan then goes back to reach, which re-opens the gripper.
v0 is untuned (manual): same too-high ``grasp_dz`` as reach, low gain, closes late.
""",
    params={
        "gain": 3.0,
        "grasp_dz": 0.03,
        "dig": 0.0,
        "close_above": 0.01,
    },
    keys={"grasp_height": "0.0"},
    ranges={"gain": GAIN_RANGE, "grasp_dz": GRASP_DZ_RANGE, "dig": DIG_RANGE, "close_above": (0.0, 0.08)},
    body="""
GRASP_HEIGHT = ${grasp_height}
\"\"\"The object's grasp point above its origin, metres (hand-written by the task).\"\"\"


def act(obs, params):
    goal = vec(obs, "${obj}_pos") + np.array([0.0, 0.0, GRASP_HEIGHT + params["grasp_dz"]])
    err = goal - vec(obs, "robot0_eef_pos")
    grip = CLOSE if -err[2] < params["close_above"] else OPEN
    move = np.array([err[0], err[1], err[2] - params["dig"]])
    return pose_action(move, grip, params["gain"], rot_error(obs["robot0_eef_quat"], held_down(obs["robot0_eef_quat"])))


def done(obs, params):
    return opening(obs) < MISSED_WIDTH
""",
)

LIFT = SkillTemplate(
    doc="""Lift ${what} straight up, keeping the gripper closed.

Rises at ``lift_speed`` (fraction of full speed) with the hand pointing down; the step's
termination predicate (height above start) ends it. ``done`` when the fingers closed fully
(gap below MISSED_WIDTH): the object slipped out.
v0 is untuned (manual): slow.
""",
    params={
        "lift_speed": 0.2,
    },
    ranges={"lift_speed": SPEED_RANGE},
    body="""
def act(obs, params):
    a = pose_action(np.zeros(3), CLOSE, 0.0, rot_error(obs["robot0_eef_quat"], held_down(obs["robot0_eef_quat"])))
    a[2] = min(max(params["lift_speed"], -1.0), 1.0)
    return a


def done(obs, params):
    return opening(obs) < MISSED_WIDTH
""",
)


LET_GO = SkillTemplate(
    doc="""Open the gripper and leave ${what} ${where}.

Opens without moving; once the finger gap exceeds RELEASED_WIDTH the hand rises at
``retreat_speed``.
""",
    params={
        "retreat_speed": 0.3,
    },
    ranges={"retreat_speed": SPEED_RANGE},
    body="""
def act(obs, params):
    a = pose_action(np.zeros(3), OPEN, 0.0, rot_error(obs["robot0_eef_quat"], held_down(obs["robot0_eef_quat"])))
    if opening(obs) > RELEASED_WIDTH:
        a[2] = min(max(params["retreat_speed"], -1.0), 1.0)
    return a
""",
)
"""The last step of stacking-like tasks: let go where the object is, then back off upward
(placeholder ``where``: how the object is left)."""
