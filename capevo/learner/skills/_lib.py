"""Building blocks of the built-in code skills: the shared prelude, rendering and publish specs.

Every built-in skill is one self-contained module (the code ECM contract allows no imports
but ``math`` and ``numpy``), so the helpers all single-arm skills share are pasted into each
source as :data:`PRELUDE`. A skill is a :class:`SkillTemplate`: a docstring, ``PARAMS`` (the
v0 values) and a body whose ``${name}`` placeholders (observation key prefixes) are filled
in per task by :func:`render`.

Invariants:
1. :func:`render` output passes the sandbox validator and its ``PARAMS`` literal equals the
   template's ``params`` (same keys, same order, values as floats); its ``PARAM_RANGES``
   literal (when the template has ranges) equals ``ranges`` and brackets every v0 value.
2. :func:`publish_spec` declares exactly the step's observation keys as inputs (shapes from
   :data:`OBS_SHAPES`), one ``action`` output of the task's action dimension bounded to
   [-1, 1], and the step's descriptor (description, applicability, termination) unchanged.
"""

from __future__ import annotations

import inspect
import string
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass, field

from capevo.errors import Invalid
from capevo.records import Interface, IOSpec, Kind, Origin, Provenance, PublishSpec
from capevo.runtime.tasks import hand_pose
from capevo.runtime.tasks.spec import EcmStep, TaskSpec

HAND_POSE = inspect.getsource(hand_pose).split("import numpy as np\n", 1)[1]
""":mod:`capevo.runtime.tasks.hand_pose` below its imports: pasted into every skill's prelude."""

PRELUDE = (
    """
import math

import numpy as np
"""
    + HAND_POSE
    + '''

def vec(obs, key):
    return np.asarray(obs[key], dtype=np.float64)


OPEN, CLOSE = -1.0, 1.0
"""Gripper commands; robosuite's gripper holds the last command's target."""
ROT_GAIN = 2.0
"""Action per radian of orientation error (keeping the hand pointing down)."""
OPEN_WIDTH = 0.065
"""Finger gap (metres) above which the gripper is open enough to go down around an object."""
MISSED_WIDTH = 0.01
"""Finger gap below which a closed gripper holds nothing."""
RELEASED_WIDTH = 0.07
"""Finger gap above which a held object has been let go."""
DONE_TOL = 0.008
"""Per-axis distance (metres, as observed) within which a positioning skill calls itself done."""


def pose_action(move, grip, gain, rot):
    """One 7-D OSC_POSE action: position error times ``gain``, orientation error times ROT_GAIN."""
    a = np.zeros(7)
    a[:3] = np.clip(np.asarray(move, dtype=np.float64) * gain, -1.0, 1.0)
    a[3:6] = np.clip(np.asarray(rot, dtype=np.float64) * ROT_GAIN, -1.0, 1.0)
    a[6] = grip
    return a


def opening(obs):
    """Finger gap in metres (about 0 closed, 0.08 fully open); not affected by position noise."""
    q = obs["robot0_gripper_qpos"]
    return float(q[0] - q[1])


def blend(direct, difference, weight):
    """Mix two noisy estimates of one vector: ``weight`` on the directly observed one."""
    return weight * np.asarray(direct, dtype=np.float64) + (1.0 - weight) * np.asarray(difference, dtype=np.float64)
'''
)
"""Helpers pasted into every single-arm skill (the contract forbids importing shared code)."""

GAIN_RANGE = (1.0, 20.0, "log")
"""Plausible position gains (action per metre of error): 1 crawls, 20 is full speed 5 cm away."""
GRASP_DZ_RANGE = (-0.04, 0.06)
"""Grasp point above an object origin: within a few centimetres of it."""
DIG_RANGE = (-0.02, 0.04)
"""How far below a target a servo may aim (negative: above) to settle on it despite noise."""
SPEED_RANGE = (0.05, 1.0)
"""Fractions of full speed."""

OBS_SHAPES: Mapping[str, tuple[int, ...]] = {
    **{f"robot{i}_{k}": (7,) for i in (0, 1) for k in ("joint_pos_cos", "joint_pos_sin", "joint_vel")},
    **{f"robot{i}_eef_pos": (3,) for i in (0, 1)},
    **{f"robot{i}_eef_quat": (4,) for i in (0, 1)},
    "robot0_gripper_qpos": (2,),
    "robot0_gripper_qvel": (2,),
    **{
        f"{o}_{k}": (4,) if k.endswith("quat") else (3,)
        for o in ("Can", "Milk", "Bread", "SquareNut")
        for k in ("pos", "quat", "to_robot0_eef_pos", "to_robot0_eef_quat", "target_pos")
    },
    **{f"cube{c}_{k}": (4,) if k == "quat" else (3,) for c in "AB" for k in ("pos", "quat")},
    "cubeA_to_cubeB": (3,),
    "gripper_to_cubeA": (3,),
    "gripper_to_cubeB": (3,),
    "hole_pos": (3,),
    "hole_quat": (4,),
    "peg_to_hole": (3,),
    "peg_quat": (4,),
    "angle": (),
    "t": (),
    "d": (),
}
"""Shape of every observation key a built-in task exposes (checked against real envs in tests)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class SkillTemplate:
    """One skill before its task fills in observation key prefixes.

    Args:
        doc: The module docstring (first line: what the skill does; then what v0 is).
        params: ``PARAMS`` of version 0, in the order they appear in the source.
        body: The functions (``act``, optional ``done`` and helpers); ``${name}`` placeholders
            are substituted by :func:`render`.
        prelude: Shared helpers placed before ``PARAMS``.
    """

    doc: str
    params: Mapping[str, float]
    body: str
    prelude: str = PRELUDE
    keys: Mapping[str, str] = field(default_factory=dict)
    """Default placeholder values."""
    ranges: Mapping[str, tuple[float, float] | tuple[float, float, str]] = field(default_factory=dict)
    """``PARAM_RANGES``: for some parameters, the span a person writing the skill considers
    physically plausible (written down with the guesses, not tuned); learners search there."""


def format_params(params: Mapping[str, float]) -> str:
    """The ``PARAMS = {...}`` block, one key per line."""
    lines = "".join(f"    {k!r}: {float(v)!r},\n" for k, v in params.items())
    return "PARAMS = {\n" + lines + "}\n"


def format_ranges(ranges: Mapping[str, tuple[float, float] | tuple[float, float, str]]) -> str:
    """The ``PARAM_RANGES = {...}`` block (empty text when there are none)."""
    if not ranges:
        return ""
    lines = "".join(
        f"    {k!r}: ({float(r[0])!r}, {float(r[1])!r}{''.join(f', {x!r}' for x in r[2:])}),\n"
        for k, r in ranges.items()
    )
    return "PARAM_RANGES = {\n" + lines + "}\n"


def provenance_note(template: SkillTemplate) -> str:
    """The paragraph every rendered skill's docstring ends with: what is learned, what is hand-written.

    Issue 19 asks each skill to say so; written here once so no skill can leave it out.
    """
    searched = ", ".join(template.params)
    return textwrap.fill(
        f"Learned: the values of PARAMS ({searched}), searched within PARAM_RANGES. "
        "Hand-written: everything else here (the phases and branches of act and done, the prelude's "
        "tolerances, the PARAM_RANGES spans) and the v0 values, which are untuned guesses.",
        width=100,
        break_on_hyphens=False,
    )


def render(template: SkillTemplate, **keys: str) -> str:
    """The skill's full source with placeholders filled in.

    Args:
        template: The skill.
        **keys: Placeholder values (e.g. ``obj="Can"``), over the template's defaults.

    Returns:
        Python source text following the code ECM contract.

    Raises:
        Invalid: a placeholder has no value.
    """
    values = {**template.keys, **keys}
    try:
        body = string.Template(template.body).substitute(values)
        doc = string.Template(template.doc).substitute(values)
    except KeyError as exc:
        raise Invalid(f"skill template needs a value for placeholder {exc.args[0]!r}") from None
    head = f'"""{doc.strip()}\n\n{provenance_note(template)}\n"""\n'
    params = format_params(template.params) + format_ranges(template.ranges)
    return head + template.prelude + "\n\n" + params + "\n" + body.strip() + "\n"


def interface_for(step: EcmStep, spec: TaskSpec) -> Interface:
    """Inputs: the step's observation keys with their shapes; output: one bounded action.

    Raises:
        Invalid: an observation key whose shape is not in :data:`OBS_SHAPES`.
    """
    inputs = []
    for key in step.observation_keys:
        try:
            shape = OBS_SHAPES[key]
        except KeyError:
            raise Invalid(f"{step.ecm}: no known shape for observation key {key!r}") from None
        units = "m" if key.endswith("_pos") or key in ("cubeA_to_cubeB", "peg_to_hole") or "to_cube" in key else None
        inputs.append(IOSpec(name=key, shape=shape, dtype="float32", units=units))
    action = IOSpec(name="action", shape=(spec.action_layout.dim,), dtype="float32", low=-1.0, high=1.0)
    return Interface(inputs=tuple(inputs), outputs=(action,))


def publish_spec(
    step: EcmStep,
    spec: TaskSpec,
    *,
    origin: Origin = Origin.MANUAL,
    parent: int | None = None,
    provenance: Provenance | None = None,
) -> PublishSpec:
    """The :class:`PublishSpec` of a built-in skill for ``step`` of task ``spec``."""
    return PublishSpec(
        kind=Kind.CODE,
        descriptor=step.descriptor(),
        interface=interface_for(step, spec),
        origin=origin,
        parent=parent,
        provenance=provenance or Provenance(learner_id="capevo.builtin-skills"),
    )
