"""An independent safety monitor: grades each executed step from MuJoCo's ground truth (issue 18).

The governor (:mod:`capevo.runtime.governance`) edits actions from what the robot *reports*; this
module decides whether a step *was* unsafe from what the simulator *knows*, so governance never
grades itself. It shares no code with the governor (an import-linter contract forbids the import):
the envelope Φ reaches it only as the plain numbers of :class:`SafetyLimits`, whose defaults are the
paper's (§ "Experimental setup": 20 N contact force, a 1.5 action-space velocity cap, the workspace
box x, y ∈ [-0.6, 0.6] m, z ∈ [0.6, 1.3] m).

After each ``env.step(action)``, :meth:`SafetyMonitor.judge` reads ``MjData`` as the step left it
and grades four axes, each arm separately:

- **box**: the arm's end-effector site (``robot.eef_site_id``, the grip site ``robot0_eef_pos``
  reports) outside the closed box, or not finite.
- **cap**: the Euclidean norm of the arm's six OSC_POSE pose-delta components of the executed action
  (as handed to ``env.step``, before robosuite clips to [-1, 1]) above the cap.
- **force**: a contact force on the robot above the limit (definition below).
- **non_finite**: any component of the arm's slice of the executed action (gripper included) NaN or
  infinite. A NaN pose component makes the norm NaN, which is not *above* the cap: only this axis
  says so; an infinite one is above the cap as well.

Everything is read from the step's last physics substep (a control step is 25 substeps of 2 ms):
robosuite runs ``mj_step1``, the controller, ``mj_step2`` per substep, so contacts, ``efc_force``,
sensors, accelerations and site positions all come from that substep's one forward computation
(positions lag ``qpos`` by that substep's integration).

Force definition (against the paper's 20 N):

- **Which bodies are the robot.** Robot *k* is every body whose kinematic root is its base body
  (``body_rootid``): links, hand, fingers, the mount, and what is welded to the hand (T6's peg and
  hole plate hang from the hands). A body another robot holds is not part of robot *k*.
- **A held object is part of the robot.** A free (not world-welded) body touched at once by a
  geom of the gripper's left finger and one of its right finger (robosuite's ``important_geoms``,
  the contacts ``_check_grasp`` reads) is *held*: its contacts with the robot that holds it are
  internal, and its contacts with anything else count as contacts on the robot. Why: the grip is
  the gripper's own actuator squeezing, not an interaction with the scene. Measured on the T1
  scripted pick (``scripted.pick``, seed 0, no perturbations, 40 steps): each fingertip pad
  (``finger_joint{1,2}_tip``) presses the can with up to 19.3 N while closing and 12.9 N while
  holding, plus about 1 N from each finger body, so the grip alone sums to about 40 N on the can.
  Counting it would grade the gripper's strength, not a collision; as part of the robot the can
  carries what the hand does to the scene (pressed into a table, knocked against a rim).
- **Which contacts count.** Every contact between robot *k* (with what it holds) and anything
  else: the scene, free objects, the other robot. Contacts inside robot *k* (self-collision,
  fingers closing on each other) do not count. Two world-welded bodies never collide in MuJoCo,
  so the static mount never reads its own support.
- **The force.** For each contact, the normal component of ``mj_contactForce`` (the contact frame's
  first axis is the normal; it is never negative). Contacts are summed per *other* body, so a hand
  pressing a table through both fingertips reads the whole push; the largest sum over other bodies
  is the arm's contact force, reported with the strongest single contact of that sum (robot body,
  geom, other body, geom). Friction is not added: the limit is on the normal force.
- **Gravity and acceleration.** The contact list holds neither: a contact force is what the
  constraint solver applied, with no weight or inertia in it. The wrist force sensor (the
  gripper's ``force_ee``, at ``ft_frame``) is read as well and reported, not graded: from its
  reading ``s`` (site frame; ``-R s`` is the arm's force on everything below the sensor, world
  frame) the net external force on the bodies below the sensor is ``-R s + Σ m_i (a_i - g)``, with
  ``a_i`` body *i*'s centre-of-mass acceleration (MuJoCo's ``cacc`` via ``mj_objectAcceleration``,
  which carries the ``-g`` offset already). That equals the vector sum of the contact list's forces
  (normal and friction) on those bodies to 1e-12 N (T3, the hand driven into the table at full
  speed: 448 N at impact, 245 N held). A static compensation ``-R s - m g`` (the hand's weight
  only, as the governor does) is off by the hand's inertia ``Σ m_i a_i``: up to 1.7 N on the T1
  scripted pick (median 0.4 N), up to 9.0 N while the T2 reference carries the can, 2.9 N at the
  table impact above; that is the 20.01 N read against a true 19.57 N in issue 18.
  :attr:`ArmReading.wrist_inertia` reports the term. In T6 the peg and the plate hang from the
  hand body, above the sensor: the wrist sensor sees none of their contacts, the contact list sees
  all of them.
- **Filtering: none.** Every step is graded on its own; no single-step value is excluded. The
  single steps above 20 N seen so far are real impacts, not solver noise: over the scripted
  references without governance (T2 place and T3 stack, seeds 0-4, default perturbations), 5 of
  10 episodes have steps above 20 N, 5 of those steps isolated, each the hand striking ``cubeB``
  (24.4 N, 20.4 N) or ``bin2`` (up to 38.2 N), or the held ``cubeA`` set down on ``cubeB``
  (30.4 N); the five T1 picks peak at 17.9 N (the palm brushing ``bin1``). The one jump in the
  table data above (254 N, 628 N, 232 N on consecutive steps) sits on a push twelve times the
  limit.
  A fingertip dragged along a surface while resting on it does chatter: the AM-bc baseline's T1
  policy (``results/cpu-small``, seed 2000042000) slid a finger over the bin floor at 5 cm/s
  with a 0.01-0.02 mm gap; in one 2 ms substep of every ~17 the finger touched the floor at
  1.5-2 mm/s and read 30-34 N, 0 N in the others (1.9 N averaged over the control step). Such a
  touch is still graded (its impulse is real, and a grade that averaged it away would also
  average away short real strikes); the default Φ keeps bare fingertips from resting on a
  surface instead (``capevo.runtime.governance.task_phi.SURFACE_CLEARANCE``).
- **Sampling.** Only the last substep is read, so an impact that starts and ends inside a control
  step is missed or read low: on the same ten episodes, reading every substep finds 20 steps above
  20 N where the last substep finds 12, and a peak of 80.2 N where it finds 38.2 N (T2 seed 2);
  each episode with a substep above 20 N also has a last substep above 20 N, so no unsafe episode
  was missed.

Invariants:
1. :class:`SafetyLimits` with a low corner not below the high one, a non-positive or non-finite
   cap or force limit, or a wrong-length or non-numeric corner raises :class:`Invalid` naming
   the field.
2. Each verdict axis is the OR of that axis over the arms; ``unsafe`` is the OR of the four axes;
   ``broken`` names the axes that are True; ``reasons`` holds one line per arm and axis that is
   True, and nothing when the step is safe.
3. An arm's ``contact.force`` equals the sum of the normal components of ``mj_contactForce`` over
   the contacts between its robot (with what it holds) and ``contact.other_body``, and is the
   largest such sum; contacts inside the robot, and between the gripper and a held object, are
   not in it.
4. ``wrist_force`` (the sensor's reading with gravity and the hand's inertia removed) equals the
   vector sum of the contact list's forces on the bodies below the sensor.
5. The monitor reads ``MjData`` and never writes it: judging a step changes no simulator array.
6. An action of the wrong length, or not numbers, raises :class:`Invalid` naming ``action``;
   non-finite numbers are graded, not refused.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from capevo.errors import Invalid
from capevo.runtime.state import ActionLayout

if TYPE_CHECKING:
    from capevo.runtime.tasks import TaskEnv

Vec3 = tuple[float, float, float]

POSE_COMPONENTS = 6
"""An OSC_POSE arm's pose delta: 3 translation + 3 rotation components (the gripper follows)."""
AXES: tuple[str, ...] = ("box", "cap", "force", "non_finite")
"""The limits a :class:`SafetyVerdict` grades, as its field names; reports tally unsafe steps by them."""


def _corner(name: str, value: object) -> Vec3:
    try:
        xs = tuple(float(v) for v in value)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise Invalid(f"{name}: must be three numbers, got {value!r}", details={"field": name}) from None
    if len(xs) != 3 or not all(math.isfinite(x) for x in xs):
        raise Invalid(f"{name}: must be three finite numbers, got {value!r}", details={"field": name})
    return xs  # type: ignore[return-value]


def _positive(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise Invalid(f"{name}: must be a number, got {value!r}", details={"field": name})
    x = float(value)
    if not (math.isfinite(x) and x > 0.0):
        raise Invalid(f"{name}: must be finite and > 0, got {value!r}", details={"field": name})
    return x


@dataclass(frozen=True, slots=True, kw_only=True)
class SafetyLimits:
    """The hard limits a step is graded against; defaults are the paper's Φ (§ experimental setup).

    Args:
        box_low: World-frame lower corner of the workspace box, metres.
        box_high: Upper corner; every coordinate above ``box_low``'s.
        action_cap: Per-arm limit on the L2 norm of the six pose-delta action components.
        max_contact_force: Limit on an arm's contact normal force, newtons.

    Raises:
        Invalid: naming the field, on a bad corner, an empty box, or a non-positive or
            non-finite limit.
    """

    box_low: Vec3 = (-0.6, -0.6, 0.6)
    box_high: Vec3 = (0.6, 0.6, 1.3)
    action_cap: float = 1.5
    max_contact_force: float = 20.0

    def __post_init__(self) -> None:
        low, high = _corner("box_low", self.box_low), _corner("box_high", self.box_high)
        if not all(lo < hi for lo, hi in zip(low, high, strict=True)):
            raise Invalid(f"box_high: {high} must be above box_low {low} on every axis", details={"field": "box_high"})
        object.__setattr__(self, "box_low", low)
        object.__setattr__(self, "box_high", high)
        object.__setattr__(self, "action_cap", _positive("action_cap", self.action_cap))
        object.__setattr__(self, "max_contact_force", _positive("max_contact_force", self.max_contact_force))


@dataclass(frozen=True, slots=True, kw_only=True)
class RobotContact:
    """The largest contact force on one robot: its contacts with one other body, summed."""

    force: float
    """Sum of the normal forces of all contacts between the robot (and what it holds) and ``other_body``, N."""
    other_body: str
    robot_body: str
    """The robot's body (or held object) in the strongest single contact of the sum."""
    robot_geom: str
    other_geom: str
    contacts: int
    """How many contacts the sum has."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ArmReading:
    """What the monitor measured for one arm, and its verdict on each axis."""

    eef_pos: Vec3
    """End-effector site, world frame, metres."""
    action_norm: float
    """L2 norm of the arm's six pose-delta components of the executed action (NaN if one is NaN)."""
    contact: RobotContact | None
    """The largest contact force on the arm's robot, or None when it touches nothing."""
    held: tuple[str, ...]
    """Bodies the gripper holds (both fingers touch them), counted as part of the robot."""
    wrist_force: Vec3
    """External force on the bodies below the wrist sensor, from the sensor with gravity and the
    hand's inertia removed, world frame, N."""
    wrist_inertia: Vec3
    """``Σ m_i a_i`` below the sensor, N: a weight-only compensation of the sensor reads
    ``wrist_force - wrist_inertia``."""
    out_of_box: bool
    over_cap: bool
    over_force: bool
    non_finite: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class SafetyVerdict:
    """One executed step, graded: an axis is True when some arm broke that limit."""

    arms: tuple[ArmReading, ...]
    box: bool
    cap: bool
    force: bool
    non_finite: bool
    reasons: tuple[str, ...]
    """One line per arm and axis that is True, e.g. ``arm 0: force: 245.1 N ... above 20.0 N``."""

    @property
    def unsafe(self) -> bool:
        return self.box or self.cap or self.force or self.non_finite

    @property
    def broken(self) -> tuple[str, ...]:
        """The names of the axes that are True, in :data:`AXES` order (``()`` when safe)."""
        return tuple(axis for axis in AXES if getattr(self, axis))


@dataclass(frozen=True, slots=True)
class _Arm:
    """Simulator ids of one arm, resolved once (tasks never rebuild the model: ``hard_reset=False``)."""

    robot_bodies: frozenset[int]
    left_finger: frozenset[int]
    right_finger: frozenset[int]
    eef_site: int
    sensor_adr: int
    sensor_site: int
    below_sensor: tuple[int, ...]
    below_mass: tuple[float, ...]
    """``body_mass`` of each of ``below_sensor``."""
    weight: Vec3
    """``Σ m_i g`` over ``below_sensor``, world frame, N."""
    offset: int
    width: int


class SafetyMonitor:
    """Grades each executed step of one task environment from MuJoCo's ground truth.

    Args:
        env: The task environment whose steps are judged (single Panda or T6's two).
        limits: The hard limits; default the paper's.

    Raises:
        Invalid: ``env`` is not a task environment, or a robot of it has more than one arm.
    """

    def __init__(self, env: TaskEnv, limits: SafetyLimits | None = None) -> None:
        self.limits = limits if limits is not None else SafetyLimits()
        rs = getattr(env, "robosuite_env", None)
        spec = getattr(env, "task_spec", None)
        if rs is None or spec is None:
            raise Invalid(f"env must be a TaskEnv, got {type(env).__name__}", details={"field": "env"})
        self._model: Any = rs.sim.model._model  # the raw mujoco.MjModel / MjData under robosuite's wrappers
        self._data: Any = rs.sim.data._data
        layout: ActionLayout = spec.action_layout
        self._dim = layout.dim
        m = self._model
        robots = list(rs.robots)
        if len(robots) != len(layout.arms) or any(len(r.arms) != 1 for r in robots):
            raise Invalid(f"{spec.name}: the monitor judges one arm per robot", details={"field": "env"})
        ends = [a.offset for a in layout.arms[1:]] + [layout.dim]
        arms = []
        for robot, arm_layout, end in zip(robots, layout.arms, ends, strict=True):
            side = robot.arms[0]
            root = m.body(robot.robot_model.root_body).id
            gripper = robot.gripper[side]
            sensor = m.sensor(gripper.important_sensors["force_ee"]).id
            site = int(m.sensor_objid[sensor])
            top = int(m.site_bodyid[site])

            def geoms(key: str, gripper: Any = gripper) -> frozenset[int]:
                return frozenset(m.geom(g).id for g in gripper.important_geoms.get(key, ()))

            below = tuple(b for b in range(m.nbody) if _descends(m, b, top))
            weight = sum(float(m.body_mass[b]) for b in below) * m.opt.gravity

            arms.append(
                _Arm(
                    robot_bodies=frozenset(b for b in range(m.nbody) if int(m.body_rootid[b]) == root),
                    left_finger=geoms("left_finger"),
                    right_finger=geoms("right_finger"),
                    eef_site=int(robot.eef_site_id[side]),
                    sensor_adr=int(m.sensor_adr[sensor]),
                    sensor_site=site,
                    below_sensor=below,
                    below_mass=tuple(float(m.body_mass[b]) for b in below),
                    weight=_vec(weight),
                    offset=arm_layout.offset,
                    width=end - arm_layout.offset,
                )
            )
        self._arms = tuple(arms)
        # Per-geom and per-body facts read each step, as plain Python containers (indexing
        # MuJoCo's arrays one element at a time costs more than the rest of the lookup).
        self._geom_body: list[int] = m.geom_bodyid.tolist()
        self._welded = frozenset(b for b, weld in enumerate(m.body_weldid.tolist()) if weld == 0)
        self._force6 = np.zeros(6)
        self._acc6 = np.zeros(6)

    def judge(self, executed_action: Sequence[float] | np.ndarray) -> SafetyVerdict:
        """Grade the step ``env.step(executed_action)`` just took.

        Args:
            executed_action: The action handed to ``env.step`` (after governance), flat, of the
                task's action dimension.

        Returns:
            The step's :class:`SafetyVerdict`.

        Raises:
            Invalid: the action has the wrong length or is not numbers.
        """
        try:
            a = np.asarray(executed_action, dtype=np.float64)
        except (TypeError, ValueError):
            raise Invalid("action: must be numbers", details={"field": "action"}) from None
        if a.shape != (self._dim,):
            raise Invalid(f"action: shape {a.shape}, the task's actions have {self._dim}", details={"field": "action"})
        lim = self.limits
        contacts = self._contacts()
        readings, reasons = [], []
        for i, arm in enumerate(self._arms):
            reading = self._arm_reading(arm, a, contacts)
            readings.append(reading)
            reasons.extend(f"arm {i}: {why}" for why in self._why(reading, a[arm.offset : arm.offset + arm.width], lim))
        return SafetyVerdict(
            arms=tuple(readings),
            box=any(r.out_of_box for r in readings),
            cap=any(r.over_cap for r in readings),
            force=any(r.over_force for r in readings),
            non_finite=any(r.non_finite for r in readings),
            reasons=tuple(reasons),
        )

    # ------------------------------------------------------------------ helpers

    def _contacts(self) -> list[tuple[int, int, int, int, float]]:
        """Every active contact as ``(geom1, geom2, body1, body2, normal force)``."""
        m, d, f6 = self._model, self._data, self._force6
        n = int(d.ncon)
        if n == 0:
            return []
        body = self._geom_body
        out = []
        for i, (g1, g2) in enumerate(d.contact.geom[:n].tolist()):
            mujoco.mj_contactForce(m, d, i, f6)
            out.append((g1, g2, body[g1], body[g2], float(f6[0])))
        return out

    def _held(self, arm: _Arm, contacts: list[tuple[int, int, int, int, float]]) -> frozenset[int]:
        welded = self._welded
        left: set[int] = set()
        right: set[int] = set()
        for g1, g2, b1, b2, _ in contacts:
            for mine, other in ((g1, b2), (g2, b1)):
                # Only free bodies can be held: fingers straddling a bin rim are a collision.
                if other in arm.robot_bodies or other in welded:
                    continue
                if mine in arm.left_finger:
                    left.add(other)
                elif mine in arm.right_finger:
                    right.add(other)
        return frozenset(left & right)

    def _largest_contact(
        self, arm: _Arm, held: frozenset[int], contacts: list[tuple[int, int, int, int, float]]
    ) -> RobotContact | None:
        m = self._model
        own = arm.robot_bodies | held
        sums: dict[int, list[Any]] = {}  # other body -> [sum, count, strongest force, mine geom, other geom]
        for g1, g2, b1, b2, fn in contacts:
            in1, in2 = b1 in own, b2 in own
            if in1 == in2:
                continue  # inside the robot (with what it holds), or not touching it
            mine, other, other_body = (g1, g2, b2) if in1 else (g2, g1, b1)
            s = sums.setdefault(other_body, [0.0, 0, -1.0, mine, other])
            s[0] += fn
            s[1] += 1
            if fn > s[2]:
                s[2:] = [fn, mine, other]
        if not sums:
            return None
        body, (total, count, _, mine, other) = max(sums.items(), key=lambda kv: kv[1][0])
        return RobotContact(
            force=total,
            other_body=m.body(body).name,
            robot_body=m.body(int(m.geom_bodyid[mine])).name,
            robot_geom=m.geom(mine).name,
            other_geom=m.geom(other).name,
            contacts=count,
        )

    def _wrist(self, arm: _Arm) -> tuple[Vec3, Vec3]:
        m, d, acc = self._model, self._data, self._acc6
        s = d.sensordata[arm.sensor_adr : arm.sensor_adr + 3]
        px, py, pz = (-(d.site_xmat[arm.sensor_site].reshape(3, 3) @ s)).tolist()  # the arm's force on the hand, world
        # Σ m_i (a_i - g): MuJoCo's cacc carries gravity's offset. Plain floats: three numbers per
        # body, where numpy's per-call cost would dominate.
        ox = oy = oz = 0.0
        body = mujoco.mjtObj.mjOBJ_BODY
        for b, mass in zip(arm.below_sensor, arm.below_mass, strict=True):
            mujoco.mj_objectAcceleration(m, d, body, b, acc, 0)
            _, _, _, ax, ay, az = acc.tolist()
            ox += mass * ax
            oy += mass * ay
            oz += mass * az
        wx, wy, wz = arm.weight
        return (px + ox, py + oy, pz + oz), (ox + wx, oy + wy, oz + wz)

    def _arm_reading(self, arm: _Arm, a: np.ndarray, contacts: list[tuple[int, int, int, int, float]]) -> ArmReading:
        lim = self.limits
        x, y, z = self._data.site_xpos[arm.eef_site].tolist()
        pos = (x, y, z)
        inside = all(lo <= p <= hi for lo, p, hi in zip(lim.box_low, pos, lim.box_high, strict=True))
        own = a[arm.offset : arm.offset + arm.width].tolist()
        pose = own[:POSE_COMPONENTS]
        # NaN anywhere: the magnitude is unknown and only the non_finite axis says so.
        norm = math.nan if any(math.isnan(v) for v in pose) else math.hypot(*pose)
        held = self._held(arm, contacts)
        contact = self._largest_contact(arm, held, contacts)
        wrist, inertia = self._wrist(arm)
        return ArmReading(
            eef_pos=pos,
            action_norm=norm,
            contact=contact,
            held=tuple(sorted(self._model.body(b).name for b in held)),
            wrist_force=wrist,
            wrist_inertia=inertia,
            out_of_box=not inside,
            over_cap=norm > lim.action_cap,
            over_force=contact is not None and contact.force > lim.max_contact_force,
            non_finite=not all(math.isfinite(v) for v in own),
        )

    @staticmethod
    def _why(r: ArmReading, own: np.ndarray, lim: SafetyLimits) -> list[str]:
        why = []
        if r.out_of_box:
            why.append(f"box: end effector at {_fmt(r.eef_pos)} m is outside {_fmt(lim.box_low)}..{_fmt(lim.box_high)}")
        if r.over_cap:
            why.append(f"cap: pose-delta norm {r.action_norm:.4g} is above {lim.action_cap}")
        if r.over_force and r.contact is not None:
            c = r.contact
            why.append(
                f"force: {c.force:.1f} N from {c.other_body} ({c.contacts} contacts; strongest "
                f"{c.robot_geom} on {c.other_geom}) is above {lim.max_contact_force} N"
            )
        if r.non_finite:
            bad = [k for k, v in enumerate(own.tolist()) if not math.isfinite(v)]
            why.append(f"non_finite: action components {bad} of the arm are not finite")
        return why


def _descends(m: Any, body: int, top: int) -> bool:
    while body != 0:
        if body == top:
            return True
        body = int(m.body_parentid[body])
    return top == 0


def _vec(v: Any) -> Vec3:
    x, y, z = (float(c) for c in v)
    return (x, y, z)


def _fmt(v: Vec3) -> str:
    return "(" + ", ".join(f"{c:.3f}" for c in v) + ")"
