"""T1 pick, T2 place and T5 pick_place_multi: robosuite PickPlace (bins arena, one Panda).

T1 and T2 use the can alone (``single_object_mode=2, object_type="can"``). T5 uses a
three-object variant (milk, bread, can, each with its own quadrant of the goal bin).

Invariants:
1. T1 success is exactly ``object_height_above_start > 0.05`` (the can's origin, against its
   height right after reset, jitter included).
2. T2 success is robosuite ``PickPlace._check_success`` (can inside its goal quadrant, below the
   bin rim, gripper more than ~4 cm away); T5 success is the same for all three objects.
3. The goal positions given as ``<Object>_target_pos`` observations are exact (never noised).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np

from capevo.runtime.state import SINGLE_PANDA
from capevo.runtime.tasks import _common as c
from capevo.runtime.tasks.base import Movable, TaskEnv
from capevo.runtime.tasks.registry import register_task
from capevo.runtime.tasks.spec import EcmStep, SignalSpec, TaskSpec, cond, pred

BIN1_POS = (0.1, -0.25, 0.8)
"""robosuite's default source bin centre; its floor top is at z 0.82, its rim at z 0.90."""
BIN_INNER_HALF = (0.19, 0.24)
LIFT_HEIGHT = 0.05
RELEASE_CLEARANCE = math.atanh(0.4) / 10.0
"""About 4.2 cm: robosuite counts an object as placed only if 1 - tanh(10 * eef distance) < 0.6."""
CARRY_HEIGHT = 0.12
"""Lift needed for an object to clear the bin rims on its way to the goal bin."""
OVER_QUADRANT = 0.04
"""How far inside its goal quadrant (``object_quadrant_margin``) the carried object must be for
``move`` to hand over to ``release``, metres: the can's radius (3.3 cm) plus a little, so that it
ends inside the quadrant, robosuite's success, after being lowered. Hand-written.

Why the quadrant and not the quadrant's centre: the can's quadrant centre lies 0.858 m
(horizontally) from the Panda's shoulder, past the 0.808 m wrist reach the default Φ holds the
arm to (``capevo.runtime.governance.task_phi.PANDA_REACH``). A hand-off "within 4 cm of the
centre" could then be met only by a can held off-centre in the fingers: under the default Φ,
T2's evolved sets timed out in ``move`` on 21 of 30 held-out seeds, braked at the reach edge.
robosuite's own success asks for the quadrant, so the hand-off asks for it too."""
RELEASE_OVER_QUADRANT = 0.02
"""``release`` applies while the object is at least this far inside its goal quadrant, metres."""

RIDGED = frozenset({"Milk"})
"""Objects whose top is a ridge, grasped with the fingers closing along it (the milk carton: in its
collision mesh, a 4 x 4 cm body to 5 cm above its origin, a roof sloping to a ridge along its own
y axis at 7 cm, and a 2 mm fin to 8.3 cm; measured in MuJoCo). Their reach and grasp read the
object's orientation (``<Object>_quat``)."""
GRASP_HEIGHT: Mapping[str, float] = MappingProxyType({"Milk": 0.065, "Bread": 0.0, "Can": 0.0})
"""Height of each object's grasp point above its origin, metres: where the grip site sits when
the fingers straddle the object. Hand-written from the meshes (measured in MuJoCo at reset): the
Panda hand's palm is 2.8 cm above the grip site. The milk carton is a 5.4 cm box up to 5 cm above
its origin, then a 3.4 x 2.2 cm top up to 8.3 cm, so the palm stops the hand 5.5 cm above the
origin; its grasp point is 6.5 cm up, fingers on the top, palm 1 cm clear. With the grasp point
at the origin, as before, the reach termination (within 2 cm in height) could not be met (T5
held-out 0/30: the hand braked 5.5-6.4 cm above the milk's origin). The can (top 4 cm) and the
bread (top 2.5 cm) are grasped at the origin, as in T1 and T2. ``release``'s termination measures
the hand's clearance from the grasp point, so for the milk it is stricter than robosuite's check
(from the origin); ``n_placed`` measures from the origin, as robosuite does."""

_CAN_KEYS = ("Can_pos", "Can_quat", "Can_to_robot0_eef_pos", "Can_to_robot0_eef_quat")
_CAN_REACH_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "Can_pos", "Can_to_robot0_eef_pos")
_CAN_TARGET_KEYS = (*_CAN_REACH_KEYS, "Can_target_pos")
_POS_KEYS_CAN = ("robot0_eef_pos", "Can_pos", "Can_to_robot0_eef_pos")
_JITTER_TEXT = (
    "object_position_jitter shifts each object's initial x, y uniformly within +-jitter after "
    "robosuite's own placement, clipped to the source bin and redrawn if it would overlap another "
    "object; obs noise on robot0_eef_pos and the object position keys."
)


def _bin_movable(sim: Any, obj: Any) -> Movable:
    r = float(obj.horizontal_radius) + 0.01
    return c.movable(
        sim,
        obj,
        x_bounds=(BIN1_POS[0] - BIN_INNER_HALF[0] + r, BIN1_POS[0] + BIN_INNER_HALF[0] - r),
        y_bounds=(BIN1_POS[1] - BIN_INNER_HALF[1] + r, BIN1_POS[1] + BIN_INNER_HALF[1] - r),
    )


class _PickPlaceBase(TaskEnv):
    """Shared machinery of the bins tasks: objects, start heights, per-object signals."""

    _object_names: tuple[str, ...] = ("Can",)

    def _bind(self) -> None:
        env = self._env
        by_name = {o.name: o for o in env.objects}
        self._objects = tuple(by_name[n] for n in self._object_names)
        self._obj_index = {n: [o.name for o in env.objects].index(n) for n in self._object_names}
        self._obj_body = {n: int(env.obj_body_id[n]) for n in self._object_names}
        self._start_z = {n: 0.0 for n in self._object_names}
        self._goals: dict[str, tuple[float, float, float]] = {}

    def _movables(self) -> tuple[Movable, ...]:
        return tuple(_bin_movable(self._sim, o) for o in self._objects)

    def _on_reset(self) -> None:
        d = self._data
        self._start_z = {n: float(d.xpos[b][2]) for n, b in self._obj_body.items()}
        self._goals = {}

    def _goal(self, name: str) -> tuple[float, float, float]:
        """Where the object's origin is when it rests in its goal quadrant.

        Worked out once per episode: robosuite's object offsets are read from the model's
        XML on every access, and the goal bin does not move.
        """
        goal = self._goals.get(name)
        if goal is None:
            goal = self._goals[name] = self._compute_goal(name)
        return goal

    def _compute_goal(self, name: str) -> tuple[float, float, float]:
        env = self._env
        tx, ty, tz = env.target_bin_placements[self._obj_index[name]]
        obj = self._objects[self._object_names.index(name)]
        # robosuite places the target at the bin's floor level; the origin sits above by the
        # object's bottom offset (plus the floor's thickness, as for the start bin).
        return (float(tx), float(ty), float(tz) - float(obj.bottom_offset[2]))

    def _extra_observations(self) -> dict[str, np.ndarray]:
        return {f"{n}_target_pos": np.array(self._goal(n), dtype=np.float32) for n in self._object_names}

    def _object_signals(
        self, name: str, eef: tuple[float, float, float], opening: float, *, to_target: bool = True
    ) -> dict[str, float]:
        """The reach signals of object ``name`` (about its grasp point), plus (``to_target``) its goal signals."""
        env = self._env
        pos = c.xyz(self._data.xpos[self._obj_body[name]])
        obj = self._objects[self._object_names.index(name)]
        grasp_point = (pos[0], pos[1], pos[2] + GRASP_HEIGHT[name])
        s = c.reach_signals(eef, grasp_point, pos[2], self._start_z[name], c.is_grasped(env, obj), opening)
        if to_target:
            s.update(c.target_signals(pos, self._goal(name)))
            s["object_quadrant_margin"] = self._quadrant_margin(pos, self._obj_index[name])
            s["object_in_bin"] = 0.0 if env.not_in_bin(np.asarray(pos), self._obj_index[name]) else 1.0
        return s

    def _quadrant_margin(self, pos: tuple[float, float, float], bin_id: int) -> float:
        """Horizontal distance from ``pos`` to the nearest edge of goal quadrant ``bin_id``:
        positive inside, negative outside (the quadrant's bounds as robosuite's ``not_in_bin``
        draws them)."""
        env = self._env
        half_x, half_y = float(env.bin_size[0]) / 2.0, float(env.bin_size[1]) / 2.0
        x_low = float(env.bin2_pos[0]) - (half_x if bin_id in (0, 2) else 0.0)
        y_low = float(env.bin2_pos[1]) - (half_y if bin_id < 2 else 0.0)
        return min(pos[0] - x_low, x_low + half_x - pos[0], pos[1] - y_low, y_low + half_y - pos[1])

    def _eef(self) -> tuple[float, float, float]:
        return c.xyz(self._data.site_xpos[self._eef_sites[0]])


def _can_env(kwargs: dict[str, Any]) -> Any:
    from robosuite.environments.manipulation.pick_place import PickPlace

    return PickPlace(robots="Panda", single_object_mode=2, object_type="can", **kwargs)


PICK_SIGNALS: tuple[SignalSpec, ...] = (*c.REACH_SIGNALS, c.SUCCESS_SIGNAL)


@register_task
class PickTask(_PickPlaceBase):
    """T1: lift the can more than 5 cm."""

    # T1's reward is its own (reach, grasp, lift); robosuite's PickPlace reward is about bins.
    reads_robosuite_reward = False

    task_spec = TaskSpec(
        id="T1",
        name="pick",
        env_name="PickPlace",
        n_arms=1,
        action_layout=SINGLE_PANDA,
        observation_keys=(*c.PANDA_PROPRIO_KEYS, *_CAN_KEYS),
        position_keys=_POS_KEYS_CAN,
        signals=PICK_SIGNALS,
        decomposition=(
            c.reach_step("pick.reach", "the can", _CAN_REACH_KEYS),
            c.grasp_step("pick.grasp", "the can", _CAN_REACH_KEYS),
            c.lift_step("pick.lift", "the can", _CAN_REACH_KEYS, LIFT_HEIGHT),
        ),
        success_text="The can's origin is more than 5 cm above its height right after reset.",
        reward_text=(
            "1.0 on a success step; otherwise 0.2*(1-tanh(10*eef_object_dist)) + 0.3*grasped "
            "+ 0.4*grasped*clip(object_height_above_start/0.05, 0, 1), so at most 0.9."
        ),
        default_horizon=150,
        perturbation_text=_JITTER_TEXT,
    )

    def _build(self, kwargs: dict[str, Any]) -> Any:
        return _can_env(kwargs)

    def _is_success(self) -> bool:
        return float(self._data.xpos[self._obj_body["Can"]][2]) - self._start_z["Can"] > LIFT_HEIGHT

    def _reward(self, robosuite_reward: float, success: bool) -> float:
        if success:
            return 1.0
        s = self.signals()
        lift = min(max(s["object_height_above_start"] / LIFT_HEIGHT, 0.0), 1.0)
        return 0.2 * (1.0 - math.tanh(10.0 * s["eef_object_dist"])) + 0.3 * s["grasped"] + 0.4 * s["grasped"] * lift

    def _signals(self) -> dict[str, float]:
        # T1 has no goal: its signals are the reach signals alone, in spec order.
        s = self._object_signals("Can", self._eef(), c.gripper_opening(self._env), to_target=False)
        s["success"] = 1.0 if s["object_height_above_start"] > LIFT_HEIGHT else 0.0
        return s


PLACE_SIGNALS: tuple[SignalSpec, ...] = (
    *c.REACH_SIGNALS,
    *c.TARGET_SIGNALS,
    SignalSpec(
        name="object_quadrant_margin",
        description="Horizontal distance from the object to the nearest edge of its goal quadrant: > 0 inside.",
        units="m",
    ),
    SignalSpec(
        name="object_in_bin",
        description="1 if the object is inside its goal quadrant below the rim (gripper ignored).",
    ),
    c.SUCCESS_SIGNAL,
)


def _move_step(ecm: str, what: str, keys: tuple[str, ...], *, prefix: str = "") -> EcmStep:
    return c.step(
        ecm,
        f"Carry {what} over its goal quadrant of the goal bin, keeping it above the rims.",
        keys,
        pred(
            f"{what} {round(OVER_QUADRANT * 100)} cm inside its goal quadrant (horizontally), still held",
            cond(f"{prefix}object_quadrant_margin", ">", OVER_QUADRANT),
            cond(f"{prefix}grasped", ">=", 1.0),
        ),
        when=c.holding(what, prefix=prefix),
    )


def _release_step(ecm: str, what: str, keys: tuple[str, ...], *, prefix: str = "") -> EcmStep:
    return c.step(
        ecm,
        f"Lower {what} into the goal quadrant, open the gripper and move the hand away.",
        keys,
        pred(
            f"{what} in its goal quadrant with the gripper clear (robosuite's check)",
            cond(f"{prefix}object_in_bin", ">=", 1.0),
            cond(f"{prefix}eef_object_dist", ">", round(RELEASE_CLEARANCE, 3) + 0.001),
        ),
        when=pred(
            f"{what} above its goal quadrant", cond(f"{prefix}object_quadrant_margin", ">", RELEASE_OVER_QUADRANT)
        ),
    )


@register_task
class PlaceTask(_PickPlaceBase):
    """T2: put the can into its quadrant of the goal bin."""

    task_spec = TaskSpec(
        id="T2",
        name="place",
        env_name="PickPlace",
        n_arms=1,
        action_layout=SINGLE_PANDA,
        observation_keys=(*c.PANDA_PROPRIO_KEYS, *_CAN_KEYS, "Can_target_pos"),
        position_keys=_POS_KEYS_CAN,
        signals=PLACE_SIGNALS,
        decomposition=(
            c.reach_step("place.reach", "the can", _CAN_REACH_KEYS),
            c.grasp_step("place.grasp", "the can", _CAN_REACH_KEYS),
            c.lift_step("place.lift", "the can", _CAN_TARGET_KEYS, CARRY_HEIGHT),
            _move_step("place.move", "the can", _CAN_TARGET_KEYS),
            _release_step("place.release", "the can", _CAN_TARGET_KEYS),
        ),
        success_text=(
            "robosuite PickPlace._check_success: the can is inside its quadrant of the goal bin, "
            "below the rim, and the gripper is more than about 4 cm from it."
        ),
        reward_text=(
            "robosuite PickPlace reward with reward_shaping=True, reward_scale=1: 1 per object in "
            "its bin plus the best staged term (reach <=0.1, grasp 0.35, lift <=0.5, hover <=0.7)."
        ),
        default_horizon=300,
        perturbation_text=_JITTER_TEXT,
    )

    def _build(self, kwargs: dict[str, Any]) -> Any:
        return _can_env(kwargs)

    def _is_success(self) -> bool:
        return bool(self._env._check_success())

    def _signals(self) -> dict[str, float]:
        s = self._object_signals("Can", self._eef(), c.gripper_opening(self._env))
        s["success"] = 1.0 if self._env._check_success() else 0.0
        return s


MULTI_OBJECTS: tuple[str, ...] = ("Milk", "Bread", "Can")
"""T5's objects, in placement order; object i goes to goal-bin quadrant i."""


@functools.cache
def _three_object_pick_place() -> type:
    from robosuite.environments.manipulation.pick_place import PickPlace
    from robosuite.models.objects import (
        BreadObject,
        BreadVisualObject,
        CanObject,
        CanVisualObject,
        MilkObject,
        MilkVisualObject,
    )

    classes = {
        "Milk": (MilkObject, MilkVisualObject),
        "Bread": (BreadObject, BreadVisualObject),
        "Can": (CanObject, CanVisualObject),
    }

    class CapevoPickPlaceThree(PickPlace):
        """PickPlace with milk, bread and can only; object i belongs in goal quadrant i."""

        def _load_model(self) -> None:
            # PickPlace indexes bins by object position in self.objects and by object_to_id in its
            # shaped reward; keep both equal.
            self.obj_names = list(MULTI_OBJECTS)
            self.object_to_id = {n.lower(): i for i, n in enumerate(MULTI_OBJECTS)}
            super()._load_model()

        def _construct_objects(self) -> None:
            self.objects = [classes[n][0](name=n) for n in MULTI_OBJECTS]

        def _construct_visual_objects(self) -> None:
            self.visual_objects = [classes[n][1](name="Visual" + n) for n in MULTI_OBJECTS]

        def reward(self, action: Any = None) -> float:
            # PickPlace divides by 4 objects in full mode; rescale so three placed objects give 3/3.
            return float(super().reward(action)) * 4.0 / len(MULTI_OBJECTS)

    return CapevoPickPlaceThree


def _multi_signals() -> tuple[SignalSpec, ...]:
    out: list[SignalSpec] = []
    for o in MULTI_OBJECTS:
        p = o.lower() + "_"
        for s in (*c.REACH_SIGNALS, *c.TARGET_SIGNALS, *PLACE_SIGNALS[-3:-1]):
            if s.name == "gripper_opening":
                continue
            out.append(SignalSpec(name=p + s.name, description=f"{o}: {s.description}", units=s.units))
    out.append(c.REACH_SIGNALS[-1])
    out.append(SignalSpec(name="n_placed", description="How many of the three objects are in their goal quadrants."))
    out.append(c.SUCCESS_SIGNAL)
    return tuple(out)


def _multi_decomposition() -> tuple[EcmStep, ...]:
    steps: list[EcmStep] = []
    for o in MULTI_OBJECTS:
        p, what = o.lower() + "_", f"the {o.lower()}"
        keys = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", f"{o}_pos", f"{o}_to_robot0_eef_pos")
        tkeys = (*keys, f"{o}_target_pos")
        if o in RIDGED:  # reach and grasp turn the hand to the carton's ridge
            keys = (*keys, f"{o}_quat")
        name = f"pick_place_multi.{o.lower()}"
        steps += [
            c.reach_step(f"{name}.reach", what, keys, prefix=p),
            c.grasp_step(f"{name}.grasp", what, keys, prefix=p),
            c.lift_step(f"{name}.lift", what, tkeys, CARRY_HEIGHT, prefix=p),
            _move_step(f"{name}.move", what, tkeys, prefix=p),
            _release_step(f"{name}.release", what, tkeys, prefix=p),
        ]
    return tuple(steps)


@register_task
class PickPlaceMultiTask(_PickPlaceBase):
    """T5: put milk, bread and can each into its own quadrant of the goal bin."""

    _object_names = MULTI_OBJECTS

    task_spec = TaskSpec(
        id="T5",
        name="pick_place_multi",
        env_name="PickPlace",
        n_arms=1,
        action_layout=SINGLE_PANDA,
        observation_keys=(
            *c.PANDA_PROPRIO_KEYS,
            *(
                k
                for o in MULTI_OBJECTS
                for k in (
                    f"{o}_pos",
                    f"{o}_quat",
                    f"{o}_to_robot0_eef_pos",
                    f"{o}_to_robot0_eef_quat",
                    f"{o}_target_pos",
                )
            ),
        ),
        position_keys=("robot0_eef_pos", *(k for o in MULTI_OBJECTS for k in (f"{o}_pos", f"{o}_to_robot0_eef_pos"))),
        signals=_multi_signals(),
        decomposition=_multi_decomposition(),
        success_text=(
            "robosuite PickPlace._check_success over milk, bread and can: every object inside its "
            "quadrant of the goal bin, below the rim, with the gripper more than about 4 cm away."
        ),
        reward_text=(
            "robosuite PickPlace reward (reward_shaping=True) rescaled to three objects: "
            "(objects placed + best staged term) / 3."
        ),
        default_horizon=900,
        perturbation_text=_JITTER_TEXT,
    )

    def _build(self, kwargs: dict[str, Any]) -> Any:
        return _three_object_pick_place()(robots="Panda", single_object_mode=0, **kwargs)

    def _is_success(self) -> bool:
        return bool(self._env._check_success())

    def _signals(self) -> dict[str, float]:
        eef = self._eef()
        opening = c.gripper_opening(self._env)
        out: dict[str, float] = {}
        placed = 0
        for o in MULTI_OBJECTS:
            s = self._object_signals(o, eef, opening)
            # robosuite's check measures the hand's distance from the object's origin.
            origin = self._data.xpos[self._obj_body[o]]
            clear = math.dist(eef, c.xyz(origin)) > RELEASE_CLEARANCE
            in_place = s["object_in_bin"] >= 1.0 and clear
            placed += int(in_place)
            p = o.lower() + "_"
            out.update({p + k: v for k, v in s.items() if k != "gripper_opening"})
        out["gripper_opening"] = opening
        out["n_placed"] = float(placed)
        out["success"] = 1.0 if self._env._check_success() else 0.0
        return out
