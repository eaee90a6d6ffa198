"""Per-task Φ: the paper's envelope plus what is known about each task's scene.

The paper's Φ (``Phi.default()``: workspace box, contact-force limit, velocity cap) is the base
and stays unchanged. :func:`task_constraints` are what
:func:`~capevo.runtime.governance.phi.phi_for_task` (``Phi.for_task``) adds, before the cap:

* ``keep_clear`` (:data:`KEEP_CLEAR`): a wrist link within 3 mm of anything, or the hand within
  3 mm of the fixed scene, steered slowly away (the proximity pairs below). It is first: it adds
  motion, and every rule after it still holds on what it leaves;
* ``stopping_distance`` (:data:`STOPPING`), second, for the same reason, on single-arm tasks: a
  hand or wrist link that the joints' measured motion carries towards the fixed scene faster than
  it could stop is pushed back, whatever the action asked (a zero OSC action damps the arm, it does
  not hold it). Not on T6: there its push let an oscillating adversary's two wrists meet at 118 N
  (``bench_governance_rates.py``, seed 49), which without it they do not, and T6's learned-policy
  strikes are arm against arm, which the rule does not read;
* ``closing_grip`` (:data:`CLOSING_GRIP`): while a gripper closes on a movable object between its
  fingers, the hand moves slowly (it is not held yet, so nothing else senses what is under it);
* ``workspace_guard`` on the same box: a braking band inside the margin, an inward push when
  an end effector is outside or within 1 cm of a face, and no turning within the margin;
* ``force_ramp`` just under the same force limit (:data:`FORCE_MARGIN`): into-contact motion
  slowed from half the limit, a slow back-off above it, and motion into a contact that went
  above it held until the hand has backed off (:data:`FORCE_RELEASE`);
* ``contact_approach`` (:data:`CONTACT_APPROACH`): motion slowed along every pair of nearest
  points between a hand (with what it touches) and the rest of the scene, which the task's
  ``robot_state()`` measures on the live simulator each step
  (:class:`~capevo.runtime.governance.proximity.ProximitySensor`): the only rule that knows
  where the movable objects are; a state without those pairs leaves it idle. The sensed part of
  each arm includes its wrist links (5-7; 3-7 on T6, whose arms work face to face), whose pairs
  are braked by how the action moves those links (:mod:`~capevo.runtime.governance.link_motion`);
* ``surface_approach`` at the task's table top (or bin floor), when there is one;
* ``obstacle_approach`` for fixed obstacles (bin walls, pegs, the robots' mounts, whose tops
  at 0.942 m stand above the tables);
* ``arm_separation`` between the hands (and what they hold) of a multi-arm task;
* ``reach_limit`` around each arm's shoulder: the Panda's reach (with a slow creep left up to
  its edge) and a column around its base wide enough to keep the elbow off its joint limit.

The per-task Φ is the runtime's default (:mod:`capevo.runtime.envelope`); the paper's Φ alone
stays selectable (``--phi paper``) to reproduce the paper's table.
The scripted pick, place and stack references (``capevo.runtime.tasks.scripted``) succeed under
it about as often as under the paper's Φ, with no unsafe step (measured by
``python -m capevo.runtime.tasks.bench --phi paper task``).

The scene numbers are robosuite's defaults for the environments capevo builds (checked against
the live simulators in the slow tests). The result is an ordinary Φ: fixed for the run, its
hash differs per task and goes into every trace like any other.

Tasks are known here by name only (:data:`TASK_GEOMETRY`): the task ids (``"T1"``) belong to
:mod:`capevo.runtime.tasks`, which sits above governance, so a caller holding an id passes the
task's spec (``capevo.runtime.tasks.task_spec("T1")``) or its environment instead.

Invariants:
1. :func:`task_constraints` depends only on the geometry and the base's constraints.
2. :func:`task_name_of` accepts a task name, a ``TaskSpec`` or a ``TaskEnv`` of a task in
   :data:`TASK_GEOMETRY`; anything else raises :class:`Invalid` listing the known names.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from capevo.errors import Invalid
from capevo.runtime.governance.base import Constraint
from capevo.runtime.governance.box import WorkspaceBox
from capevo.runtime.governance.closing_grip import ClosingGrip
from capevo.runtime.governance.contact_approach import ContactApproach
from capevo.runtime.governance.force import ContactForce
from capevo.runtime.governance.guard import WorkspaceGuard
from capevo.runtime.governance.keep_clear import KeepClear
from capevo.runtime.governance.obstacle import ObstacleApproach
from capevo.runtime.governance.ramp import ForceRamp
from capevo.runtime.governance.reach import ReachLimit
from capevo.runtime.governance.separation import ArmSeparation
from capevo.runtime.governance.stopping import StoppingDistance
from capevo.runtime.governance.surface import SurfaceApproach
from capevo.runtime.governance.zone import Aabb

Vec3 = tuple[float, float, float]

PANDA_SHOULDER = 0.333
"""Height of the Panda's shoulder (joint 2 axis) above its base, metres."""
PANDA_REACH = 0.808
"""Wrist distance from the shoulder beyond which the Panda is steered back, metres. Measured in
the PickPlace scene with the gripper down: driven towards the far goal quadrant the wrist stops
at 0.806 (the elbow still bent), and the place reference lowers the can there at 0.795-0.807;
driven straight along +x the elbow straightens at about 0.80 and a further push makes the hand
fall onto the bin (a constant full +x push under this Φ: contained with R = 0.808 and a 0.05
creep, max 10 N; 6 unsafe steps, 245 N, with R = 0.81; 6, 206 N, with a 0.15 creep at 0.805;
8, 1.3 kN, with a 0.25 creep at 0.82). With margin 0.01 and brake 0.05, outward motion slows
from 0.748 and from 0.7955 on is the creep alone."""
PANDA_SITE_REACH = 0.8
"""The reach for arms whose limited point is the grip site itself (a held peg or plate,
:attr:`TaskGeometry.hands`): :data:`PANDA_REACH` was measured for the wrist of a Panda with its
gripper down, so these keep their earlier limit."""
PANDA_CREEP = 0.05
"""Outward speed (action units; the radial part of the motion, see ``reach_limit``) left up to
the reach: what a stretched arm survives being pushed at (see :data:`PANDA_REACH`). Lowering a
can at full stretch is mostly motion along the reach sphere, which ``reach_limit`` leaves alone,
so the place reference still lowers it at a few millimetres per step."""
PANDA_WRIST = (0.0, 0.0, -0.2)
"""The Panda's wrist in its grip-site frame: 0.2 m back from the fingertips towards the flange."""
PANDA_COLUMN = 0.3
"""Radius around the base axis that the hand must stay out of, metres: the Panda's own base and lower
links, and the folded elbow (driven closer, joint 4 hits its limit and the jolt reads 35 N at the hand)."""
PANDA_HAND: tuple[Aabb, ...] = (
    Aabb(low=(-0.102, -0.032, -0.124), high=(0.106, 0.032, -0.026)),
    Aabb(low=(-0.05, -0.011, -0.049), high=(0.05, 0.011, 0.012)),
)
"""The robosuite Panda gripper's collision geometry in its grip-site frame (+z out through the
fingertips, +x along the fingers' travel): the hand body, and both fingers fully open.
Measured from the model's geom bounding boxes."""
CONTACT_APPROACH: Mapping[str, float] = MappingProxyType(
    {
        "clearance": 0.005,
        "brake": 0.1,
        "touch": 0.04,
        "touch_loose": 0.04,
        "touch_arm": 0.01,
        "touch_rotation": 0.01,
    }
)
"""``contact_approach`` settings of every per-task Φ. ``touch_arm`` and ``touch_rotation`` are a
quarter of ``touch``: a learned whole-task policy (the AM-bc baseline of ``results/cpu-small``)
found that the two arms of T6 meet with their heavy links behind the hands (29-52 N at the
translation touch speed, link 5 or 6 against the other arm or its plate) and that twisting the
peg in the plate's hole at 0.04 wedges it (45-66 N with every translation held). With both at
0.01, that policy's unsafe T6 episodes on its held-out seeds went from 3/10 to 0/10 (iteration 3)
and from 3/10 to 1/10 (iteration 1; the one step left read 21.3 N, link 5 on link 5)."""
CLOSING_GRIP: Mapping[str, float] = MappingProxyType({"within": 0.01, "speed": 0.05})
"""``closing_grip`` settings of every per-task Φ (hand-written; the measurement that calls for the
rule is in :mod:`capevo.runtime.governance.closing_grip`): while a gripper closes on a movable
object between its fingers, the hand's translation is at most 0.05 (2.5 mm per step)."""
KEEP_CLEAR: Mapping[str, float] = MappingProxyType({"within": 0.003, "restore": 0.1})
"""``keep_clear`` settings of every per-task Φ (hand-written; the measurements that call for the
rule and for these values are in :mod:`capevo.runtime.governance.keep_clear`): a wrist link, or
the hand near the fixed scene, is steered away within 3 mm (inside ``contact_approach``'s 5 mm
clearance) at up to 0.1, about 5 mm per step at contact."""
STOPPING: Mapping[str, float] = MappingProxyType({"decel": 0.2, "clearance": 0.003, "gain": 3.0, "touch": 0.04})
"""``stopping_distance`` settings of the single-arm tasks' Φ (hand-written; the measurements that call for
the rule and for these values are in :mod:`capevo.runtime.governance.stopping`): a hand or wrist
link closing on the fixed scene faster than it could stop at 0.2 m/s² before 3 mm (and faster than
``contact_approach``'s touch speed, 0.04 action units a step = 0.04 m/s) is pushed back at 3 action
units per m/s of the excess."""
FORCE_MARGIN = 2.0
"""Newtons below the paper's 20 N at which ``force_ramp`` ends its ramp and starts backing off.
Governance reads the wrist sensor with the hand's weight removed but not its acceleration
(:mod:`capevo.runtime.governance.robosuite_state`); measured on a grasp, that term read 20.01 N
against a true 19.57 N (MuJoCo's contact forces). 2 N, four times that error, keeps a reading of
18 N below the true 20 N; the independent safety monitor grades against the 20 N itself."""
FORCE_RELEASE = 0.02
"""Hysteresis of ``force_ramp``: after a force above its limit, motion into that contact is held
until the hand has backed off 2 cm (a re-approach at touch speed then starts from clear of it)."""
SURFACE_CLEARANCE = 0.0
"""The fingertips stop at the surface, not in it. A clearance of -0.004 let them settle 4 mm
"into" it with a gentle OSC push (about 10 N on average), but a hand dragged along the surface
there (``lateral`` 0.2) chatters: measured on the AM-bc baseline's T1 policy
(``results/cpu-small``, seed 2000042000), a fingertip sliding on the bin floor touched it in one
2 ms substep of every ~17, at 30-34 N each time (1.9 N averaged over the control step), and the
last substep of 5 of 10 held-out episodes caught such a touch. At 0.0 the same policy's episodes
have none (0/10), and the scripted references keep their success (``capevo.runtime.tasks.bench
--phi task``)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class TaskGeometry:
    """What governance needs to know about a task's scene, world frame, metres."""

    surface_height: float | None
    """Top of the surface objects rest on (table top, bin floor); None when there is none."""
    arm_bases: tuple[Vec3, ...]
    """Each arm's base (robot root body) position, in action-layout order."""
    obstacles: tuple[Aabb, ...] = ()
    """Fixed obstacles (bin walls, pegs, robot pedestals) as world-frame boxes."""
    hands: tuple[tuple[Aabb, ...], ...] = ()
    """Per arm, boxes covering its hand and anything it holds, in the end-effector site frame;
    empty means the Panda gripper (:data:`PANDA_HAND`) for every arm."""

    def hand(self, arm: int) -> tuple[Aabb, ...]:
        return self.hands[arm] if self.hands else PANDA_HAND

    @property
    def shoulders(self) -> tuple[Vec3, ...]:
        return tuple((x, y, z + PANDA_SHOULDER) for x, y, z in self.arm_bases)


def _box(low: Vec3, high: Vec3) -> Aabb:
    return Aabb(low=low, high=high)


_BIN_WALLS = (
    # bin1 (source), centred at (0.1, -0.25): four walls 0.1 m high on a floor whose top is at 0.82.
    _box((-0.11, -0.01, 0.8), (0.31, 0.01, 0.9)),
    _box((-0.11, -0.51, 0.8), (0.31, -0.49, 0.9)),
    _box((0.29, -0.5, 0.8), (0.31, 0.0, 0.9)),
    _box((-0.11, -0.5, 0.8), (-0.09, 0.0, 0.9)),
    # bin2 (goal), centred at (0.1, 0.28): four walls and two dividers making the quadrants.
    _box((-0.11, 0.52, 0.8), (0.31, 0.54, 0.9)),
    _box((-0.11, 0.02, 0.8), (0.31, 0.04, 0.9)),
    _box((0.29, 0.03, 0.8), (0.31, 0.53, 0.9)),
    _box((-0.11, 0.03, 0.8), (-0.09, 0.53, 0.9)),
    _box((-0.1, 0.27, 0.8), (0.3, 0.29, 0.9)),
    _box((0.09, 0.03, 0.8), (0.11, 0.53, 0.9)),
)


def _pedestal(base: Vec3) -> Aabb:
    """A single Panda's mount: a cylinder of radius 0.18 centred 2 cm behind the base, up to z 0.942."""
    x, y, _ = base
    return Aabb(low=(x - 0.2, y - 0.18, 0.322), high=(x + 0.16, y + 0.18, 0.942))


_BINS = TaskGeometry(
    surface_height=0.82, arm_bases=((-0.5, -0.1, 0.912),), obstacles=(*_BIN_WALLS, _pedestal((-0.5, -0.1, 0.912)))
)
"""robosuite PickPlace: bin floors 0.02 thick on bodies at z 0.8; Panda mounted at (-0.5, -0.1)."""
_PEDESTALS = (
    # Each robot's mount: a cylinder of radius 0.18 up to z 0.942 under the base, and the Panda's
    # own base and first link (about 0.1 around the base axis, up to the shoulder).
    _box((-0.18, -0.8, 0.322), (0.18, -0.44, 0.942)),
    _box((-0.18, 0.44, 0.322), (0.18, 0.8, 0.942)),
    _box((-0.11, -0.71, 0.9), (0.11, -0.49, 1.3)),
    _box((-0.11, 0.49, 0.9), (0.11, 0.71, 1.3)),
)
_PEG_HAND = (Aabb(low=(-0.03, -0.03, 0.0), high=(0.03, 0.03, 0.26)),)
"""Robot 0 of TwoArmPegInHole: the peg, 0.26 m long along the site's +z, as thick as the largest radius
an episode draws (``PEG_RADIUS_RANGE``, 3 cm)."""
_PLATE_HAND = (Aabb(low=(-0.01, -0.17, 0.0), high=(0.01, 0.17, 0.34)),)
"""Robot 1 of TwoArmPegInHole: the plate with the hole, 0.34 x 0.34 m, 2 cm thick."""
_PEGS = (
    _box((0.214, 0.084, 0.75), (0.246, 0.116, 0.95)),  # square peg, 0.032 m square
    _box((0.21, -0.12, 0.75), (0.25, -0.08, 0.95)),  # round peg, radius 0.02
)

TASK_GEOMETRY: Mapping[str, TaskGeometry] = MappingProxyType(
    {
        "pick": _BINS,
        "place": _BINS,
        "stack": TaskGeometry(
            surface_height=0.8, arm_bases=((-0.56, 0.0, 0.912),), obstacles=(_pedestal((-0.56, 0.0, 0.912)),)
        ),
        "nut_assembly": TaskGeometry(
            surface_height=0.82,
            arm_bases=((-0.56, 0.0, 0.912),),
            obstacles=(*_PEGS, _pedestal((-0.56, 0.0, 0.912))),
        ),
        "pick_place_multi": _BINS,
        # TwoArmPegInHole, "opposed": no table; the Pandas face each other across y.
        "peg_in_hole": TaskGeometry(
            surface_height=None,
            arm_bases=((0.0, -0.6, 0.912), (0.0, 0.6, 0.912)),
            obstacles=_PEDESTALS,
            hands=(_PEG_HAND, _PLATE_HAND),
        ),
    }
)
"""Scene geometry of the built-in tasks, by task name."""


def task_name_of(task: Any) -> str:
    """The task name for a name, a ``TaskSpec`` or anything with a ``task_spec`` (a ``TaskEnv``).

    Raises:
        Invalid: if no geometry is known for the task; the message lists the known names.
    """
    spec = getattr(task, "task_spec", task)
    name = getattr(spec, "name", spec)
    if not isinstance(name, str) or name not in TASK_GEOMETRY:
        raise Invalid(
            f"task: no scene geometry for {name!r}; known tasks: {', '.join(TASK_GEOMETRY)} "
            f"(for a task id, pass its spec: capevo.runtime.tasks.task_spec(id))",
            details={"field": "task", "valid": list(TASK_GEOMETRY)},
        )
    return name


def task_constraints(geometry: TaskGeometry, base: Sequence[Constraint]) -> list[Constraint]:
    """The constraints a per-task Φ adds to the constraints ``base`` for a scene.

    The guard and the force ramp take their box and force limit from ``base``'s
    ``workspace_box`` and ``contact_force`` (their defaults when it has none).
    """
    box = next((c for c in base if isinstance(c, WorkspaceBox)), WorkspaceBox())
    force = next((c for c in base if isinstance(c, ContactForce)), ContactForce())
    added: list[Constraint] = [
        # First: it adds motion, and every rule after it still holds on what it leaves.
        KeepClear(**KEEP_CLEAR),
        # One arm only: its push can carry one arm towards another, which it does not read.
        *([StoppingDistance(**STOPPING)] if len(geometry.arm_bases) == 1 else []),
        ClosingGrip(**CLOSING_GRIP),
        WorkspaceGuard(low=box.low, high=box.high, margin=box.margin),
        ForceRamp(
            max_force=force.max_force - FORCE_MARGIN,
            soft_from=force.max_force / 2,
            release=FORCE_RELEASE,
        ),
        ContactApproach(**CONTACT_APPROACH),
    ]
    if geometry.surface_height is not None:
        added.append(
            SurfaceApproach(
                height=geometry.surface_height, clearance=SURFACE_CLEARANCE, hand=geometry.hand(0), lateral=0.2
            )
        )
    if geometry.obstacles:
        n = len(geometry.arm_bases)
        if all(geometry.hand(i) == geometry.hand(0) for i in range(n)):
            added.append(ObstacleApproach(boxes=geometry.obstacles, hand=geometry.hand(0)))
        else:  # arms holding different things: one rule per arm, each with its own hand
            added.extend(
                ObstacleApproach(
                    boxes=geometry.obstacles, hand=geometry.hand(i), arm=i, name=f"obstacle_approach.arm{i}"
                )
                for i in range(n)
            )
    if len(geometry.arm_bases) > 1:
        added.append(ArmSeparation(hands=tuple(geometry.hand(i) for i in range(len(geometry.arm_bases)))))
    added.append(
        ReachLimit(
            centres=geometry.shoulders,
            max_radius=PANDA_REACH if not geometry.hands else PANDA_SITE_REACH,
            min_radius=PANDA_COLUMN,
            margin=0.01,
            brake=0.05,
            creep=PANDA_CREEP,
            point=PANDA_WRIST if not geometry.hands else (0.0, 0.0, 0.0),
        )
    )
    return added
