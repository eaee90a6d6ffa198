"""What governance sees of the robot, and where each arm's commands sit in the action vector.

Tasks produce :class:`RobotState` each step; governance reads it. Plain tuples of floats,
not numpy arrays: governance runs on every action and numpy's per-call cost dominates on
vectors this small (see BENCHMARKS.md, governance overhead).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True, kw_only=True)
class ArmState:
    """One arm's end effector in the world frame."""

    eef_pos: tuple[float, float, float]
    """Position in metres."""
    eef_force: tuple[float, float, float]
    """Contact force at the end effector in newtons, from the robot's force sensor."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RobotState:
    """All arms of the robot(s) in the scene, in the order of :attr:`ActionLayout.arms`."""

    arms: tuple[ArmState, ...]


@dataclass(frozen=True, slots=True, kw_only=True)
class ArmActionLayout:
    """OSC_POSE slice of one arm: ``offset..offset+3`` translation, ``offset+3..offset+6`` rotation."""

    offset: int
    gripper: int | None = None
    """Index of the gripper command, or None for an arm without a gripper."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ActionLayout:
    """How a task's flat action vector splits into arms."""

    dim: int
    arms: tuple[ArmActionLayout, ...]


SINGLE_PANDA = ActionLayout(dim=7, arms=(ArmActionLayout(offset=0, gripper=6),))
"""Panda with OSC_POSE via the BASIC composite controller: 6 pose deltas + 1 gripper."""
