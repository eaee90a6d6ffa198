"""The work TaskEnv switches off in robosuite's step changes nothing an episode shows.

A differential test: for every task, two environments are built in this process, one as TaskEnv
runs it (lean stepping, :mod:`capevo.runtime.tasks.lean_stepping`) and one with robosuite's methods
as shipped (stock). They are reset with the same seeds and stepped side by side with the same
actions, and after every step everything the episode exposes (observations, clean observations,
reward, flags, info, signals, the arms' state) and the raw simulator state must be equal bit for
bit. It runs, and can fail, on any machine: no recorded digests.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from capevo.runtime.tasks import TaskEnv, lean_stepping, make_task, task_ids

pytestmark = pytest.mark.slow

STEPS = 25
SEEDS = (0, 3)
SIM_FIELDS = ("qpos", "qvel", "act", "ctrl", "qfrc_actuator", "sensordata")


def _assert_same(lean: Any, stock: Any, where: str) -> None:
    """``lean`` and ``stock`` equal bit for bit (arrays by dtype, shape and bytes)."""
    if isinstance(lean, np.ndarray) or isinstance(stock, np.ndarray):
        lean, stock = np.asarray(lean), np.asarray(stock)
        assert (lean.dtype, lean.shape) == (stock.dtype, stock.shape), where
        assert lean.tobytes() == stock.tobytes(), f"{where}: lean {lean!r} != stock {stock!r}"
    elif isinstance(lean, dict):
        assert isinstance(stock, dict) and sorted(lean) == sorted(stock), where
        for key in lean:
            _assert_same(lean[key], stock[key], f"{where}.{key}")
    elif isinstance(lean, (tuple, list)):
        assert type(lean) is type(stock) and len(lean) == len(stock), where
        for i, (a, b) in enumerate(zip(lean, stock, strict=True)):
            _assert_same(a, b, f"{where}[{i}]")
    else:
        assert type(lean) is type(stock) and repr(lean) == repr(stock), f"{where}: {lean!r} != {stock!r}"


def _snapshot(env: TaskEnv) -> dict[str, Any]:
    data = env.robosuite_env.sim.data._data
    return {
        "obs": env.obs_dict,
        "clean_obs": env.clean_obs_dict,
        "signals": env.signals(),
        # The physical state only: governance may add derived fields to the arms' records.
        "arms": [(a.eef_pos, a.eef_force, a.eef_rot) for a in env.robot_state().arms],
        "sim": {field: np.array(getattr(data, field)) for field in SIM_FIELDS},
    }


def _side_by_side(lean: TaskEnv, stock: TaskEnv, seed: int) -> Iterator[tuple[int, Any, Any]]:
    """Reset both with ``seed`` and step both with the same seeded random actions in +-0.7;
    yields ``(step, lean values, stock values)`` after the reset and after every step."""
    rng = np.random.default_rng(1000 + seed)
    yield 0, (lean.reset(seed=seed), _snapshot(lean)), (stock.reset(seed=seed), _snapshot(stock))
    for step in range(1, STEPS + 1):
        action = rng.uniform(-0.7, 0.7, lean.action_space.shape)
        got_lean, got_stock = lean.step(action), stock.step(action.copy())
        yield step, (got_lean, _snapshot(lean)), (got_stock, _snapshot(stock))
        if got_lean[2] or got_lean[3]:
            break


@pytest.mark.parametrize("task", task_ids())
def test_lean_and_stock_robosuite_give_the_same_episode(quiet: None, task: str) -> None:
    lean, stock = make_task(task, horizon=STEPS), make_task(task, horizon=STEPS)
    try:
        assert lean.robosuite_overrides, "TaskEnv installed no override: nothing is being checked"
        lean_stepping.remove(stock.robosuite_env, stock.robosuite_overrides)
        assert not set(stock.robosuite_overrides) & set(vars(stock.robosuite_env)), "remove() left an override"
        for seed in SEEDS:
            steps = 0
            for steps, got_lean, got_stock in _side_by_side(lean, stock, seed):
                _assert_same(got_lean, got_stock, f"{task} seed {seed} step {steps}")
            assert steps > 0
    finally:
        lean.close()
        stock.close()


def test_installing_again_restores_the_lean_episode(quiet: None) -> None:
    lean, toggled = make_task("T1", horizon=STEPS), make_task("T1", horizon=STEPS)
    try:
        lean_stepping.remove(toggled.robosuite_env, toggled.robosuite_overrides)
        lean_stepping.install(toggled.robosuite_env, toggled.robosuite_overrides)
        assert set(toggled.robosuite_overrides) <= set(vars(toggled.robosuite_env))
        for steps, got_lean, got_toggled in _side_by_side(lean, toggled, 0):
            _assert_same(got_lean, got_toggled, f"T1 step {steps}")
    finally:
        lean.close()
        toggled.close()


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
