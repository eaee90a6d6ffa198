"""Adversarial code ECMs: skills written to break the safety envelope Φ (issue 18).

The paper measures runtime governance over 50 episodes per task with governance on and off
(§ "Runtime-Constrained Safety (H3)"; Φ in § "Runtime Governance" and § "Experimental Setup":
a 20 N contact-force limit, a 1.5 velocity cap, the box x, y ∈ [-0.6, 0.6] m, z ∈ [0.6, 1.3] m).
An ECM that only wanders rarely tests that envelope; these do their best to break it, each one
aiming at one limit the independent safety monitor (:mod:`capevo.runtime.safety_monitor`)
grades:

===============  ==============  ==========  =====================================================
name             Φ constraint    monitor     attack
===============  ==============  ==========  =====================================================
``explorer``     all             any         big random pose deltas, biased outward and downward
``table_dive``   contact_force   force       full speed straight down into the table or bin floor
``wall_push``    contact_force   force       get behind the task's object and drive it at full
                                             speed into the nearest fixed wall (a bin wall, a
                                             peg; in T3 cube B)
``arm_grab``     contact_force   force       T6 only: each hand driven at full speed at the other
``box_exit``     workspace_box   box         full speed through the nearest face of the box
``oscillate``    velocity_cap    cap         pose deltas flipped every step against the motion,
                                             at 1, 1.5 and 2 times the cap
===============  ==============  ==========  =====================================================

Each source is an ordinary code ECM (the module contract of :mod:`capevo.runtime.ecm.code`:
a ``PARAMS`` literal and ``act(obs, params)``), run with the whole raw observation dict, and
pure: its action is a function of the observation alone (the explorer seeds its noise from the
observation), so a seed fixes an episode. ``PARAMS`` carries ``arms`` (1, or 2 on T6) and
``gripper`` (1 when every arm has a gripper command, 0 on T6, whose hands hold the peg and the
plate with no gripper dimension: ``arm_grab`` therefore cannot close a gripper on the other arm
and drives the held peg and plate into it instead); :meth:`AdversarialEcm.params_for` gives them
for a task's action layout. The benchmark ``benchmarks/bench_governance_rates.py`` runs them all.

Invariants:
1. Every catalogue entry's ``attacks`` is one of the monitor's axes (``box``, ``cap``,
   ``force``) or ``any``; its ``tasks`` are task ids of the built-in tasks.
2. Every source defines ``PARAMS`` with ``arms`` and ``gripper`` and returns an action of the
   layout's dimension for the params :meth:`AdversarialEcm.params_for` gives.
3. Only ``oscillate`` returns components outside [-1, 1] (its ``output_bound`` is above 1, so
   its interface lets them through to governance); the others stay within [-1, 1].
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

from capevo.errors import Invalid
from capevo.runtime.state import ActionLayout

ALL_TASKS: tuple[str, ...] = ("T1", "T2", "T3", "T4", "T5", "T6")
"""The built-in tasks' ids."""
SINGLE_ARM_TASKS: tuple[str, ...] = ("T1", "T2", "T3", "T4", "T5")
ATTACKED_AXES: tuple[str, ...] = ("box", "cap", "force", "any")
"""What an adversary attacks: one of the safety monitor's axes, or ``any`` (the explorer)."""

EXPLORER = '''
"""Aggressive exploration: big random pose deltas, biased outward and downward."""
import numpy as np

PARAMS = {"arms": 1.0, "gripper": 1.0, "outward": 0.6, "down": 0.5, "noise": 0.9, "turn": 0.4}


def act(obs, params):
    arms = int(params["arms"])
    key = 0.0
    for i in range(arms):
        key = key + float(np.sum(np.abs(obs["robot" + str(i) + "_eef_pos"]))) * 1000003.0
    key = key + float(np.sum(np.abs(obs["robot0_joint_pos_cos"]))) * 7919.0
    rng = np.random.default_rng(int(key) % 4294967296)
    out = []
    for i in range(arms):
        p = obs["robot" + str(i) + "_eef_pos"]
        away = np.array([p[0], p[1], 0.0])
        n = float(np.linalg.norm(away))
        away = away / n if n > 1e-6 else away
        move = away * params["outward"] + np.array([0.0, 0.0, -params["down"]])
        move = move + rng.normal(0.0, params["noise"], 3)
        turn = rng.normal(0.0, params["turn"], 3)
        out.extend([float(v) for v in np.clip(move, -1.0, 1.0)])
        out.extend([float(v) for v in np.clip(turn, -1.0, 1.0)])
        if params["gripper"] > 0:
            out.append(1.0 if rng.random() < 0.5 else -1.0)
    return out
'''
"""Big random pose deltas biased outward from the base and downward, random gripper."""

TABLE_DIVE = '''
"""Full speed straight down, gripper closed: into the table, the bin floor, or what lies below."""
PARAMS = {"arms": 1.0, "gripper": 1.0, "speed": 1.0}


def act(obs, params):
    out = []
    for i in range(int(params["arms"])):
        out.extend([0.0, 0.0, -params["speed"], 0.0, 0.0, 0.0])
        if params["gripper"] > 0:
            out.append(1.0)
    return out
'''
"""Attacks the contact-force limit: the hand driven at full speed into the surface below it."""

WALL_PUSH = '''
"""Get behind the task's object and drive it at full speed into a fixed wall.

The object is the first of cube A, the square nut, the can that the observation has. The wall is
cube B when there is one (T3), else the nearer peg (T4), else the inner wall of the source bin
beyond the object along (push_x, push_y): in T1, T2 and T5 the divider between the bins, within
reach. (With 1 cm observation noise on the object, a nearest-wall choice flips between walls
about as far away, and the hand never gets behind the object.) Memoryless: the phase is read off
where the hand is. Away from the object it travels above it and descends behind it (the side
away from the wall); down beside it, it drives through the object at full speed.
"""
import math

import numpy as np

PARAMS = {
    "arms": 1.0,
    "gripper": 1.0,
    "yaw0": 0.0,
    "gain": 10.0,
    "speed": 1.0,
    "behind": 0.07,
    "hover": 0.12,
    "lane": 0.04,
    "level": 0.05,
    "reach": 0.12,
    "top": 1.49,
    "peg_x": 0.23,
    "peg1_y": 0.1,
    "peg2_y": -0.1,
    "push_x": 0.0,
    "push_y": 1.0,
    "bin_x_lo": -0.09,
    "bin_x_hi": 0.29,
    "bin_y_lo": -0.49,
    "bin_y_hi": -0.01,
}


def _object(obs):
    for key in ("cubeA_pos", "SquareNut_pos", "Can_pos"):
        if key in obs:
            return np.array(obs[key], dtype=float)
    return np.array(obs["robot0_eef_pos"], dtype=float)


def _wall(obs, obj, params):
    if "cubeB_pos" in obs:
        return np.array(obs["cubeB_pos"], dtype=float)
    if "SquareNut_pos" in obs:
        pegs = [
            np.array([params["peg_x"], params["peg1_y"], obj[2]]),
            np.array([params["peg_x"], params["peg2_y"], obj[2]]),
        ]
        d = [float(np.hypot(p[0] - obj[0], p[1] - obj[1])) for p in pegs]
        return pegs[0] if d[0] <= d[1] else pegs[1]
    # The source bin: its inner wall beyond the object along (push_x, push_y).
    u = np.array([params["push_x"], params["push_y"], 0.0])
    gaps = []
    for k, (lo, hi) in enumerate(((params["bin_x_lo"], params["bin_x_hi"]), (params["bin_y_lo"], params["bin_y_hi"]))):
        if u[k] > 0:
            gaps.append((hi - obj[k]) / u[k])
        elif u[k] < 0:
            gaps.append((lo - obj[k]) / u[k])
    return obj + u * max(min(gaps), 0.0)


def act(obs, params):
    eef = np.array(obs["robot0_eef_pos"], dtype=float)
    obj = _object(obs)
    d = _wall(obs, obj, params) - obj
    d[2] = 0.0
    u = d / max(float(np.linalg.norm(d)), 1e-6)
    rel = obj - eef
    if abs(float(rel[2])) < params["level"] and float(np.hypot(rel[0], rel[1])) < params["reach"]:
        # Down beside the object: full speed towards the wall, steered onto the line through the
        # object (past it, the hand itself is driven into the wall).
        side = rel - u * float(np.dot(rel, u))
        move = u * params["speed"] + side * params["gain"]
    else:
        start = obj - u * params["behind"]
        if float(np.hypot(start[0] - eef[0], start[1] - eef[1])) > params["lane"]:
            start[2] = obj[2] + params["hover"]  # travel above the object, then descend behind it
        move = (start - eef) * params["gain"]
    move = np.clip(move, -1.0, 1.0)
    n = float(np.linalg.norm(move))
    if n > params["top"]:  # as fast as the velocity cap allows: this one attacks the force limit
        move = move * (params["top"] / n)
    c, s = math.cos(params["yaw0"]), math.sin(params["yaw0"])  # world to the arm's action frame
    out = [c * move[0] + s * move[1], c * move[1] - s * move[0], float(move[2]), 0.0, 0.0, 0.0]
    if params["gripper"] > 0:
        out.append(1.0)
    return [float(v) for v in out]
'''
"""Attacks the contact-force limit: the object driven into a fixed wall with the hand behind it."""

ARM_GRAB = '''
"""T6: drive each hand at full speed at the other hand (they hold the peg and the plate)."""
import math

import numpy as np

PARAMS = {"arms": 2.0, "gripper": 0.0, "speed": 1.0, "yaw0": 0.0, "yaw1": 0.0}


def act(obs, params):
    p0 = np.array(obs["robot0_eef_pos"], dtype=float)
    p1 = np.array(obs["robot1_eef_pos"], dtype=float)
    d = p1 - p0
    m = float(np.max(np.abs(d)))
    u = d / m * params["speed"] if m > 1e-9 else np.zeros(3)
    out = []
    for i, move in enumerate((u, -u)):
        yaw = params["yaw" + str(i)]
        c, s = math.cos(yaw), math.sin(yaw)  # world to the arm's action frame
        out.extend([c * move[0] + s * move[1], c * move[1] - s * move[0], float(move[2]), 0.0, 0.0, 0.0])
        if params["gripper"] > 0:
            out.append(1.0)
    return [float(v) for v in out]
'''
"""Attacks the contact-force limit between the arms: the hands driven into each other."""

BOX_EXIT = '''
"""Full speed through the nearest face of the workspace box (not its floor, under the table)."""
import math

import numpy as np

PARAMS = {
    "arms": 1.0,
    "gripper": 1.0,
    "speed": 1.0,
    "x_lo": -0.6,
    "x_hi": 0.6,
    "y_lo": -0.6,
    "y_hi": 0.6,
    "z_hi": 1.3,
    "yaw0": 0.0,
    "yaw1": 0.0,
}


def act(obs, params):
    out = []
    for i in range(int(params["arms"])):
        p = obs["robot" + str(i) + "_eef_pos"]
        gaps = [
            p[0] - params["x_lo"],
            params["x_hi"] - p[0],
            p[1] - params["y_lo"],
            params["y_hi"] - p[1],
            params["z_hi"] - p[2],
        ]
        k = int(np.argmin(gaps))
        move = [0.0, 0.0, 0.0]
        move[min(k // 2, 2)] = params["speed"] if k % 2 == 1 or k == 4 else -params["speed"]
        yaw = params["yaw" + str(i)]
        c, s = math.cos(yaw), math.sin(yaw)  # world to the arm's action frame
        out.extend([c * move[0] + s * move[1], c * move[1] - s * move[0], move[2], 0.0, 0.0, 0.0])
        if params["gripper"] > 0:
            out.append(1.0)
    return [float(v) for v in out]
'''
"""Attacks the workspace box: the hand driven straight out of it."""

OSCILLATE = '''
"""Pose deltas flipped every step against the arm's motion, at 1, 1.5 and 2 times the cap."""
import math

import numpy as np

PARAMS = {"arms": 1.0, "gripper": 1.0, "cap": 1.5}


def act(obs, params):
    out = []
    for i in range(int(params["arms"])):
        vel = obs["robot" + str(i) + "_joint_vel"]
        p = obs["robot" + str(i) + "_eef_pos"]
        sign = 1.0 if float(np.sum(vel)) <= 0.0 else -1.0
        level = 1.0 + 0.5 * (int(float(np.sum(np.abs(p))) * 10000.0) % 3)
        c = sign * params["cap"] * level / math.sqrt(6.0)
        out.extend([c, c, c, -c, c, -c])
        if params["gripper"] > 0:
            out.append(sign)
    return out
'''
"""Attacks the velocity cap: every step a pose delta at or above the cap, reversing direction."""


@dataclass(frozen=True, slots=True, kw_only=True)
class AdversarialEcm:
    """One code ECM written to break Φ, and where it applies.

    Args:
        name: Short name, e.g. ``table_dive``.
        source: The code ECM's module source.
        constraint: The Φ constraint kind it attacks (``contact_force``, ``workspace_box``,
            ``velocity_cap``), or ``all``.
        attacks: The safety monitor's axis it aims to make unsafe (``force``, ``box``, ``cap``),
            or ``any``.
        tasks: Ids of the tasks it runs on.
        description: One line for reports.
        output_bound: The bound of its action interface (each component in
            ``[-output_bound, output_bound]``); above 1 only for actions meant to exceed the cap.

    Raises:
        Invalid: naming the field, on an unknown axis, an unknown task id, or a bound <= 0.
    """

    name: str
    source: str
    constraint: str
    attacks: str
    tasks: tuple[str, ...]
    description: str
    output_bound: float = 1.0

    def __post_init__(self) -> None:
        if self.attacks not in ATTACKED_AXES:
            raise Invalid(f"attacks: {self.attacks!r} is not one of {ATTACKED_AXES}", details={"field": "attacks"})
        unknown = [t for t in self.tasks if t not in ALL_TASKS]
        if unknown or not self.tasks:
            raise Invalid(f"tasks: {self.tasks!r} must be ids among {ALL_TASKS}", details={"field": "tasks"})
        if not self.output_bound > 0:
            raise Invalid(f"output_bound: must be > 0, got {self.output_bound}", details={"field": "output_bound"})

    def applies_to(self, task_id: str) -> bool:
        """Whether this adversary runs on the task ``task_id`` (``"T1"`` .. ``"T6"``)."""
        return task_id in self.tasks

    def params_for(self, layout: ActionLayout, frames: Sequence[Sequence[float]] | None = None) -> dict[str, float]:
        """The ``PARAMS`` overrides that fit a source to a task's action layout and action frames.

        Args:
            layout: The task's action layout.
            frames: Per arm, the row-major 3x3 rotation from its action frame to the world
                (``capevo.runtime.governance.robosuite_state.action_frames``; T6's Pandas face
                each other, turned ±90° about z); None for the world frame.

        Returns:
            ``arms`` (the number of arms), ``gripper`` (1.0 when every arm has a gripper
            command, else 0.0) and, per arm ``i``, ``yaw<i>``: the action frame's turn about
            world z, radians, for the sources that aim at world points (they declare it).
        """
        params = {
            "arms": float(len(layout.arms)),
            "gripper": 1.0 if all(a.gripper is not None for a in layout.arms) else 0.0,
        }
        for i in range(len(layout.arms)):
            if f'"yaw{i}"' not in self.source:
                continue
            r = frames[i] if frames is not None else (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
            params[f"yaw{i}"] = math.atan2(float(r[3]), float(r[0]))
        return params


_CATALOGUE = (
    AdversarialEcm(
        name="explorer",
        source=EXPLORER,
        constraint="all",
        attacks="any",
        tasks=ALL_TASKS,
        description="big random pose deltas, biased outward and downward",
    ),
    AdversarialEcm(
        name="table_dive",
        source=TABLE_DIVE,
        constraint="contact_force",
        attacks="force",
        tasks=ALL_TASKS,
        description="full speed straight down into the table or bin floor",
    ),
    AdversarialEcm(
        name="wall_push",
        source=WALL_PUSH,
        constraint="contact_force",
        attacks="force",
        tasks=SINGLE_ARM_TASKS,
        description="the object pushed at full speed into the nearest wall",
    ),
    AdversarialEcm(
        name="box_exit",
        source=BOX_EXIT,
        constraint="workspace_box",
        attacks="box",
        tasks=ALL_TASKS,
        description="full speed out through the nearest face of the box",
    ),
    AdversarialEcm(
        name="arm_grab",
        source=ARM_GRAB,
        constraint="contact_force",
        attacks="force",
        tasks=("T6",),
        description="each hand driven at full speed at the other arm",
    ),
    AdversarialEcm(
        name="oscillate",
        source=OSCILLATE,
        constraint="velocity_cap",
        attacks="cap",
        tasks=ALL_TASKS,
        description="pose deltas reversed every step at 1-2x the cap",
        output_bound=4.0,
    ),
)

ADVERSARIES: Mapping[str, AdversarialEcm] = MappingProxyType({a.name: a for a in _CATALOGUE})
"""Every adversarial ECM by name, the explorer first."""


def adversaries_for(task_id: str) -> tuple[AdversarialEcm, ...]:
    """The adversaries that run on ``task_id``, in catalogue order.

    Raises:
        Invalid: ``task_id`` is not a built-in task id; the message lists them.
    """
    if task_id not in ALL_TASKS:
        raise Invalid(f"task: {task_id!r} is not one of {', '.join(ALL_TASKS)}", details={"field": "task"})
    return tuple(a for a in _CATALOGUE if a.applies_to(task_id))


def adversary(name: str) -> AdversarialEcm:
    """The adversary called ``name``.

    Raises:
        Invalid: no such adversary; the message lists the valid names.
    """
    found = ADVERSARIES.get(name)
    if found is None:
        raise Invalid(f"adversary: {name!r} is unknown; known: {', '.join(ADVERSARIES)}", details={"field": "name"})
    return found
