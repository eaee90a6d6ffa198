"""The work TaskEnv switches off in robosuite's step changes nothing an episode shows.

Each test runs real robosuite episodes twice on one environment, once as TaskEnv runs it
(lean) and once with robosuite's methods as shipped (stock), and compares digests of
everything the episode exposes, plus the raw simulator state.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from golden_support import Digest, task_episode_digest

from capevo.runtime.tasks import TaskEnv, lean_stepping, make_task

pytestmark = pytest.mark.slow

STEPS = 25


def _episode(env: TaskEnv, seed: int) -> tuple[str, str]:
    """The TaskEnv digest and a digest of the raw MuJoCo state and controller after it."""
    digest = task_episode_digest(env, seed, STEPS)
    sim = Digest()
    data = env.robosuite_env.sim.data._data
    for field in ("qpos", "qvel", "act", "ctrl", "qfrc_actuator", "sensordata"):
        sim.add(np.array(getattr(data, field)))
    return digest, sim.hexdigest()


@pytest.mark.parametrize("task", ["T1", "T3", "T6"])
def test_lean_and_stock_robosuite_give_the_same_episode(quiet: None, task: str) -> None:
    env = make_task(task, horizon=STEPS)
    try:
        rs = env.robosuite_env
        overrides = env.robosuite_overrides
        lean = [_episode(env, seed) for seed in (0, 3)]
        lean_stepping.remove(rs, overrides)
        assert not set(overrides) & set(vars(rs)), "remove() left an override behind"
        stock = [_episode(env, seed) for seed in (0, 3)]
        lean_stepping.install(rs, overrides)
        again = [_episode(env, seed) for seed in (0, 3)]
    finally:
        env.close()
    assert lean == stock
    assert again == lean


def test_reward_is_skipped_only_where_the_task_has_its_own(quiet: None) -> None:
    pick, place = make_task("T1", horizon=5), make_task("T2", horizon=5)
    try:
        assert "reward" in pick.robosuite_overrides
        assert "reward" not in place.robosuite_overrides
        assert {"_update_observables", "_pre_action"} <= set(place.robosuite_overrides)
        # T2's reward is robosuite's staged reward, so it must still move with the state.
        place.reset(seed=0)
        rewards = {place.step(np.full(7, 0.5))[1] for _ in range(5)}
        assert len(rewards) > 1
    finally:
        pick.close()
        place.close()


def test_cached_pre_action_refuses_a_wrong_action_size(quiet: None) -> None:
    env = make_task("T6", horizon=5)
    try:
        pre_action = env.robosuite_overrides["_pre_action"]
        with pytest.raises(AssertionError, match="expected 12, got 7"):
            pre_action(np.zeros(7), policy_step=True)
    finally:
        env.close()


def test_an_environment_with_its_own_pre_action_keeps_it() -> None:
    from robosuite.environments.robot_env import RobotEnv

    class Custom(RobotEnv):  # never instantiated: only its method table matters
        def _pre_action(self, action: Any, policy_step: bool = False) -> None:
            raise NotImplementedError

    fake = object.__new__(Custom)
    overrides = lean_stepping.lean_overrides(fake, reads_reward=True)
    assert "_pre_action" not in overrides
    assert set(overrides) == {"_update_observables"}
