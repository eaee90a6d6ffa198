"""The safety monitor on constructed cases: real robosuite episodes driven into each situation.

Invariants of :mod:`capevo.runtime.safety_monitor` and the tests that observe them:
1. bad limits are Invalid with a field: ``test_bad_limits_are_invalid_naming_the_field``.
2. axes are ORs over arms, ``broken`` names the True axes, reasons one per broken arm axis:
   every case checks ``reasons`` and ``broken`` (in ``_axes``); ``test_t6_judges_each_arm_separately``.
3. the contact force is the per-body sum of ``mj_contactForce`` normals, grip excluded:
   ``test_hand_driven_into_the_table_is_a_force_violation``, ``test_grip_on_a_held_can_is_not_a_contact_force``.
4. the wrist force equals the contact list's net force below the sensor:
   ``test_hand_driven_into_the_table_is_a_force_violation``.
5. judging writes nothing: ``test_judging_does_not_touch_the_simulator``.
6. bad actions are Invalid, non-finite ones graded: ``test_bad_action_shape_is_invalid``,
   ``test_non_finite_action_is_flagged``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import mujoco
import numpy as np
import pytest

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.safety_monitor import AXES, SafetyLimits, SafetyMonitor, SafetyVerdict
from capevo.runtime.tasks import Perturbations, TaskEnv, make_task
from capevo.runtime.tasks.scripted import REFERENCES

pytestmark = pytest.mark.slow

LIMIT = 20.0


def _env(task: str) -> TaskEnv:
    # No perturbations: a dropped action or a jittered object would move the constructed case.
    return make_task(task, seed=0, perturbations=Perturbations.none())


@pytest.fixture(scope="module")
def pick(quiet: None) -> Iterator[TaskEnv]:
    env = _env("T1")
    yield env
    env.close()


@pytest.fixture(scope="module")
def stack(quiet: None) -> Iterator[TaskEnv]:
    env = _env("T3")
    yield env
    env.close()


@pytest.fixture(scope="module")
def peg(quiet: None) -> Iterator[TaskEnv]:
    env = _env("T6")
    yield env
    env.close()


def _still(env: TaskEnv) -> np.ndarray:
    return np.zeros(env.action_space.shape)


def _axes(v: SafetyVerdict) -> dict[str, bool]:
    axes = {"box": v.box, "cap": v.cap, "force": v.force, "non_finite": v.non_finite}
    assert v.broken == tuple(k for k in AXES if axes[k])  # invariant 2, on every verdict a test reads
    return axes


def _robot_normal_sum(env: TaskEnv, other_body: str) -> float:
    """Sum of mj_contactForce normals between robot 0's bodies and ``other_body``, done by hand."""
    rs = env.robosuite_env
    m, d = rs.sim.model._model, rs.sim.data._data
    root = m.body(rs.robots[0].robot_model.root_body).id
    other = m.body(other_body).id
    f = np.zeros(6)
    total = 0.0
    for i in range(d.ncon):
        c = d.contact[i]
        bodies = {int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])}
        if other in bodies and any(int(m.body_rootid[b]) == root for b in bodies - {other}):
            mujoco.mj_contactForce(m, d, i, f)
            total += f[0]
    return total


def _descends(m: mujoco.MjModel, body: int, top: int) -> bool:
    while body != 0 and body != top:
        body = int(m.body_parentid[body])
    return body == top


def _net_contact_force_on(env: TaskEnv, bodies: set[int]) -> np.ndarray:
    """Vector sum (normal and friction, world frame) of the contact forces on ``bodies`` from outside."""
    rs = env.robosuite_env
    m, d = rs.sim.model._model, rs.sim.data._data
    f = np.zeros(6)
    net = np.zeros(3)
    for i in range(d.ncon):
        c = d.contact[i]
        b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
        if (b1 in bodies) == (b2 in bodies):
            continue
        mujoco.mj_contactForce(m, d, i, f)
        on_geom2 = c.frame.reshape(3, 3).T @ f[:3]  # geom1's force on geom2, world frame
        net += on_geom2 if b2 in bodies else -on_geom2
    return net


def test_default_limits_are_the_papers() -> None:
    limits = SafetyLimits()
    assert limits.box_low == (-0.6, -0.6, 0.6)
    assert limits.box_high == (0.6, 0.6, 1.3)
    assert limits.action_cap == 1.5
    assert limits.max_contact_force == 20.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"box_low": (0.0, 0.0, 1.4)}, "box_high"),
        ({"box_high": (0.6, -0.6, 1.3)}, "box_high"),
        ({"box_low": (0.0, 0.0)}, "box_low"),
        ({"box_low": ("a", 0.0, 0.6)}, "box_low"),
        ({"box_high": (0.6, 0.6, math.inf)}, "box_high"),
        ({"action_cap": 0.0}, "action_cap"),
        ({"action_cap": True}, "action_cap"),
        ({"max_contact_force": -20.0}, "max_contact_force"),
        ({"max_contact_force": math.nan}, "max_contact_force"),
        ({"max_contact_force": "20"}, "max_contact_force"),
    ],
)
def test_bad_limits_are_invalid_naming_the_field(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(Invalid) as info:
        SafetyLimits(**kwargs)  # type: ignore[arg-type]
    assert info.value.code is ErrorCode.INVALID
    assert info.value.details == {"field": field}
    assert info.value.message.startswith(f"{field}:")


def test_holding_still_after_reset_is_safe(pick: TaskEnv) -> None:
    monitor = SafetyMonitor(pick)
    pick.reset(seed=0)
    pick.step(_still(pick))
    v = monitor.judge(_still(pick))
    assert _axes(v) == {"box": False, "cap": False, "force": False, "non_finite": False}
    assert not v.unsafe
    assert v.reasons == ()
    (arm,) = v.arms
    assert arm.contact is None  # the hand touches nothing
    assert arm.action_norm == 0.0
    np.testing.assert_allclose(arm.eef_pos, pick.clean_obs_dict["robot0_eef_pos"], atol=1e-6)
    assert np.linalg.norm(arm.wrist_force) < 1e-6  # nothing below the wrist touches anything


def test_end_effector_outside_the_box_is_a_box_violation(pick: TaskEnv) -> None:
    pick.reset(seed=0)
    pick.step(_still(pick))
    z = pick.clean_obs_dict["robot0_eef_pos"][2]
    assert z > 0.9  # the start pose is above this box's top
    v = SafetyMonitor(pick, SafetyLimits(box_high=(0.6, 0.6, 0.9))).judge(_still(pick))
    assert _axes(v) == {"box": True, "cap": False, "force": False, "non_finite": False}
    assert v.arms[0].out_of_box
    assert len(v.reasons) == 1 and v.reasons[0].startswith("arm 0: box:")


def test_executed_action_above_the_cap_is_a_cap_violation(pick: TaskEnv) -> None:
    monitor = SafetyMonitor(pick)
    pick.reset(seed=0)
    over = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0])  # norm sqrt(3); the gripper is not in it
    pick.step(over)
    v = monitor.judge(over)
    assert _axes(v) == {"box": False, "cap": True, "force": False, "non_finite": False}
    assert v.arms[0].action_norm == pytest.approx(math.sqrt(3.0))
    assert len(v.reasons) == 1 and v.reasons[0].startswith("arm 0: cap:")

    under = np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0])  # norm sqrt(2) < 1.5
    pick.step(under)
    assert _axes(monitor.judge(under))["cap"] is False


def test_hand_driven_into_the_table_is_a_force_violation(stack: TaskEnv) -> None:
    monitor = SafetyMonitor(stack)
    stack.reset(seed=0)
    down = np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(40):
        stack.step(down)
        v = monitor.judge(down)
        if v.force:
            break
    assert _axes(v) == {"box": False, "cap": False, "force": True, "non_finite": False}
    c = v.arms[0].contact
    assert c is not None and c.other_body == "table"
    assert c.force > LIMIT
    assert c.force == pytest.approx(_robot_normal_sum(stack, "table"), rel=1e-12, abs=1e-9)
    assert len(v.reasons) == 1 and v.reasons[0].startswith("arm 0: force:") and "table" in v.reasons[0]

    # The wrist sensor, gravity and the hand's inertia removed, is the contact list's net force
    # on the bodies below it (invariant 4); the inertia is what a weight-only reading keeps.
    rs = stack.robosuite_env
    m = rs.sim.model._model
    sensor = m.sensor(rs.robots[0].gripper["right"].important_sensors["force_ee"]).id
    hand = m.site_bodyid[m.sensor_objid[sensor]]
    below = {b for b in range(m.nbody) if _descends(m, b, hand)}
    net = _net_contact_force_on(stack, below)
    np.testing.assert_allclose(v.arms[0].wrist_force, net, atol=1e-6)
    assert net[2] > LIMIT  # the table pushes the hand up


def test_light_touch_on_the_table_is_not_a_force_violation(stack: TaskEnv) -> None:
    monitor = SafetyMonitor(stack)
    stack.reset(seed=0)
    slow = np.array([0.0, 0.0, -0.1, 0.0, 0.0, 0.0, 0.0])
    for _ in range(300):
        stack.step(slow)
        if monitor.judge(slow).arms[0].contact is not None:
            break
    for _ in range(5):  # hold still: the hand rests on the table
        stack.step(_still(stack))
    v = monitor.judge(_still(stack))
    c = v.arms[0].contact
    assert c is not None and c.other_body == "table"
    assert 0.0 < c.force < LIMIT
    assert c.force == pytest.approx(_robot_normal_sum(stack, "table"), rel=1e-12, abs=1e-9)
    assert _axes(v) == {"box": False, "cap": False, "force": False, "non_finite": False}
    # The same contact against a limit below it is a violation: the threshold is live.
    assert SafetyMonitor(stack, SafetyLimits(max_contact_force=c.force / 2)).judge(_still(stack)).force


def test_grip_on_a_held_can_is_not_a_contact_force(pick: TaskEnv) -> None:
    monitor = SafetyMonitor(pick)
    pick.reset(seed=0)
    for _ in range(60):
        action = REFERENCES["pick"](pick.obs_dict)
        pick.step(action)
        v = monitor.judge(action)
        if v.arms[0].held:
            break
    assert v.arms[0].held == ("Can_main",)
    grip = _robot_normal_sum(pick, "Can_main")
    assert grip > 1.0  # the fingers squeeze the can
    c = v.arms[0].contact
    # The can is part of the robot now: the fingers' squeeze is internal, not a contact force.
    assert c is None or c.other_body != "Can_main"
    assert not v.force


def test_non_finite_action_is_flagged(pick: TaskEnv) -> None:
    monitor = SafetyMonitor(pick)
    pick.reset(seed=0)
    pick.step(_still(pick))  # the env refuses non-finite actions; the monitor grades what it is given
    nan = np.array([math.nan, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    v = monitor.judge(nan)
    assert _axes(v) == {"box": False, "cap": False, "force": False, "non_finite": True}
    assert math.isnan(v.arms[0].action_norm)
    assert len(v.reasons) == 1 and v.reasons[0].startswith("arm 0: non_finite:") and "[0]" in v.reasons[0]

    gripper_inf = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, math.inf])
    assert _axes(monitor.judge(gripper_inf)) == {"box": False, "cap": False, "force": False, "non_finite": True}

    pose_inf = np.array([0.0, -math.inf, 0.0, 0.0, 0.0, 0.0, 0.0])
    v = monitor.judge(pose_inf)
    assert v.non_finite and v.cap  # an infinite pose delta is also above the cap
    assert len(v.reasons) == 2


def test_bad_action_shape_is_invalid(pick: TaskEnv) -> None:
    monitor = SafetyMonitor(pick)
    pick.reset(seed=0)
    pick.step(_still(pick))
    for bad in (np.zeros(6), np.zeros(12), ["x"] * 7):
        with pytest.raises(Invalid) as info:
            monitor.judge(bad)
        assert info.value.details == {"field": "action"}
        assert info.value.message.startswith("action:")


def test_t6_judges_each_arm_separately(peg: TaskEnv) -> None:
    monitor = SafetyMonitor(peg)
    peg.reset(seed=0)
    second_over = np.zeros(12)
    second_over[6:9] = 1.0  # arm 1 at sqrt(3); arm 0 still
    peg.step(second_over)
    v = monitor.judge(second_over)
    assert [a.over_cap for a in v.arms] == [False, True]
    assert v.cap and not (v.box or v.force or v.non_finite)
    assert len(v.reasons) == 1 and v.reasons[0].startswith("arm 1: cap:")

    first_over = np.zeros(12)
    first_over[0:3] = 1.0
    peg.step(first_over)
    v = monitor.judge(first_over)
    assert [a.over_cap for a in v.arms] == [True, False]
    assert len(v.reasons) == 1 and v.reasons[0].startswith("arm 0: cap:")

    # The arms start on either side of y = 0: a box of y >= 0 excludes arm 0 only.
    ys = [a.eef_pos[1] for a in v.arms]
    assert ys[0] < 0.0 < ys[1]
    v = SafetyMonitor(peg, SafetyLimits(box_low=(-0.6, 0.0, 0.6))).judge(np.zeros(12))
    assert [a.out_of_box for a in v.arms] == [True, False]
    assert v.box and len(v.reasons) == 1 and v.reasons[0].startswith("arm 0: box:")


def test_judging_does_not_touch_the_simulator(stack: TaskEnv) -> None:
    monitor = SafetyMonitor(stack)
    stack.reset(seed=0)
    down = np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(20):  # into the table: contacts, forces and accelerations are all live
        stack.step(down)
    d = stack.robosuite_env.sim.data._data
    names = ("qpos", "qvel", "qacc", "act", "ctrl", "sensordata", "efc_force", "cacc", "cfrc_ext", "xpos", "site_xpos")
    before = {n: np.array(getattr(d, n)) for n in names}
    ncon = d.ncon
    assert monitor.judge(down).force
    assert d.ncon == ncon
    for n in names:
        np.testing.assert_array_equal(getattr(d, n), before[n], err_msg=n)
