"""Skills of T3 stack: reach, grasp and lift cube A (from :mod:`.grasping`), then align it over
cube B, lower it on and let go.

Cube A's stacked pose is cube B's origin plus ``stack_dz`` (half sizes 2 cm + 2.5 cm). The
vector from A to B is observed twice with independent noise: directly (``cubeA_to_cubeB``) and
as the difference of the two positions; ``rel_weight`` blends them (2/3 on the direct one
halves the variance; 0 ignores it).

Version 0 is *manual and untuned*: ``align`` and ``lower`` mostly trust the two noisy
positions (``rel_weight`` 0.2), ``align`` carries cube A 10 cm above its stacked height with
a low gain, and ``lower`` aims 1 cm too high (``stack_dz`` 5.5 cm), so cube A may hover just
above B.

Invariants:
1. Every ECM of T3's decomposition gets exactly one skill.
"""

from __future__ import annotations

from collections.abc import Mapping

from capevo.learner.skills._lib import DIG_RANGE, GAIN_RANGE, SkillTemplate
from capevo.learner.skills.grasping import GRASP, LET_GO, LIFT, REACH
from capevo.runtime.tasks.spec import TaskSpec

STACK_DZ_RANGE = (0.02, 0.08)
"""Cube A's origin above cube B's when stacked: somewhere between touching half sizes."""

_TO_STACKED = '''
def to_stacked(obs, params):
    """Vector from cube A's origin to where it rests on cube B (world frame, metres)."""
    a = vec(obs, "cubeA_pos")
    b = vec(obs, "cubeB_pos")
    rel = blend(obs["cubeA_to_cubeB"], b - a, params["rel_weight"])
    return rel + np.array([0.0, 0.0, params["stack_dz"]])
'''

ALIGN = SkillTemplate(
    doc="""Carry cube A until it hangs right above cube B.

Servos cube A towards ``carry_dz`` above its stacked pose; while more than ``climb_margin``
below that height it climbs first. ``done`` when the fingers closed fully (cube A fell).
v0 is untuned (manual): high carry, low gain, direct A-to-B observation mostly ignored.
""",
    params={
        "gain": 3.0,
        "carry_dz": 0.1,
        "climb_margin": 0.02,
        "stack_dz": 0.045,
        "rel_weight": 0.2,
    },
    ranges={
        "gain": GAIN_RANGE,
        "carry_dz": (0.0, 0.2),
        "climb_margin": (0.0, 0.1),
        "stack_dz": STACK_DZ_RANGE,
        "rel_weight": (0.0, 1.0),
    },
    body=_TO_STACKED
    + """

def act(obs, params):
    d = to_stacked(obs, params)
    move = np.array([d[0], d[1], d[2] + params["carry_dz"]])
    if move[2] > params["climb_margin"]:
        move[0] *= 0.1
        move[1] *= 0.1
    return pose_action(move, CLOSE, params["gain"], rot_error(obs["robot0_eef_quat"]))


def done(obs, params):
    return opening(obs) < MISSED_WIDTH
""",
)

LOWER = SkillTemplate(
    doc="""Lower cube A onto cube B until they touch.

Servos cube A horizontally over B and down towards ``dig`` below its stacked pose, gripper
closed. ``done`` when the fingers closed fully (cube A fell).
v0 is untuned (manual): aims 1 cm too high, low gain.
""",
    params={
        "gain": 3.0,
        "stack_dz": 0.055,
        "rel_weight": 0.2,
        "dig": 0.0,
    },
    ranges={"gain": GAIN_RANGE, "stack_dz": STACK_DZ_RANGE, "rel_weight": (0.0, 1.0), "dig": DIG_RANGE},
    body=_TO_STACKED
    + """

def act(obs, params):
    d = to_stacked(obs, params)
    move = np.array([d[0], d[1], d[2] - params["dig"]])
    return pose_action(move, CLOSE, params["gain"], rot_error(obs["robot0_eef_quat"]))


def done(obs, params):
    return opening(obs) < MISSED_WIDTH
""",
)

_BY_STEP: Mapping[str, SkillTemplate] = {
    "reach": REACH,
    "grasp": GRASP,
    "lift": LIFT,
    "align": ALIGN,
    "lower": LOWER,
    "release": LET_GO,
}


def templates(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    """Template and placeholder values for every ECM of T3."""
    keys = {"obj": "cubeA", "what": "cube A", "where": "resting on cube B"}
    return {ecm: (_BY_STEP[ecm.split(".")[-1]], keys) for ecm in spec.ecm_names}
