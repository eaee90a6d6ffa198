"""Pieces shared by the single-Panda gripper tasks: observation keys, signal specs, the
pick-style decomposition and the per-step signal arithmetic.

Signals of the single-arm tasks follow one vocabulary so that predicates read the same in
every task: ``object`` is the thing being manipulated now and ``target`` where it must go.
"""

from __future__ import annotations

import math
from typing import Any

from capevo.records import Predicate
from capevo.runtime.tasks.base import Movable
from capevo.runtime.tasks.spec import EcmStep, SignalSpec, cond, pred

PANDA_PROPRIO_KEYS: tuple[str, ...] = (
    "robot0_joint_pos_cos",
    "robot0_joint_pos_sin",
    "robot0_joint_vel",
    "robot0_eef_pos",
    "robot0_eef_quat",
    "robot0_gripper_qpos",
    "robot0_gripper_qvel",
)
"""Proprioception of a single Panda, in flat-observation order."""

GRIPPER_OPEN = 0.06
"""Finger gap in metres above which the gripper counts as open (fully open is about 0.08)."""

REACH_SIGNALS: tuple[SignalSpec, ...] = (
    SignalSpec(
        name="eef_object_dist",
        description="End effector (grip site) to the object's grasp point (its origin unless the task says otherwise).",
        units="m",
    ),
    SignalSpec(name="eef_object_xy_dist", description="Horizontal part of eef_object_dist.", units="m"),
    SignalSpec(
        name="eef_object_dz",
        description="End-effector height minus the object's grasp point height (positive: above).",
        units="m",
    ),
    SignalSpec(
        name="object_height_above_start",
        description="Object height minus its resting height at the start of the episode.",
        units="m",
    ),
    SignalSpec(
        name="grasped",
        description="1 if both finger pads touch the object (robosuite _check_grasp), else 0.",
    ),
    SignalSpec(
        name="gripper_opening",
        description="Gap between the two Panda fingers (about 0 closed, 0.08 fully open).",
        units="m",
    ),
)
TARGET_SIGNALS: tuple[SignalSpec, ...] = (
    SignalSpec(name="object_target_xy_dist", description="Horizontal distance object to its goal.", units="m"),
    SignalSpec(
        name="object_target_dz",
        description="Object height minus the height it has when correctly placed at the goal.",
        units="m",
    ),
)
SUCCESS_SIGNAL = SignalSpec(name="success", description="1 while the task's success criterion holds, else 0.")


def xyz(a: Any) -> tuple[float, float, float]:
    return (float(a[0]), float(a[1]), float(a[2]))


def reach_signals(
    eef: tuple[float, float, float],
    grasp_point: tuple[float, float, float],
    object_z: float,
    start_z: float,
    grasped: bool,
    opening: float,
) -> dict[str, float]:
    """The :data:`REACH_SIGNALS` from positions (world frame, metres)."""
    dx, dy, dz = eef[0] - grasp_point[0], eef[1] - grasp_point[1], eef[2] - grasp_point[2]
    xy = math.hypot(dx, dy)
    return {
        "eef_object_dist": math.hypot(xy, dz),
        "eef_object_xy_dist": xy,
        "eef_object_dz": dz,
        "object_height_above_start": object_z - start_z,
        "grasped": 1.0 if grasped else 0.0,
        "gripper_opening": opening,
    }


def target_signals(obj: tuple[float, float, float], goal: tuple[float, float, float]) -> dict[str, float]:
    """The :data:`TARGET_SIGNALS`: ``goal`` is where the object's origin sits when placed."""
    return {
        "object_target_xy_dist": math.hypot(obj[0] - goal[0], obj[1] - goal[1]),
        "object_target_dz": obj[2] - goal[2],
    }


def gripper_opening(env: Any) -> float:
    robot = env.robots[0]
    q = env.sim.data.qpos[robot._ref_gripper_joint_pos_indexes["right"]]
    return float(q[0] - q[1])


def is_grasped(env: Any, obj: Any) -> bool:
    """Whether both finger pads of the Panda's gripper touch ``obj`` (robosuite ``_check_grasp``)."""
    return bool(env._check_grasp(gripper=env.robots[0].gripper["right"], object_geoms=obj))


def movable(sim: Any, obj: Any, *, x_bounds: tuple[float, float], y_bounds: tuple[float, float]) -> Movable:
    """The :class:`Movable` of robosuite object ``obj``: its free joint and contact geoms."""
    return Movable(
        joint=obj.joints[0],
        geom_ids=frozenset(int(sim.model.geom_name2id(g)) for g in obj.contact_geoms),
        x_bounds=x_bounds,
        y_bounds=y_bounds,
    )


def step(
    ecm: str, description: str, keys: tuple[str, ...], done: Predicate, *, when: Predicate | None = None
) -> EcmStep:
    """One ECM of a decomposition: what it does, what it reads, when it is done (termination)
    and when it can start (applicability; none by default)."""
    return EcmStep(
        ecm=ecm,
        description=description,
        observation_keys=keys,
        termination=done,
        applicability=when if when is not None else Predicate(),
    )


def holding(what: str, *, prefix: str = "") -> Predicate:
    """``<what> grasped``: the gripper holds the object (both finger pads touch it)."""
    return pred(f"{what} grasped", cond(f"{prefix}grasped", ">=", 1.0))


def reach_step(ecm: str, what: str, keys: tuple[str, ...], *, prefix: str = "") -> EcmStep:
    p = prefix
    return step(
        ecm,
        f"Bring the open gripper around {what}, fingers straddling its grasp point.",
        keys,
        pred(
            f"gripper open and within 2 cm of {what}'s grasp point",
            cond(f"{p}eef_object_xy_dist", "<", 0.02),
            cond(f"{p}eef_object_dz", "<", 0.02),
            cond(f"{p}eef_object_dz", ">", -0.02),
            cond("gripper_opening", ">", GRIPPER_OPEN),
        ),
    )


def grasp_step(ecm: str, what: str, keys: tuple[str, ...], *, prefix: str = "") -> EcmStep:
    return step(
        ecm,
        f"Close the gripper on {what} without moving it.",
        keys,
        pred(f"both finger pads touch {what}", cond(f"{prefix}grasped", ">=", 1.0)),
        when=pred(f"gripper near {what}", cond(f"{prefix}eef_object_dist", "<", 0.04)),
    )


def lift_step(ecm: str, what: str, keys: tuple[str, ...], height: float, *, prefix: str = "") -> EcmStep:
    return step(
        ecm,
        f"Lift {what} straight up by more than {height * 100:.0f} cm, keeping the grasp.",
        keys,
        pred(
            f"{what} more than {height * 100:.0f} cm above its start",
            cond(f"{prefix}object_height_above_start", ">", height),
        ),
        when=holding(what, prefix=prefix),
    )
