"""Skills of T6 peg_in_hole: two Pandas (no grippers), the peg on arm 0, the plate on arm 1.

Every step runs the same geometric controller with different gains: it reads the peg's axis
(``peg_quat``), the hole's centre and normal (``hole_pos``, ``hole_quat``; the hole is 0.1 m
along the plate's x axis) and the peg's position (``hole_pos - peg_to_hole``). It picks the
*facing* direction, the hole normal or its opposite: until the peg points within about 45
degrees of the normal (``|cos| > 0.7``), the one from the peg's side of the plate towards it;
after that, whichever sign is nearer the peg's axis (the success check uses ``|cos|``). Then it

* turns the peg's axis towards the facing direction (``peg_rot_gain``) and the facing
  direction towards the peg's axis (``hole_rot_gain``);
* moves the peg (``peg_move_gain``) and the plate (``hole_move_gain``) to put the peg's centre on
  the line through the hole centre along the facing direction;
* moves the peg along the facing direction until the hole centre is ``axial_target`` ahead of the
  peg's centre (``axial_gain``); while it is nearer, sideways motion runs at a tenth of its speed.

Why positions are measured along the facing direction and not the peg's current axis (issue 19's
T6 traces, training seeds 300000-300009): with the axis still turning, "the hole centre on the peg's
axis" lies far off, and the hand climbed to the workspace's top face or its reach limit chasing
it. Why the side rule: at reset the peg hangs 3-4 cm beside the plate's face, and which way it
turned was a coin toss on ``cos`` = 0; turning towards the plate from the far side swept the peg
into it. Measured with the gains of the 2026-12-05 evolved set and ``orient_peg`` backing off
(``axial_gain`` 5, ``axial_target`` 0.2): 9 of those 10 seeds, against 5 of 10 before.

Actions are computed in the world frame and turned into each arm's OSC action frame (robosuite's
"opposed" layout mounts arm 0 at +90 degrees and arm 1 at -90 degrees of yaw).

What is hand-written (fixed; no learner changes it): the eight phases and their order (the task's
decomposition, with its termination thresholds), the controller above (which arm turns and moves
for which error, the facing rule and its 0.7 switch, the tenth-speed sideways motion while the peg
is too near, the hole centre 0.1 m along the plate's x axis as robosuite computes it), the arms'
action-frame yaws, and every ``PARAM_RANGES`` span (physical spans written with the guesses, not tuned). What
is learned: the values of ``PARAMS`` inside those spans. Every step declares all six parameters
with a range that contains 0, so a gain that is 0 in v0 (the arm it drives holds still) is searched
too rather than frozen.

Version 0 is *manual and untuned*: every gain is a guess, low, without running the simulator.
Known weaknesses, which the learners are meant to find:

* the gains are low (0.2-0.3 per radian, 1-2 per metre), so at the task's horizon (300 steps)
  v0 is too slow: it runs out of steps a few to a few tens of steps short (issue 19 measured 0/3
  at 300 and 3/3 at 600 steps);
* ``orient_peg`` turns the peg in place (``axial_gain`` 0): from 3-4 cm beside the plate the turn
  towards it is braked by the envelope's ``contact_approach`` and rarely finishes; backing off
  along the normal while turning (``axial_gain`` > 0, ``axial_target`` 0.1-0.3) is for the learner
  to find;
* ``hold`` has every gain at 0 (both arms just hold still);
* ``insert`` aims ``axial_target`` = 0 (the tip 13 cm through the plate), but robosuite's success,
  which ends the episode, holds from t = 0.14 on, with the tip still 1 cm short of the plate: the
  strict check ``peg_inserted`` (:mod:`capevo.runtime.tasks.peg_in_hole`) reports the difference.

Invariants:
1. Every ECM of T6's decomposition gets exactly one skill; every action has 12 values in [-1, 1].
"""

from __future__ import annotations

from collections.abc import Mapping

from capevo.learner.skills._lib import SkillTemplate
from capevo.runtime.tasks.spec import TaskSpec

ROT_GAIN_RANGE = (0.0, 3.0)
"""Action per radian of misalignment: at 3 a 20-degree error already saturates the arm's rotation
action (1.0); 0 keeps that arm's orientation. Linear, because 0 is a meaningful choice."""
MOVE_GAIN_RANGE = (0.0, 20.0)
"""Action per metre of offset: 20 is full speed 5 cm away (as the single-arm GAIN_RANGE); 0 keeps
that arm in place."""
AXIAL_TARGET_RANGE = (-0.1, 0.35)
"""Where the hole centre should sit ahead of the peg centre along the peg's axis (robosuite's t,
metres). The peg is 0.26 m long, its tip 0.13 m ahead of its centre: 0.35 keeps the tip 22 cm
back from the plate; -0.1 pushes the tip 23 cm through it (the hand is then about 3 cm from the
plate)."""
PEG_RANGES: Mapping[str, tuple[float, float]] = {
    "peg_rot_gain": ROT_GAIN_RANGE,
    "hole_rot_gain": ROT_GAIN_RANGE,
    "peg_move_gain": MOVE_GAIN_RANGE,
    "hole_move_gain": MOVE_GAIN_RANGE,
    "axial_gain": MOVE_GAIN_RANGE,
    "axial_target": AXIAL_TARGET_RANGE,
}
"""The same spans for every step: they all run one controller with different gains."""

PEG_PRELUDE = '''
import math

import numpy as np

ARM_YAW = (0.5 * math.pi, -0.5 * math.pi)
"""Yaw of each arm's OSC action frame in the world frame."""


def vec(obs, key):
    return np.asarray(obs[key], dtype=np.float64)


def quat_matrix(q):
    """Rotation matrix of quaternion ``q`` (x, y, z, w)."""
    x, y, z, w = (float(c) for c in q)
    n = x * x + y * y + z * z + w * w
    s = 2.0 / n if n > 1e-12 else 0.0
    return np.array(
        [
            [1.0 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1.0 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1.0 - s * (x * x + y * y)],
        ]
    )


def rotation_between(a, b):
    """Axis-angle (radians) turning unit vector ``a`` onto ``b``."""
    c = np.cross(a, b)
    s = float(np.linalg.norm(c))
    angle = math.atan2(s, float(np.dot(a, b)))
    if s < 1e-9:
        return np.zeros(3)
    return c / s * angle


def to_arm(world, arm):
    """A world-frame vector in arm ``arm``'s action frame."""
    yaw = ARM_YAW[arm]
    c, s = math.cos(yaw), math.sin(yaw)
    x, y, z = (float(v) for v in world)
    return np.array([c * x + s * y, -s * x + c * y, z])
'''

_BODY = '''
def geometry(obs):
    """Peg centre, peg axis, hole centre and hole normal (world frame)."""
    r_hole = quat_matrix(obs["hole_quat"])
    hole = vec(obs, "hole_pos")
    center = hole + r_hole @ np.array([0.1, 0.0, 0.0])
    normal = r_hole[:, 2]
    peg = hole - vec(obs, "peg_to_hole")
    axis = quat_matrix(obs["peg_quat"])[:, 2]
    return peg, axis, center, normal


def facing_of(peg, axis, center, normal):
    """The hole normal or its opposite: from the peg's side of the plate until the peg points
    within about 45 degrees of it, then the sign nearer the peg's axis."""
    cos = float(np.dot(normal, axis))
    side = cos if abs(cos) > 0.7 else float(np.dot(normal, center - peg))
    return normal if side >= 0.0 else -normal


def act(obs, params):
    peg, axis, center, normal = geometry(obs)
    facing = facing_of(peg, axis, center, normal)
    peg_rot = rotation_between(axis, facing) * params["peg_rot_gain"]
    hole_rot = rotation_between(facing, axis) * params["hole_rot_gain"]
    to_center = center - peg
    along = float(np.dot(to_center, facing))
    perp = to_center - along * facing
    # while the hole is nearer than axial_target, back off first: sideways
    # motion with the peg's tip at the plate would push the peg into the plate
    lateral = 1.0 if params["axial_gain"] <= 0.0 or along >= params["axial_target"] - 0.05 else 0.1
    axial = facing * (along - params["axial_target"]) * params["axial_gain"]
    peg_move = perp * params["peg_move_gain"] * lateral + axial
    hole_move = -perp * params["hole_move_gain"] * lateral
    a = np.concatenate([to_arm(peg_move, 0), to_arm(peg_rot, 0), to_arm(hole_move, 1), to_arm(hole_rot, 1)])
    return np.clip(a, -1.0, 1.0)
'''


def _template(doc: str, **params: float) -> SkillTemplate:
    base = {
        "peg_rot_gain": 0.0,
        "hole_rot_gain": 0.0,
        "peg_move_gain": 0.0,
        "hole_move_gain": 0.0,
        "axial_gain": 0.0,
        "axial_target": 0.1,
    }
    base.update(params)
    doc += "\nv0 is untuned (manual): low guessed gains.\n"
    return SkillTemplate(doc=doc, params=base, body=_BODY, prelude=PEG_PRELUDE, ranges=dict(PEG_RANGES))


_BY_STEP: Mapping[str, SkillTemplate] = {
    "orient_peg": _template("Peg arm turns the peg towards the hole normal.", peg_rot_gain=0.3),
    "orient_hole": _template("Plate arm turns the plate so the hole faces the peg.", hole_rot_gain=0.3),
    # the approach steps also keep the peg back along its axis (axial_target): sideways
    # motion with the peg's tip through the plate's plane would push it into the plate
    "approach_peg": _template(
        "Peg arm moves the peg in front of the hole.",
        peg_rot_gain=0.2,
        hole_rot_gain=0.2,
        peg_move_gain=2.0,
        axial_gain=2.0,
        axial_target=0.25,
    ),
    "approach_hole": _template(
        "Plate arm moves the hole onto the peg's axis.",
        peg_rot_gain=0.2,
        hole_rot_gain=0.2,
        hole_move_gain=2.0,
        axial_gain=1.0,
        axial_target=0.25,
    ),
    "align": _template(
        "Both arms turn so peg and hole are coaxial.",
        peg_rot_gain=0.3,
        hole_rot_gain=0.3,
        peg_move_gain=1.0,
        hole_move_gain=1.0,
        axial_gain=1.0,
        axial_target=0.25,
    ),
    "pre_insert": _template(
        "Bring the peg to the hole entrance along its axis.",
        peg_rot_gain=0.2,
        hole_rot_gain=0.2,
        peg_move_gain=1.0,
        hole_move_gain=1.0,
        axial_gain=1.0,
        axial_target=0.15,
    ),
    "insert": _template(
        "Push the peg through the hole.",
        peg_rot_gain=0.2,
        hole_rot_gain=0.2,
        peg_move_gain=1.0,
        hole_move_gain=1.0,
        axial_gain=1.0,
        axial_target=0.0,
    ),
    "hold": _template("Hold peg and plate still with the peg inside the hole.", axial_target=0.0),
}


def templates(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    """Template and placeholder values for every ECM of T6."""
    return {ecm: (_BY_STEP[ecm.split(".")[-1]], {}) for ecm in spec.ecm_names}
