"""Read :class:`RobotState` from a live robosuite 1.5 environment, in governance's conventions.

robosuite exposes the end-effector force as ``robot.ee_force[arm]``: the gripper's
``force_ee`` MuJoCo sensor at its ``ft_frame`` site. That raw reading is (a) in the site's
own frame, not the world frame, (b) the force the arm's last link exerts on the hand
(measured: pointing down while the hand presses on a table), and (c) includes holding up
the weight of everything below the sensor (hand, fingers, and in the two-arm tasks the
attached peg or hole). Governance wants the contact force the environment exerts on the
end effector in the world frame (see :mod:`capevo.runtime.governance.force`), so, for a
hand of subtree mass ``m`` under gravity ``g`` at rest or moving slowly::

    f_contact = −R_site · f_sensor − m · g

Hand acceleration (``m · a``, a few newtons at most for a 0.5 kg hand) is not removed.

Invariants:
1. With the hand still and touching nothing, :func:`eef_contact_force` is near zero
   (the weight is removed); pressing down on a table gives ``f_z > 0``.
2. Every lookup goes through ``robot.sim`` at call time, so the functions stay correct
   after a hard reset replaces the simulation.
3. :func:`robot_state` and :func:`action_frames` list arms robot by robot, each robot's arms
   in ``robot.arms`` order: the order of robosuite's flat action vector.
4. :func:`sensor_contact_force` with a :class:`ForceSensor` resolved once gives exactly what
   :func:`eef_contact_force` gives (which resolves it on every call).
5. :func:`action_frames` entries within 1e-9 of -1, 0 or 1 are snapped to them, so the
   right-angle mountings robosuite uses rotate actions exactly (no 1e-17 residues).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.state import RobotState


@dataclass(frozen=True, slots=True)
class ForceSensor:
    """Where one hand's ``force_ee`` sensor lives in a compiled model: resolve once, read every step."""

    adr: int
    """Index of the sensor's first value in ``data.sensordata``."""
    site: int
    """The sensor's site (its frame)."""
    mass: float
    """Subtree mass hanging from the sensor's body, kg."""


def force_sensor(robot: Any, arm: str) -> ForceSensor:
    """Resolve ``robot``'s ``force_ee`` sensor of ``arm`` (valid until a hard reset rebuilds the model)."""
    model = robot.sim.model
    sensor = model.sensor_name2id(robot.gripper[arm].important_sensors["force_ee"])
    site = int(model.sensor_objid[sensor])
    return ForceSensor(
        adr=int(model.sensor_adr[sensor]), site=site, mass=float(model.body_subtreemass[int(model.site_bodyid[site])])
    )


def sensor_contact_force(data: Any, sensor: ForceSensor, gravity: Sequence[float]) -> tuple[float, float, float]:
    """The contact force on the hand from ``sensor``'s reading in MuJoCo ``data``, newtons, world frame.

    Args:
        data: ``MjData`` (or robosuite's wrapper of it).
        sensor: From :func:`force_sensor`.
        gravity: The model's gravity vector.
    """
    a = sensor.adr
    sx, sy, sz = data.sensordata[a : a + 3].tolist()
    r = data.site_xmat[sensor.site].tolist()  # row-major 3x3, site frame to world frame
    gx, gy, gz = gravity
    m = sensor.mass
    return (
        -(r[0] * sx + r[1] * sy + r[2] * sz) - m * gx,
        -(r[3] * sx + r[4] * sy + r[5] * sz) - m * gy,
        -(r[6] * sx + r[7] * sy + r[8] * sz) - m * gz,
    )


def eef_contact_force(robot: Any, arm: str) -> tuple[float, float, float]:
    """Contact force on ``robot``'s end effector ``arm`` from the environment, newtons, world frame.

    Args:
        robot: A robosuite ``Robot`` of a reset environment.
        arm: One of ``robot.arms`` (``"right"`` for a single-arm Panda).

    Returns:
        ``(fx, fy, fz)`` as plain floats.
    """
    sim = robot.sim
    return sensor_contact_force(sim.data, force_sensor(robot, arm), sim.model.opt.gravity.tolist())


def eef_rotation(robot: Any, arm: str) -> tuple[float, ...]:
    """Rotation of the end-effector site to the world frame, row-major 9 floats."""
    return tuple(robot.sim.data.site_xmat[robot.eef_site_id[arm]].tolist())


def eef_position(robot: Any, arm: str) -> tuple[float, float, float]:
    """World position of the end-effector site in metres (what obs ``robot0_eef_pos`` reports)."""
    x, y, z = robot.sim.data.site_xpos[robot.eef_site_id[arm]].tolist()
    return (x, y, z)


def robot_state(robots: Sequence[Any]) -> RobotState:
    """Governance's view of every arm of ``robots`` (``env.robots``), in action-vector order.

    Each arm is an :class:`~capevo.runtime.governance.pose.ArmPose` (position, force, orientation).
    """
    return RobotState(
        arms=tuple(
            ArmPose(
                eef_pos=eef_position(robot, arm),
                eef_force=eef_contact_force(robot, arm),
                eef_rot=eef_rotation(robot, arm),  # type: ignore[arg-type]
            )
            for robot in robots
            for arm in robot.arms
        )
    )


def action_frames(robots: Sequence[Any]) -> tuple[tuple[float, ...], ...]:
    """Per arm, the rotation from its OSC action frame to the world frame (row-major, 9 floats).

    robosuite's OSC controllers with ``input_ref_frame="base"`` (the BASIC default) read pose
    deltas in the frame of the arm's ``{prefix}{arm}_center`` site; pass the result as
    ``phi.governor(layout, frames=...)``. Call it after ``env.reset()``.
    """
    out = []
    for robot in robots:
        for arm in robot.arms:
            ctrl = robot.composite_controller.part_controllers[arm]
            name = f"{ctrl.naming_prefix}{ctrl.part_name}_center"
            r = robot.sim.data.site_xmat[robot.sim.model.site_name2id(name)].tolist()
            out.append(tuple(_snap(float(x)) for x in r))
    return tuple(out)


def _snap(x: float) -> float:
    for v in (-1.0, 0.0, 1.0):
        if abs(x - v) <= 1e-9:
            return v
    return x
