"""The paper's reward shaping for learned ECMs, as a gymnasium wrapper.

Per episode the shaping adds ``α·1[success] − β·t_exec − γ·n_retry`` to the task's own
(dense, shaped) reward. It is spread over the steps so that an RL learner sees it when it
happens:

* ``+α`` on the step where ``info[success_key]`` first becomes true (the flag is latched by
  the environments here; a flag that drops and comes back is rewarded once);
* ``−β·dt`` on every step, ``dt`` the simulated control period in seconds, so the episode
  total is ``−β·t_exec`` with ``t_exec = steps·dt`` (simulated, hence reproducible, time);
* ``−γ·k`` on a step where the cumulative counter ``info[retries_key]`` grew by ``k``.

The wrapper writes ``info["reward_task"]`` (the inner reward) and ``info["reward_shaping"]``
(what it added) on every step.

Invariants:
1. For every episode, ``sum(shaped) == sum(task) + α·1[success by the end] − β·dt·steps
   − γ·n_retry`` (up to float rounding), ``n_retry`` the final counter value.
2. With ``α = β = γ = 0`` the wrapper returns the inner reward unchanged.
3. :class:`RewardShaping` refuses non-finite or negative coefficients and non-positive
   ``dt`` with :class:`Invalid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from capevo.errors import Invalid


def _coefficient(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise Invalid(f"{name} must be a finite number >= 0, got {value!r}", details={"field": name})
    return float(value)


@dataclass(frozen=True, slots=True, kw_only=True)
class RewardShaping:
    """Coefficients of ``r = α·1[success] − β·t_exec − γ·n_retry``.

    Args:
        success_bonus: α, added once when the episode first reports success.
        time_penalty: β, per simulated second of execution.
        retry_penalty: γ, per retry.
        success_key: Info key of the (latched) success flag.
        retries_key: Info key of the cumulative retry counter (absent means 0).

    Raises:
        Invalid: a negative or non-finite coefficient, or an empty key.
    """

    success_bonus: float = 5.0
    time_penalty: float = 1.0
    retry_penalty: float = 1.0
    success_key: str = "is_success"
    retries_key: str = "retries"

    def __post_init__(self) -> None:
        for name in ("success_bonus", "time_penalty", "retry_penalty"):
            _coefficient(name, getattr(self, name))
        for name in ("success_key", "retries_key"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise Invalid(f"{name} must be a non-empty string, got {value!r}", details={"field": name})

    def step_bonus(self, *, newly_succeeded: bool, dt: float, new_retries: int) -> float:
        """The shaping term of one step (see the module docstring)."""
        return (
            (self.success_bonus if newly_succeeded else 0.0)
            - self.time_penalty * dt
            - self.retry_penalty * max(0, int(new_retries))
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "success_bonus": self.success_bonus,
            "time_penalty": self.time_penalty,
            "retry_penalty": self.retry_penalty,
            "success_key": self.success_key,
            "retries_key": self.retries_key,
        }


def control_dt(env: gym.Env[Any, Any]) -> float | None:
    """Seconds per step of ``env``: its ``control_dt`` attribute, or 1 / robosuite's ``control_freq``."""
    inner = env.unwrapped
    dt = getattr(inner, "control_dt", None)
    if isinstance(dt, (int, float)) and dt > 0:
        return float(dt)
    robosuite_env = getattr(inner, "robosuite_env", None)
    freq = getattr(robosuite_env, "control_freq", None)
    if isinstance(freq, (int, float)) and freq > 0:
        return 1.0 / float(freq)
    return None


class ShapedReward(gym.Wrapper[Any, Any, Any, Any]):
    """Adds :class:`RewardShaping` to an environment's reward.

    Args:
        env: The environment; its infos carry the success flag and the retry counter.
        shaping: The coefficients.
        dt: Seconds per step; default read from the environment (:func:`control_dt`).

    Raises:
        Invalid: no ``dt`` given and none can be read from ``env``, or ``dt`` not positive.
    """

    def __init__(self, env: gym.Env[Any, Any], shaping: RewardShaping, *, dt: float | None = None) -> None:
        super().__init__(env)
        if not isinstance(shaping, RewardShaping):
            raise Invalid(
                f"shaping must be a RewardShaping, got {type(shaping).__name__}", details={"field": "shaping"}
            )
        if dt is None:
            dt = control_dt(env)
            if dt is None:
                raise Invalid("cannot tell the environment's control period; pass dt=", details={"field": "dt"})
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
            raise Invalid(f"dt must be a positive number of seconds, got {dt!r}", details={"field": "dt"})
        self.shaping = shaping
        self.dt = float(dt)
        self._succeeded = False
        self._retries = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._succeeded = bool(info.get(self.shaping.success_key, False))
        self._retries = int(info.get(self.shaping.retries_key, 0) or 0)
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        success = bool(info.get(self.shaping.success_key, False))
        retries = int(info.get(self.shaping.retries_key, 0) or 0)
        bonus = self.shaping.step_bonus(
            newly_succeeded=success and not self._succeeded, dt=self.dt, new_retries=retries - self._retries
        )
        self._succeeded = self._succeeded or success
        self._retries = max(self._retries, retries)
        info = dict(info)
        info["reward_task"] = float(reward)
        info["reward_shaping"] = bonus
        return obs, float(reward) + bonus, terminated, truncated, info
