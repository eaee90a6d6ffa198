"""T4 nut_assembly: robosuite NutAssembly with the square nut only, fitted onto the square peg.

robosuite drops the nut from 6 cm above the table at reset, so heights are measured against
the nut's resting height on the table rather than its height right after reset.

Success is robosuite's own ``NutAssembly._check_success`` (Invariant 1), latched per episode. Besides
the nut's position it asks the hand to be away from the nut's centre (robosuite's ``1 - tanh(10 d)
< 0.6``, d > 4.2 cm), which a hand still holding the nut by its handle (5.4 cm out) meets: a seated nut
still held counts, and ``release`` follows only to leave the scene clean.

Horizon: 300 control steps (15 s at robosuite's 20 Hz), ``default_horizon`` in the spec. The paper
(§4.1) names no horizon and robosuite's own default is 1000; capevo fixed 300 when the task was first
written, before any evolution run, and keeps it: it is part of the task, not of a budget, and is never
changed to make a target pass.

Invariants:
1. Success is exactly robosuite ``NutAssembly._check_success`` (single square nut): the nut's
   centre within 3 cm of the square peg in x and y and less than 5 cm above the table top, the
   end effector more than about 4.2 cm from the nut's centre.
2. ``object_height_above_start`` is 0 for a nut lying flat on the table.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from capevo.runtime.state import SINGLE_PANDA
from capevo.runtime.tasks import _common as c
from capevo.runtime.tasks.base import Movable, TaskEnv
from capevo.runtime.tasks.registry import register_task
from capevo.runtime.tasks.spec import SignalSpec, TaskSpec, cond, pred

NUT_HALF_THICKNESS = 0.01
PEG_CLEAR_HEIGHT = 0.15
"""Nut height above rest at which it clears the 0.2 m square peg (top 0.13 m above rest)."""

_NUT_KEYS = ("SquareNut_pos", "SquareNut_quat", "SquareNut_to_robot0_eef_pos", "SquareNut_to_robot0_eef_quat")
_REACH_KEYS = (
    "robot0_eef_pos",
    "robot0_eef_quat",
    "robot0_gripper_qpos",
    "SquareNut_pos",
    "SquareNut_quat",
    "SquareNut_to_robot0_eef_pos",
)
_TARGET_KEYS = (*_REACH_KEYS, "SquareNut_target_pos")

NUT_SIGNALS: tuple[SignalSpec, ...] = (
    *(
        SignalSpec(name=s.name, description=s.description.replace("grasp point", "handle"), units=s.units)
        for s in c.REACH_SIGNALS
    ),
    *c.TARGET_SIGNALS,
    c.SUCCESS_SIGNAL,
)


@register_task
class NutAssemblyTask(TaskEnv):
    """T4: fit the square nut over the square peg."""

    task_spec = TaskSpec(
        id="T4",
        name="nut_assembly",
        env_name="NutAssembly",
        n_arms=1,
        action_layout=SINGLE_PANDA,
        observation_keys=(*c.PANDA_PROPRIO_KEYS, *_NUT_KEYS, "SquareNut_target_pos"),
        position_keys=("robot0_eef_pos", "SquareNut_pos", "SquareNut_to_robot0_eef_pos"),
        signals=NUT_SIGNALS,
        decomposition=(
            c.reach_step("nut_assembly.reach", "the nut's handle", _REACH_KEYS),
            c.grasp_step("nut_assembly.grasp", "the nut", _REACH_KEYS),
            c.lift_step("nut_assembly.lift", "the nut", _TARGET_KEYS, PEG_CLEAR_HEIGHT),
            c.step(
                "nut_assembly.align",
                "Carry the nut until its hole is centred over the square peg, above the peg's top.",
                _TARGET_KEYS,
                pred(
                    "nut centre within 1 cm (horizontally) of the peg and above its top",
                    cond("object_target_xy_dist", "<", 0.01),
                    cond("object_height_above_start", ">", 0.13),
                    cond("grasped", ">=", 1.0),
                ),
                when=c.holding("nut"),
            ),
            c.step(
                "nut_assembly.insert",
                "Lower the nut down the peg until it is seated.",
                _TARGET_KEYS,
                pred("nut seated (robosuite's check)", cond("success", ">=", 1.0)),
                when=pred("nut over the peg", cond("object_target_xy_dist", "<", 0.02)),
            ),
            c.step(
                "nut_assembly.release",
                "Open the gripper and leave the nut on the peg.",
                _TARGET_KEYS,
                pred("nut seated and released", cond("success", ">=", 1.0), cond("grasped", "<", 1.0)),
                when=pred("nut seated", cond("success", ">=", 1.0)),
            ),
        ),
        success_text=(
            "robosuite NutAssembly._check_success with the square nut only: nut centre within 3 cm "
            "of the square peg in x and y and less than 5 cm above the table top, with the end effector "
            "more than about 4.2 cm from the nut's centre."
        ),
        reward_text=(
            "robosuite NutAssembly reward with reward_shaping=True, reward_scale=1: 1 when seated "
            "plus the best staged term (reach <=0.1, grasp 0.35, lift <=0.5, hover <=0.7)."
        ),
        default_horizon=300,
        perturbation_text=(
            "object_position_jitter shifts the nut's initial x, y uniformly within +-jitter, "
            "clipped to its start region (x in [-0.2, 0.05], y in [0.05, 0.3]); obs noise on "
            "robot0_eef_pos and the nut position keys."
        ),
    )

    def _build(self, kwargs: dict[str, Any]) -> Any:
        from robosuite.environments.manipulation.nut_assembly import NutAssembly

        return NutAssembly(robots="Panda", single_object_mode=2, nut_type="square", **kwargs)

    def _bind(self) -> None:
        env, sim = self._env, self._sim
        self._nut = env.nuts[env.nut_id]
        self._nut_body = int(env.obj_body_id[self._nut.name])
        self._handle_site = int(sim.model.site_name2id(self._nut.important_sites["handle"]))
        self._peg_body = int(env.peg1_body_id)
        self._rest_z = float(env.table_offset[2]) + NUT_HALF_THICKNESS

    def _movables(self) -> tuple[Movable, ...]:
        return (c.movable(self._sim, self._nut, x_bounds=(-0.2, 0.05), y_bounds=(0.05, 0.3)),)

    def _goal(self) -> tuple[float, float, float]:
        p = self._data.xpos[self._peg_body]
        return (float(p[0]), float(p[1]), self._rest_z)

    def _extra_observations(self) -> dict[str, np.ndarray]:
        return {"SquareNut_target_pos": np.array(self._goal(), dtype=np.float32)}

    def _is_success(self) -> bool:
        return bool(self._env._check_success())

    def _signals(self) -> dict[str, float]:
        env, d = self._env, self._data
        nut = c.xyz(d.xpos[self._nut_body])
        handle = c.xyz(d.site_xpos[self._handle_site])
        eef = c.xyz(d.site_xpos[self._eef_sites[0]])
        grasped = c.is_grasped(env, self._nut)
        s = c.reach_signals(eef, handle, nut[2], self._rest_z, grasped, c.gripper_opening(env))
        s.update(c.target_signals(nut, self._goal()))
        s["success"] = 1.0 if env._check_success() else 0.0
        return s
