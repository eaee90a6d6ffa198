"""Work robosuite 1.5.2 does in every ``env.step`` that capevo never reads, switched off per environment.

robosuite's control step runs ~25 physics substeps; around them it does three things a
:class:`~capevo.runtime.tasks.TaskEnv` has no use for:

* **Per-substep observable sampling** (``_update_observables`` in every substep): those
  samples are taken early in the step and nothing reads them, because after each step
  ``TaskEnv`` recomputes every observable from the final state.
* **Recomputing each robot's action size** (``RobotEnv._pre_action`` asks
  ``robot.action_dim`` twice per robot per substep, and each ask concatenates the
  controllers' action limits): the sizes are fixed once the controllers are built, and
  ``TaskEnv`` runs with ``hard_reset=False``, so they never change for the environment's life.
* **robosuite's own reward** (``_post_action`` calls ``reward()`` every step): a task
  whose reward is its own (``TaskEnv.reads_robosuite_reward = False``) discards it.

Each is an *instance* attribute shadowing robosuite's method, so nothing outside the
wrapped environment changes, and :func:`remove` puts robosuite back exactly as shipped
(``benchmarks/bench_worker.py`` does, to time stock robosuite on the same environment).

Invariants:
1. With the overrides installed, every simulator state, observation, reward and info that
   ``TaskEnv`` produces is bit for bit what it produces without them (a differential test,
   ``tests/runtime/tasks/test_lean_stepping.py``: stock and lean environments side by side, same
   seeds and actions, every task).
2. An override is installed only when the method it replaces is robosuite's own
   (``RobotEnv._pre_action``, not a subclass's): an environment that customises it keeps it.
3. Forced observable refreshes (reset, ``_get_observations(force_update=True)``) still run.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

ROBOSUITE_REWARD_SKIPPED = 0.0
"""What ``reward()`` returns while skipped; a task that sets ``reads_robosuite_reward = False``
must not read it."""


def lean_overrides(env: Any, *, reads_reward: bool) -> dict[str, Callable[..., Any]]:
    """The instance overrides that skip unread work in ``env.step``.

    Args:
        env: A robosuite environment, fully built (robots and controllers loaded).
        reads_reward: Whether the task reads robosuite's reward; False skips computing it.

    Returns:
        Attribute name -> the function to install as that instance attribute.
    """
    overrides: dict[str, Callable[..., Any]] = {"_update_observables": _forced_only(env)}
    pre_action = _cached_pre_action(env)
    if pre_action is not None:
        overrides["_pre_action"] = pre_action
    if not reads_reward:
        overrides["reward"] = _skipped_reward
    return overrides


def install(env: Any, overrides: Mapping[str, Callable[..., Any]]) -> None:
    """Shadow robosuite's methods on ``env`` with ``overrides``."""
    for name, fn in overrides.items():
        setattr(env, name, fn)


def remove(env: Any, overrides: Mapping[str, Callable[..., Any]]) -> None:
    """Drop ``overrides`` from ``env``: its methods are robosuite's as shipped again."""
    for name in overrides:
        env.__dict__.pop(name, None)


def _forced_only(env: Any) -> Callable[..., None]:
    # Bound to the class's method, not whatever the instance holds: installing twice must not
    # wrap the override in itself.
    update = type(env)._update_observables.__get__(env)

    def update_observables(force: bool = False) -> None:
        if force:
            update(force=True)

    return update_observables


def _cached_pre_action(env: Any) -> Callable[..., None] | None:
    """``RobotEnv._pre_action`` with each robot's action size computed once."""
    from robosuite.environments.robot_env import RobotEnv

    if type(env)._pre_action is not RobotEnv._pre_action:
        return None
    robots = tuple(env.robots)
    parts: list[tuple[Any, int, int]] = []
    cutoff = 0
    for robot in robots:
        dim = int(robot.action_dim)
        parts.append((robot, cutoff, cutoff + dim))
        cutoff += dim
    total = cutoff
    plan = tuple(parts)

    def pre_action(action: Any, policy_step: bool = False) -> None:
        # The same check and the same slices as robosuite's, minus the recomputed sizes.
        if len(action) != total:
            raise AssertionError(f"environment got invalid action dimension -- expected {total}, got {len(action)}")
        for robot, start, stop in plan:
            robot.control(action[start:stop], policy_step=policy_step)

    return pre_action


def _skipped_reward(action: Any = None) -> float:
    return ROBOSUITE_REWARD_SKIPPED
