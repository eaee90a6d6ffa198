"""T3 stack: robosuite Stack, put the red cube A on the green cube B.

Success is robosuite's own ``Stack._check_success`` (Invariant 1), latched per episode. Horizon: 200
control steps (10 s at robosuite's 20 Hz), ``default_horizon`` in the spec. The paper (§4.1) names no
horizon and robosuite's own default is 1000; capevo fixed 200 when the task was first written, before
any evolution run, and keeps it: it is part of the task, not of a budget, and is never changed to make
a target pass.

Invariants:
1. Success is exactly robosuite ``Stack._check_success``: cube A above the table by 4 cm,
   touching cube B, and not grasped.
2. ``object_target_dz`` is 0 when cube A rests flat on cube B (target height is cube B's
   origin plus both half sizes).
"""

from __future__ import annotations

from typing import Any

from capevo.runtime.state import SINGLE_PANDA
from capevo.runtime.tasks import _common as c
from capevo.runtime.tasks.base import Movable, TaskEnv
from capevo.runtime.tasks.registry import register_task
from capevo.runtime.tasks.spec import SignalSpec, TaskSpec, cond, pred

TABLE_REACH = 0.15
"""Half-width of the table square (around its centre) that jittered cubes are clipped into."""

_CUBE_KEYS = (
    "cubeA_pos",
    "cubeA_quat",
    "cubeB_pos",
    "cubeB_quat",
    "cubeA_to_cubeB",
    "gripper_to_cubeA",
    "gripper_to_cubeB",
)
_REACH_KEYS = (
    "robot0_eef_pos",
    "robot0_eef_quat",
    "robot0_gripper_qpos",
    "cubeA_pos",
    "cubeA_quat",
    "gripper_to_cubeA",
)
_TARGET_KEYS = (*_REACH_KEYS, "cubeB_pos", "cubeA_to_cubeB")

STACK_SIGNALS: tuple[SignalSpec, ...] = (
    *c.REACH_SIGNALS,
    *c.TARGET_SIGNALS,
    SignalSpec(name="object_on_target", description="1 if cube A touches cube B, else 0."),
    c.SUCCESS_SIGNAL,
)


@register_task
class StackTask(TaskEnv):
    """T3: stack cube A on cube B."""

    task_spec = TaskSpec(
        id="T3",
        name="stack",
        env_name="Stack",
        n_arms=1,
        action_layout=SINGLE_PANDA,
        observation_keys=(*c.PANDA_PROPRIO_KEYS, *_CUBE_KEYS),
        position_keys=(
            "robot0_eef_pos",
            "cubeA_pos",
            "cubeB_pos",
            "cubeA_to_cubeB",
            "gripper_to_cubeA",
            "gripper_to_cubeB",
        ),
        signals=STACK_SIGNALS,
        decomposition=(
            c.reach_step("stack.reach", "cube A", _REACH_KEYS),
            c.grasp_step("stack.grasp", "cube A", _REACH_KEYS),
            c.lift_step("stack.lift", "cube A", _TARGET_KEYS, 0.06),
            c.step(
                "stack.align",
                "Carry cube A until it hangs right above cube B.",
                _TARGET_KEYS,
                pred(
                    "cube A within 1 cm (horizontally) of cube B and clear of it",
                    cond("object_target_xy_dist", "<", 0.01),
                    cond("object_target_dz", ">", 0.0),
                    cond("grasped", ">=", 1.0),
                ),
                when=c.holding("cube A"),
            ),
            c.step(
                "stack.lower",
                "Lower cube A onto cube B until they touch.",
                _TARGET_KEYS,
                pred("cube A touches cube B", cond("object_on_target", ">=", 1.0), cond("object_target_dz", "<", 0.01)),
                when=pred("cube A above cube B", cond("object_target_xy_dist", "<", 0.02)),
            ),
            c.step(
                "stack.release",
                "Open the gripper and leave cube A resting on cube B.",
                _TARGET_KEYS,
                pred("cube A stacked and released (robosuite's check)", cond("success", ">=", 1.0)),
                when=pred("cube A on cube B", cond("object_on_target", ">=", 1.0)),
            ),
        ),
        success_text=(
            "robosuite Stack._check_success: cube A more than 4 cm above the table, touching cube B, not grasped."
        ),
        reward_text=(
            "robosuite Stack reward with reward_shaping=True, reward_scale=1: max of reach+grasp "
            "(<=0.5), lift+align (<=1.5) and stacked (2.0), divided by 2."
        ),
        default_horizon=200,
        perturbation_text=(
            "object_position_jitter shifts both cubes' initial x, y uniformly within +-jitter, "
            "clipped to +-0.15 m around the table centre and redrawn if the cubes would overlap; "
            "obs noise on robot0_eef_pos and every cube position / offset key."
        ),
    )

    def _build(self, kwargs: dict[str, Any]) -> Any:
        from robosuite.environments.manipulation.stack import Stack

        return Stack(robots="Panda", **kwargs)

    def _bind(self) -> None:
        env = self._env
        self._a_body = int(env.cubeA_body_id)
        self._b_body = int(env.cubeB_body_id)
        self._stack_dz = float(env.cubeA.size[2] + env.cubeB.size[2])
        # robosuite drops the cubes from 1 cm; heights count from cube A resting on the table.
        self._start_z = float(env.table_offset[2]) + float(env.cubeA.size[2])

    def _movables(self) -> tuple[Movable, ...]:
        env = self._env
        cx, cy = float(env.table_offset[0]), float(env.table_offset[1])
        return tuple(
            c.movable(
                self._sim,
                cube,
                x_bounds=(cx - TABLE_REACH, cx + TABLE_REACH),
                y_bounds=(cy - TABLE_REACH, cy + TABLE_REACH),
            )
            for cube in (env.cubeA, env.cubeB)
        )

    def _is_success(self) -> bool:
        return bool(self._env._check_success())

    def _signals(self) -> dict[str, float]:
        env, d = self._env, self._data
        a = c.xyz(d.xpos[self._a_body])
        b = c.xyz(d.xpos[self._b_body])
        eef = c.xyz(d.site_xpos[self._eef_sites[0]])
        s = c.reach_signals(eef, a, a[2], self._start_z, c.is_grasped(env, env.cubeA), c.gripper_opening(env))
        s.update(c.target_signals(a, (b[0], b[1], b[2] + self._stack_dz)))
        s["object_on_target"] = 1.0 if env.check_contact(env.cubeA, env.cubeB) else 0.0
        s["success"] = 1.0 if env._check_success() else 0.0
        return s
