"""Shared fixtures for the ECM tests: a real SB3 model zip."""

from __future__ import annotations

import io

import pytest


@pytest.fixture(scope="session")
def sac_zip() -> bytes:
    """A real SAC model zip on Pendulum-v1 (tiny net, one env step, no gradient update)."""
    import gymnasium as gym
    from stable_baselines3 import SAC

    from capevo.learner.neural_seed import silent_logger

    env = gym.make("Pendulum-v1")
    model = SAC(
        "MlpPolicy",
        env,
        learning_starts=10**6,
        buffer_size=64,
        policy_kwargs={"net_arch": [16, 16]},
        device="cpu",
        seed=0,
    )
    model.set_logger(silent_logger())  # else SB3 leaves an empty $TMPDIR/SB3-<time> folder
    model.learn(total_timesteps=1)
    buf = io.BytesIO()
    model.save(buf)
    env.close()
    return buf.getvalue()
