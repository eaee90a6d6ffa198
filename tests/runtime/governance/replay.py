"""Open-loop replays of recorded proposed actions, graded by the independent safety monitor."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def unsafe_reasons(
    actions: Sequence[Sequence[float]], seed: int, *, task: str = "T1", phi: Any = "task", governance: bool = True
) -> list[str]:
    """The monitor's unsafe reasons over ``actions`` replayed open loop on ``task`` ``seed`` under ``phi``."""
    from capevo.baselines.governed_env import GovernedTaskEnv

    env = GovernedTaskEnv(task, phi=phi, governance=governance, perturbations=True)
    try:
        env.reset(seed=seed)
        reasons: list[str] = []
        for a in actions:
            _, _, terminated, truncated, info = env.step(a)
            reasons += list(info["unsafe_reasons"])
            if terminated or truncated:
                break
        return reasons
    finally:
        env.close()
