"""T6 peg_in_hole: robosuite TwoArmPegInHole with two Pandas facing each other ("opposed").

Robot 0 holds the peg, robot 1 the plate with the square hole; neither has a gripper, so the
action is 12 values, 6 OSC_POSE deltas per arm, each in that robot's own base frame (the two
bases are turned +90 and -90 degrees about z).

The peg radius, which robosuite draws at construction, is pinned (``PEG_RADIUS``) so every
environment instance builds the same peg whatever its seed.

Invariants:
1. Success is exactly robosuite ``TwoArmPegInHole._check_success``: perpendicular distance of
   the hole centre from the peg axis < 6 cm, axial offset t in [-0.12, 0.14] m, cos > 0.95.
2. The signals ``peg_hole_perp_dist``, ``peg_hole_axial_dist`` and ``peg_hole_cos`` are
   robosuite's ``_compute_orientation`` values.
3. With jitter on, the peg never starts inside the plate (placement redrawn).
4. ``robot_state()`` force per arm is the total contact force on the object that arm holds
   (peg or plate): they hang from the hand body beside, not under, the wrist force sensor, so
   the sensor never sees their contacts.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from capevo.records import Predicate
from capevo.runtime.state import ActionLayout, ArmActionLayout
from capevo.runtime.tasks import _common as c
from capevo.runtime.tasks.base import JITTER_TRIES, PENETRATION_LIMIT, TaskEnv
from capevo.runtime.tasks.registry import register_task
from capevo.runtime.tasks.spec import EcmStep, SignalSpec, TaskSpec, cond, pred

TWO_PANDAS_NO_GRIPPER = ActionLayout(dim=12, arms=(ArmActionLayout(offset=0), ArmActionLayout(offset=6)))
"""Two Pandas, OSC_POSE via the BASIC composite controller, no grippers: robot 0 then robot 1."""

PEG_RADIUS = 0.0225
"""Middle of robosuite's default draw range (0.015, 0.03); the square hole is 0.1 m wide."""

_ARM_KEYS = ("joint_pos_cos", "joint_pos_sin", "joint_vel", "eef_pos", "eef_quat")
_OBJ_KEYS = ("hole_pos", "hole_quat", "peg_to_hole", "peg_quat", "angle", "t", "d")
_BOTH = ("robot0_eef_pos", "robot0_eef_quat", "robot1_eef_pos", "robot1_eef_quat", *_OBJ_KEYS)

PEG_SIGNALS: tuple[SignalSpec, ...] = (
    SignalSpec(name="peg_hole_dist", description="Peg centre to hole centre distance.", units="m"),
    SignalSpec(
        name="peg_hole_perp_dist",
        description="Distance of the hole centre from the peg's axis (robosuite's d).",
        units="m",
    ),
    SignalSpec(
        name="peg_hole_axial_dist",
        description="Signed distance along the peg axis from the peg centre to the hole plane (robosuite's t).",
        units="m",
    ),
    SignalSpec(name="peg_hole_axial_abs", description="abs(peg_hole_axial_dist).", units="m"),
    SignalSpec(name="peg_hole_cos", description="|cos| of the angle between peg axis and hole normal (1 = aligned)."),
    SignalSpec(name="peg_hole_rel_speed", description="Relative linear speed of peg and plate.", units="m/s"),
    SignalSpec(name="peg_hole_contact_force", description="Norm of the summed contact force on the peg.", units="N"),
    c.SUCCESS_SIGNAL,
)


_INSIDE = ("success", ">=", 1.0)

# (ECM, what it does, when it is done, its termination conditions, applicability or None).
# At reset the peg hangs down and the plate stands upright (cos about 0), 20-35 cm apart.
_PEG_STEPS: tuple[tuple[str, str, str, tuple[tuple[str, str, float], ...], Predicate | None], ...] = (
    (
        "orient_peg",
        "Peg arm turns the peg from hanging down toward pointing at the plate.",
        "peg axis within about 45 degrees of the hole normal",
        (("peg_hole_cos", ">", 0.7),),
        None,
    ),
    (
        "orient_hole",
        "Plate arm turns the plate so the hole faces the peg.",
        "peg axis within about 25 degrees of the hole normal",
        (("peg_hole_cos", ">", 0.9),),
        None,
    ),
    (
        "approach_peg",
        "Peg arm moves the peg in front of the hole.",
        "hole centre within 6 cm of the peg axis",
        (("peg_hole_perp_dist", "<", 0.06), ("peg_hole_cos", ">", 0.9)),
        None,
    ),
    (
        "approach_hole",
        "Plate arm moves the hole onto the peg's axis.",
        "hole centre within 3 cm of the peg axis",
        (("peg_hole_perp_dist", "<", 0.03), ("peg_hole_cos", ">", 0.9)),
        None,
    ),
    (
        "align",
        "Both arms fine-tune orientation so peg and hole are coaxial.",
        "peg axis within about 14 degrees of the hole normal, centred",
        (("peg_hole_cos", ">", 0.97), ("peg_hole_perp_dist", "<", 0.03)),
        None,
    ),
    (
        "pre_insert",
        "Bring the peg to the hole entrance along its axis.",
        "peg centre within 20 cm of the hole plane, centred and aligned",
        (("peg_hole_axial_abs", "<", 0.2), ("peg_hole_perp_dist", "<", 0.03), ("peg_hole_cos", ">", 0.95)),
        None,
    ),
    (
        "insert",
        "Push the peg through the hole.",
        "peg inside the hole (robosuite's check) with its centre within 5 cm of the hole plane",
        (_INSIDE, ("peg_hole_axial_abs", "<", 0.05)),
        pred("peg at the entrance", cond("peg_hole_perp_dist", "<", 0.04)),
    ),
    (
        "hold",
        "Hold peg and plate still with the peg inside the hole.",
        "peg inside the hole and both arms still",
        (_INSIDE, ("peg_hole_rel_speed", "<", 0.01)),
        pred("peg inside the hole", cond(*_INSIDE)),
    ),
)

PEG_DECOMPOSITION: tuple[EcmStep, ...] = tuple(
    c.step(f"peg_in_hole.{name}", description, _BOTH, pred(text, *(cond(*x) for x in done)), when=when)
    for name, description, text, done, when in _PEG_STEPS
)


@register_task
class PegInHoleTask(TaskEnv):
    """T6: two arms put the peg through the plate's hole."""

    # The arms work face to face: under the default envelope, 5 of 300 adversarial episodes still
    # pressed one arm's link 5-7 on the other arm or its plate (25-250 N) while both hands kept clear.
    sensed_wrist_links = 2

    task_spec = TaskSpec(
        id="T6",
        name="peg_in_hole",
        env_name="TwoArmPegInHole",
        n_arms=2,
        action_layout=TWO_PANDAS_NO_GRIPPER,
        observation_keys=(*(f"robot{i}_{k}" for i in (0, 1) for k in _ARM_KEYS), *_OBJ_KEYS),
        position_keys=("robot0_eef_pos", "robot1_eef_pos", "hole_pos", "peg_to_hole"),
        signals=PEG_SIGNALS,
        decomposition=PEG_DECOMPOSITION,
        success_text=(
            "robosuite TwoArmPegInHole._check_success: hole centre within 6 cm of the peg axis, "
            "axial offset t in [-0.12, 0.14] m and |cos(peg axis, hole normal)| > 0.95."
        ),
        reward_text=(
            "robosuite TwoArmPegInHole reward with reward_shaping=True, reward_scale=1: "
            "(success + (1-tanh(dist)) + (1-tanh(d)) + (1-tanh(|t|)) + cos) / 5."
        ),
        default_horizon=300,
        perturbation_text=(
            "object_position_jitter moves each end effector's initial x, y (so the held peg or "
            "plate) uniformly within +-jitter, keeping height and orientation, through a joint "
            "offset from the arm's Jacobian; obs noise on robot0_eef_pos, robot1_eef_pos, hole_pos and peg_to_hole "
            "(angle, t and d stay exact)."
        ),
    )

    def _build(self, kwargs: dict[str, Any]) -> Any:
        from robosuite.environments.manipulation.two_arm_peg_in_hole import TwoArmPegInHole

        kwargs = {"peg_radius": (PEG_RADIUS, PEG_RADIUS), "env_configuration": "opposed", **kwargs}
        return TwoArmPegInHole(robots=["Panda", "Panda"], **kwargs)

    def _bind(self) -> None:
        import mujoco

        self._mj = mujoco
        env = self._env
        self._peg_body = int(env.peg_body_id)
        self._hole_body = int(env.hole_body_id)
        self._held_geoms = tuple(
            np.array([g for g in range(self._model.ngeom) if int(self._model.geom_bodyid[g]) == body], dtype=np.int64)
            for body in (self._peg_body, self._hole_body)
        )
        self._vel = np.zeros(6)
        self._cf = np.zeros(6)
        self._arm_dofs = tuple(np.asarray(r._ref_joint_vel_indexes) for r in env.robots)
        self._arm_qpos = tuple(np.asarray(r._ref_joint_pos_indexes) for r in env.robots)

    def _apply_jitter(self, rng: np.random.Generator, half_width: float) -> None:
        # Each end effector moves by (dx, dy) with height and orientation kept, through the joint
        # offset pinv(J) [dx, dy, 0, 0, 0, 0]; redrawn while the peg would start inside the plate.
        m, d, mj = self._model, self._data, self._mj
        held = frozenset(int(g) for geoms in self._held_geoms for g in geoms)
        start = d.qpos.copy()
        jac = np.zeros((6, m.nv))
        for _ in range(JITTER_TRIES):
            for site, dofs, qadr in zip(self._eef_sites, self._arm_dofs, self._arm_qpos, strict=True):
                dx, dy = rng.uniform(-half_width, half_width, size=2)
                mj.mj_jacSite(m, d, jac[:3], jac[3:], site)
                d.qpos[qadr] += np.linalg.pinv(jac[:, dofs]) @ np.array([dx, dy, 0.0, 0.0, 0.0, 0.0])
            self._sim.forward()
            if self._max_penetration(held) <= PENETRATION_LIMIT:
                return
            d.qpos[:] = start
            self._sim.forward()

    def _is_success(self) -> bool:
        return bool(self._env._check_success())

    def _arm_force(self, arm: int) -> tuple[float, float, float]:
        return tuple(float(x) for x in self._contact_force(self._held_geoms[arm]))  # type: ignore[return-value]

    def _contact_force(self, geoms: np.ndarray) -> np.ndarray:
        """Sum of contact forces other geoms exert on ``geoms``, world frame."""
        d, m = self._data, self._model
        total = np.zeros(3)
        n = d.ncon
        if n == 0:
            return total
        g1 = d.contact.geom1[:n]
        g2 = d.contact.geom2[:n]
        on2 = np.isin(g2, geoms)
        on1 = np.isin(g1, geoms)
        for i in np.flatnonzero(on1 ^ on2):
            self._mj.mj_contactForce(m, d, int(i), self._cf)
            # contact frame rows: normal (from geom1 to geom2), then two tangents
            world = d.contact.frame[i].reshape(3, 3).T @ self._cf[:3]
            total += world if on2[i] else -world
        return total

    def _signals(self) -> dict[str, float]:
        env, d, m = self._env, self._data, self._model
        t, dist_perp, cos = env._compute_orientation()
        hole_pos = d.xpos[self._hole_body]
        centre = hole_pos + d.xmat[self._hole_body].reshape(3, 3) @ np.array([0.1, 0.0, 0.0])
        peg = d.xpos[self._peg_body]
        v = []
        for body in (self._peg_body, self._hole_body):
            self._mj.mj_objectVelocity(m, d, self._mj.mjtObj.mjOBJ_BODY, body, self._vel, 0)
            v.append(self._vel[3:].copy())
        success = bool(env._check_success())
        return {
            "peg_hole_dist": float(np.linalg.norm(peg - centre)),
            "peg_hole_perp_dist": float(dist_perp),
            "peg_hole_axial_dist": float(t),
            "peg_hole_axial_abs": abs(float(t)),
            "peg_hole_cos": float(cos),
            "peg_hole_rel_speed": float(np.linalg.norm(v[0] - v[1])),
            "peg_hole_contact_force": float(np.linalg.norm(self._contact_force(self._held_geoms[0]))),
            "success": 1.0 if success else 0.0,
        }
