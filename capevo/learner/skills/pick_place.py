"""Skills of the bins tasks: T1 pick, T2 place and T5 pick_place_multi (robosuite PickPlace).

Reach, grasp and lift come from :mod:`.grasping`; this module adds carrying the object over
its goal quadrant (``move``) and putting it down (``release``). Goals are read from the exact
``<Object>_target_pos`` observation.

Version 0 is *manual and untuned*: ``move`` carries the object only ``carry_dz`` = 5 cm above
its goal height (the bin rims are higher: the can hits the wall), and ``release`` lets go
10 cm above the goal, so the can may bounce or tip out.

Invariants:
1. Every ECM of T1, T2 and T5's decompositions gets exactly one skill.
"""

from __future__ import annotations

from collections.abc import Mapping

from capevo.learner.skills._lib import GAIN_RANGE, SPEED_RANGE, SkillTemplate
from capevo.learner.skills.grasping import GRASP, LIFT, REACH
from capevo.runtime.tasks.pick_place import GRASP_HEIGHT, RIDGED
from capevo.runtime.tasks.spec import TaskSpec

MOVE = SkillTemplate(
    doc="""Carry ${what} over its goal quadrant, keeping it above the bin rims.

Servos the object (not the hand) towards ``carry_dz`` above its goal; while the object is more
than ``climb_margin`` below that height it climbs first, moving sideways at a tenth of the
speed. ``done`` when the fingers closed fully (the object fell out).
v0 is untuned (manual): carries too low for the rims, low gain.
""",
    params={
        "gain": 3.0,
        "carry_dz": 0.05,
        "climb_margin": 0.05,
    },
    ranges={"gain": GAIN_RANGE, "carry_dz": (0.0, 0.3), "climb_margin": (0.0, 0.15)},
    body="""
def act(obs, params):
    obj = vec(obs, "${obj}_pos")
    goal = vec(obs, "${obj}_target_pos")
    carry = goal[2] + params["carry_dz"]
    move = np.array([goal[0] - obj[0], goal[1] - obj[1], carry - obj[2]])
    if obj[2] < carry - params["climb_margin"]:
        move[0] *= 0.1
        move[1] *= 0.1
    quat = obs["robot0_eef_quat"]
    return pose_action(move, CLOSE, params["gain"], rot_error(quat, held_down(quat)))


def done(obs, params):
    return opening(obs) < MISSED_WIDTH
""",
)

RELEASE = SkillTemplate(
    doc="""Lower ${what} into its goal quadrant, open the gripper and move the hand away.

While closed and the object is more than ``release_dz`` above its goal height, lowers it
(towards half that height) over the goal; then opens the gripper without moving; once the
finger gap exceeds RELEASED_WIDTH the hand rises at ``retreat_speed``.
v0 is untuned (manual): lets go from 10 cm, low gain.
""",
    params={
        "gain": 3.0,
        "release_dz": 0.1,
        "retreat_speed": 0.3,
    },
    ranges={"gain": GAIN_RANGE, "release_dz": (0.0, 0.2), "retreat_speed": SPEED_RANGE},
    body="""
def act(obs, params):
    obj = vec(obs, "${obj}_pos")
    goal = vec(obs, "${obj}_target_pos")
    rot = rot_error(obs["robot0_eef_quat"], held_down(obs["robot0_eef_quat"]))
    if opening(obs) > RELEASED_WIDTH:
        a = pose_action(np.zeros(3), OPEN, 0.0, rot)
        a[2] = min(max(params["retreat_speed"], -1.0), 1.0)
        return a
    if obj[2] > goal[2] + params["release_dz"]:
        move = np.array([goal[0] - obj[0], goal[1] - obj[1], goal[2] + 0.5 * params["release_dz"] - obj[2]])
        return pose_action(move, CLOSE, params["gain"], rot)
    return pose_action(np.zeros(3), OPEN, params["gain"], rot)
""",
)

SOURCE_BIN_WALLS = "(-0.09, 0.29, -0.49, -0.01)"
"""Inner faces of the source bin's walls, world frame (robosuite PickPlace's bin1 at (0.1, -0.25),
0.4 x 0.5 m inside; hand-written from the scene, as ``capevo.runtime.governance.task_phi`` has it)."""

_BY_STEP: Mapping[str, SkillTemplate] = {
    "reach": REACH,
    "grasp": GRASP,
    "lift": LIFT,
    "move": MOVE,
    "release": RELEASE,
}


def templates(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    """Template and placeholder values for every ECM of a bins task.

    ECM names are ``<task>.<step>`` (one object: the can) or ``<task>.<object>.<step>`` (T5).
    """
    out: dict[str, tuple[SkillTemplate, dict[str, str]]] = {}
    for ecm in spec.ecm_names:
        parts = ecm.split(".")
        obj = parts[1].capitalize() if len(parts) == 3 else "Can"
        keys = {
            "obj": obj,
            "what": f"the {obj.lower()}",
            "walls": SOURCE_BIN_WALLS,
            "grasp_height": repr(GRASP_HEIGHT[obj]),
            "ridge": repr(obj in RIDGED),
        }
        out[ecm] = (_BY_STEP[parts[-1]], keys)
    return out
