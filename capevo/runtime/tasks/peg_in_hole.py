"""T6 peg_in_hole: robosuite TwoArmPegInHole with two Pandas facing each other ("opposed").

Robot 0 holds the peg, robot 1 the plate with the square hole; neither has a gripper, so the
action is 12 values, 6 OSC_POSE deltas per arm, each in that robot's own base frame (the two
bases are turned +90 and -90 degrees about z).

The peg radius is drawn per episode as robosuite draws it: uniformly within robosuite's default
``peg_radius`` range (``PEG_RADIUS_RANGE``, 1.5-3 cm) from the episode's scene generator
(``env.rng``). robosuite draws it when it loads the model, so with ``hard_reset=False`` (one model
per environment, see :mod:`.base`) it would be drawn once per instance; here the model is built
with the largest radius (its collision bounds then hold any draw) and every reset sets the peg's
geoms, mass and inertia (density kept) to the episode's draw. (MuJoCo's ``mj_setConst`` quantities,
used only by the constraint solver's diagonal approximation, keep the compiled peg's values.)

Success and the strict insertion check. robosuite's ``_check_success`` (the task's success, which
ends the episode) accepts the hole plane anywhere from 12 cm behind to 14 cm ahead of the peg's
centre; the peg's tip is 13 cm ahead of it, so the check passes with the tip still 1 cm short of
the plate, before the peg ever touches it (issue 19 measured 0.0 N contact force through
successful episodes). ``peg_inserted`` is a strict check from ground truth reported beside it:
the peg's axis crosses the plate's mid-plane inside the square opening with the peg's radius to
spare (within ``INSERT_TOL``), the tip is through the plate (``peg_insertion_depth`` at least the
plate's thickness) and peg and hole are aligned as robosuite requires (|cos| > 0.95).
:attr:`PegInHoleTask.peg_inserted` latches it per episode as ``info["is_success"]`` latches robosuite's.

Horizon: 300 control steps (15 s at robosuite's 20 Hz), ``default_horizon`` in the spec. The paper
(§4.1) names no horizon and robosuite's own default is 1000; capevo fixed 300 when the task was first
written (before any evolution run) and keeps it: it is part of the task, not of a budget, and is never
changed to make a target pass. v0 does not finish within it (issue 19 measured 0/3 at 300 steps and
3/3 at 600, 3-26 steps too slow): that is one of v0's weaknesses, its low gains, for the learners to
fix, not a reason to lengthen the task.

Invariants:
1. Success is exactly robosuite ``TwoArmPegInHole._check_success``: perpendicular distance of
   the hole centre from the peg axis < 6 cm, axial offset t in [-0.12, 0.14] m, cos > 0.95.
2. The signals ``peg_hole_perp_dist``, ``peg_hole_axial_dist`` and ``peg_hole_cos`` are
   robosuite's ``_compute_orientation`` values.
3. With jitter on, the peg never starts inside the plate, nor within :data:`START_CLEARANCE` of it
   (placement redrawn).
4. ``robot_state()`` force per arm is the total contact force on the object that arm holds
   (peg or plate): they hang from the hand body beside, not under, the wrist force sensor, so
   the sensor never sees their contacts.
5. ``peg_radius`` lies in ``PEG_RADIUS_RANGE``; equal seeds draw equal radii, whatever the jitter
   setting (the draw comes from the scene generator right after robosuite's reset).
6. ``peg_inserted`` implies ``peg_insertion_depth`` >= ``PLATE_THICKNESS``.
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

START_CLEARANCE = 0.01
"""Metres the jittered peg must start clear of the plate, else the placement is redrawn. Measured
before any skill acted (zero action, default perturbations): on seed 100051 the peg started 1.7 mm
inside the plate (within the objects' 2 mm overlap tolerance) and read 29.8 N after the first step;
on seed 250206 it started 0.8 mm clear and read 35.6 N. Of seeds 250000-250299, 7 started with
the two touching. A 20 N limit broken at step 0 grades an episode unsafe that no
skill or Φ could have kept safe."""

TWO_PANDAS_NO_GRIPPER = ActionLayout(dim=12, arms=(ArmActionLayout(offset=0), ArmActionLayout(offset=6)))
"""Two Pandas, OSC_POSE via the BASIC composite controller, no grippers: robot 0 then robot 1."""

PEG_RADIUS_RANGE = (0.015, 0.03)
"""robosuite ``TwoArmPegInHole``'s default ``peg_radius`` draw range (metres); the square hole is 0.1 m wide."""
PEG_HALF_LENGTH = 0.13
"""robosuite's default ``peg_length``, the cylinder's half-length: the tip is this far ahead of its centre."""
OPENING_X = (0.06, 0.16)
OPENING_Y = (-0.05, 0.05)
"""The square opening in the plate's frame (metres), between its four boxes (``plate-with-hole.xml``).
robosuite's hole centre (0.1, 0) is 1 cm off the opening's true centre (0.11, 0)."""
PLATE_THICKNESS = 0.02
"""The plate's boxes are 2 cm thick, centred on its frame's z = 0 plane."""
INSERT_TOL = 0.003
"""Metres the peg's surface may lie past the opening's edge for ``peg_inserted``: contacts are soft,
and a peg tilted by up to acos(0.95) widens its section through the plate by about 3 mm."""
ALIGNED_COS = 0.95
"""robosuite's alignment threshold, kept for the strict check."""

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
    SignalSpec(
        name="peg_insertion_depth",
        description="How far the peg's tip is past the plate's entry face along the hole normal (0: not reached).",
        units="m",
    ),
    SignalSpec(
        name="peg_inserted",
        description=(
            "Strict insertion (ground truth): the peg's axis crosses the plate inside the opening with its "
            "radius to spare, the tip through the plate, |cos| > 0.95; 1 or 0."
        ),
    ),
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

    # The arms work face to face: with the hands alone sensed, 5 of 300 adversarial episodes pressed
    # one arm's link 5-7 on the other arm or its plate (25-250 N) while both hands kept clear, and
    # a learned whole-task policy (AM-bc, results/cpu-small) met link 5 on link 5 at 27 N; with
    # links 5-7 braked by their own motion, the same policy's last unsafe step was link 3 on the
    # other arm's plate (22.4 N, seed 2000042001). So here links 3-7 are sensed.
    sensed_wrist_links = 5

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

        # Compiled with the largest radius: the collision bounds (rbound, aabb, BVH) then hold every
        # radius a reset draws, which only shrinks the geoms.
        top = PEG_RADIUS_RANGE[1]
        kwargs = {"peg_radius": (top, top), "env_configuration": "opposed", **kwargs}
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
        m = self._model
        # the peg's collision and visual cylinders; its density from the compiled mass
        self._peg_geoms = np.array([g for g in range(m.ngeom) if int(m.geom_bodyid[g]) == self._peg_body], np.int64)
        r0, h = (float(x) for x in m.geom_size[self._peg_geoms[0], :2])
        self._peg_half_length = h
        self._peg_density = float(m.body_mass[self._peg_body]) / (np.pi * r0 * r0 * 2.0 * h)
        self.peg_radius = r0
        """This episode's peg radius (metres), drawn at every reset."""
        self._peg_compiled = (
            m.geom_size[self._peg_geoms].copy(),
            float(m.body_mass[self._peg_body]),
            m.body_inertia[self._peg_body].copy(),
        )
        """The peg as the model was compiled: restored before every reset (see :meth:`reset`)."""
        self._radius_drawn = False
        self._inserted = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """:meth:`TaskEnv.reset` with the peg put back as compiled first.

        robosuite's own reset (the robots' and controllers' reset) runs on the model as it is, and
        the peg radius drawn for the last episode changed its mass and inertia: without this an
        episode depended on the one before it (measured: robot 0's joints 1e-5 rad apart after
        one step of the same seed, after 300 steps enough to turn a held-out episode unsafe or
        safe). With it a seed fixes the episode whatever ran before in the process.
        """
        sizes, mass, inertia = self._peg_compiled
        m = self._model
        m.geom_size[self._peg_geoms] = sizes
        m.body_mass[self._peg_body] = mass
        m.body_inertia[self._peg_body] = inertia
        return super().reset(seed=seed, options=options)

    def _draw_peg_radius(self) -> None:
        """Draw and set this episode's peg radius as robosuite's ``get_size`` draws it at model load."""
        env, m = self._env, self._model
        # get_size draws one uniform per size component: the radius, then the (fixed) half-length
        r = float(env.rng.uniform(*PEG_RADIUS_RANGE))
        env.rng.uniform(self._peg_half_length, self._peg_half_length)
        h = self._peg_half_length
        m.geom_size[self._peg_geoms, 0] = r
        mass = self._peg_density * np.pi * r * r * 2.0 * h
        m.body_mass[self._peg_body] = mass
        # solid cylinder about its centre; z is its axis
        side = mass * (3.0 * r * r + (2.0 * h) ** 2) / 12.0
        m.body_inertia[self._peg_body] = (side, side, 0.5 * mass * r * r)
        env.peg_radius = (r, r)
        self.peg_radius = r
        self._radius_drawn = True
        self._sim.forward()

    def _on_reset(self) -> None:
        if not self._radius_drawn:  # jitter off: _apply_jitter did not run
            self._draw_peg_radius()
        self._radius_drawn = False
        self._inserted = False

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """:meth:`TaskEnv.step`, latching the strict check in :attr:`peg_inserted` (``info`` keeps the
        keys every task returns)."""
        out = super().step(action)
        # computed here rather than read from signals(): filling the signal cache on every step would
        # change when it is computed for everyone else
        self._inserted = self._inserted or self._strict_insertion(float(self._env._compute_orientation()[2]))[1]
        return out

    @property
    def peg_inserted(self) -> bool:
        """Latched strict insertion of the current episode (see the module docstring)."""
        return self._inserted

    @property
    def strict_success(self) -> bool | None:
        """:attr:`peg_inserted`: the strict check every outcome reports beside robosuite's success."""
        return self._inserted

    def _apply_jitter(self, rng: np.random.Generator, half_width: float) -> None:
        # Each end effector moves by (dx, dy) with height and orientation kept, through the joint
        # offset pinv(J) [dx, dy, 0, 0, 0, 0]; redrawn while the peg would start inside the plate.
        # the radius first: the placement check below sees this episode's peg
        self._draw_peg_radius()
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
            if self._max_penetration(held) <= PENETRATION_LIMIT and self._peg_plate_gap() >= START_CLEARANCE:
                return
            d.qpos[:] = start
            self._sim.forward()

    def _peg_plate_gap(self) -> float:
        """Distance between the peg's and the plate's collision geoms, metres (at most START_CLEARANCE)."""
        m, d, mj = self._model, self._data, self._mj
        gap = START_CLEARANCE
        for g in self._held_geoms[0]:
            for h in self._held_geoms[1]:
                if (m.geom_contype[g] or m.geom_conaffinity[g]) and (m.geom_contype[h] or m.geom_conaffinity[h]):
                    gap = min(gap, float(mj.mj_geomDistance(m, d, int(g), int(h), START_CLEARANCE, None)))
        return gap

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
        depth, inserted = self._strict_insertion(float(cos))
        return {
            "peg_hole_dist": float(np.linalg.norm(peg - centre)),
            "peg_hole_perp_dist": float(dist_perp),
            "peg_hole_axial_dist": float(t),
            "peg_hole_axial_abs": abs(float(t)),
            "peg_hole_cos": float(cos),
            "peg_hole_rel_speed": float(np.linalg.norm(v[0] - v[1])),
            "peg_hole_contact_force": float(np.linalg.norm(self._contact_force(self._held_geoms[0]))),
            "peg_insertion_depth": depth,
            "peg_inserted": 1.0 if inserted else 0.0,
            "success": 1.0 if success else 0.0,
        }

    def _strict_insertion(self, cos: float) -> tuple[float, bool]:
        """``(peg_insertion_depth, peg_inserted)`` from the simulator's poses (see the module docstring)."""
        d = self._data
        r_hole = d.xmat[self._hole_body].reshape(3, 3)
        # peg centre and axis in the plate's frame: its z is the hole normal, z = 0 its mid-plane
        p = r_hole.T @ (d.xpos[self._peg_body] - d.xpos[self._hole_body])
        a = r_hole.T @ d.xmat[self._peg_body].reshape(3, 3)[:, 2]
        h, r = self._peg_half_length, self.peg_radius
        if abs(a[2]) < 1e-6:
            return 0.0, False  # the peg lies in the plate's plane: it cannot be through the hole
        side = 1.0 if a[2] > 0 else -1.0  # the tip moves along +a, entering from the face at z = -side * t/2
        s = -p[2] / a[2]  # where the axis crosses the mid-plane, along the axis from the peg's centre
        if s < -h:
            return 0.0, False  # the plate is behind the hand: the peg points away from it
        depth = max(0.0, side * (p[2] + h * a[2]) + 0.5 * PLATE_THICKNESS)
        q = p + s * a
        room = r - INSERT_TOL
        inside = (
            OPENING_X[0] + room <= q[0] <= OPENING_X[1] - room
            and OPENING_Y[0] + room <= q[1] <= OPENING_Y[1] - room
            and s <= h
        )
        return depth, bool(inside and depth >= PLATE_THICKNESS and cos > ALIGNED_COS)
