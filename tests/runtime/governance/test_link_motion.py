"""link_motion: how an OSC_POSE action moves a point on an arm, on a live robosuite Panda."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from capevo.runtime.governance.link_motion import ArmJoints, LinkMotion
from capevo.runtime.tasks import make_task


@pytest.fixture(scope="module")
def t1():
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    env = make_task("T1")
    env.reset(seed=3)
    yield env
    env.close()


def _motion(env) -> tuple[LinkMotion, ArmJoints]:
    robot = env._env.robots[0]
    joints = ArmJoints(
        site=int(robot.eef_site_id["right"]),
        dofs=tuple(robot._ref_joint_vel_indexes),
        scale=tuple(float(v) for v in robot.part_controllers["right"].output_max),
    )
    return LinkMotion(env._model, env._data, [joints]), joints


def test_a_point_on_the_hand_moves_rigidly_with_the_end_effector(t1) -> None:
    """Invariant 1: on the end-effector body the row is (n, (r x n) S_r / S_t)."""
    import mujoco

    motion, joints = _motion(t1)
    m, d = t1._model, t1._data
    hand = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "robot0_right_hand")
    site = d.site_xpos[joints.site].copy()
    rng = np.random.default_rng(0)
    for _ in range(5):
        r = rng.uniform(-0.1, 0.1, 3)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        g = np.array(motion.row(0, hand, site + r, n))
        ratio = joints.scale[3] / joints.scale[0]
        np.testing.assert_allclose(g[:3], n, atol=1e-6)
        np.testing.assert_allclose(g[3:], np.cross(r, n) * ratio, atol=1e-6)


def test_the_forearm_moves_otherwise_than_a_rigid_hand_would(t1) -> None:
    """Why links get rows of their own: under OSC a point on link 5 does not follow the hand
    rigidly. At the start pose, rolling the hand about world x swings a rigid point 19 cm above
    and behind the site towards -y, but moves the forearm towards +y."""
    import mujoco

    motion, joints = _motion(t1)
    m, d = t1._model, t1._data
    link5 = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "robot0_link5")
    point = d.xpos[link5].copy()
    site = d.site_xpos[joints.site].copy()
    n = np.array([0.0, 1.0, 0.0])
    g = np.array(motion.row(0, link5, point, n))
    rigid = np.r_[n, np.cross(point - site, n) * joints.scale[3] / joints.scale[0]]
    assert g[3] * rigid[3] < 0, (g, rigid)
    assert np.abs(g - rigid).max() > 1.0, (g, rigid)
