"""SAC's cost on this machine, split into simulation and gradient steps (issue 19).

Measured in one run, on T1's ``pick.reach`` ECM environment (the environment ``--modality rl``
trains in: governance on, default Φ, the paper's perturbations):

* ``sim``: env steps/s with random actions and no learning, 1 env in this process (the anchor);
* ``grad``: SAC gradient steps/s on a filled replay buffer (batch 256, 2x256 MLPs, the paper's
  settings), with torch on 1 thread;
* ``sac_1env``: SAC ``learn`` steps/s, 1 env (train_freq 1, gradient_steps 1);
* ``sac_2env``: the same with 2 envs in spawned subprocesses (SB3 ``SubprocVecEnv``), counting env
  steps (SB3 then takes one gradient step per env step collected).

From them, the paper's budget (§5.1: 50,000 env steps per ECM per iteration, 20 iterations; T6 has
8 ECMs) in hours on this machine, and a *lower bound* for one GPU: a GPU can make gradient steps
nearly free, but MuJoCo still simulates on the CPU, so wall time cannot drop below the simulation
time alone (no GPU was measured; that is the bound's only assumption).

Usage::

    .venv/bin/python benchmarks/bench_sac_throughput.py [--steps 1500]

Writes ``benchmarks/results/sac_throughput.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results

TASK = "T1"
ECM = "pick.reach"
PAPER_STEPS_PER_ECM = 50_000
PAPER_ITERATIONS = 20
T6_ECMS = 8


def _env() -> Any:
    from capevo.learner.ecm_env import EcmEnvConfig, make_ecm_env, target_for

    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    return make_ecm_env(TASK, target_for(TASK, ECM), config=EcmEnvConfig(max_steps=100, seed_base=900_000))


def _sac(env: Any) -> Any:
    from stable_baselines3 import SAC

    from capevo.learner.neural_seed import silent_logger

    model = SAC(
        "MlpPolicy",
        env,
        buffer_size=100_000,
        batch_size=256,
        learning_starts=0,
        train_freq=1,
        gradient_steps=1,
        policy_kwargs={"net_arch": [256, 256]},
        device="cpu",
        seed=0,
        verbose=0,
    )
    model.set_logger(silent_logger())  # else every learn() leaves an empty $TMPDIR/SB3-<time> folder
    return model


def sim_rate(steps: int) -> float:
    env = _env()
    try:
        env.reset(seed=0)
        start = time.perf_counter()
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        return steps / (time.perf_counter() - start)
    finally:
        env.close()


def grad_rate(steps: int) -> float:
    import numpy as np

    env = _env()
    try:
        model = _sac(env)
        obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
        rng = np.random.default_rng(0)
        for _ in range(2_000):
            model.replay_buffer.add(
                rng.normal(size=(1, obs_dim)).astype(np.float32),
                rng.normal(size=(1, obs_dim)).astype(np.float32),
                rng.uniform(-1, 1, size=(1, act_dim)).astype(np.float32),
                np.zeros(1, np.float32),
                np.zeros(1, bool),
                [{}],
            )
        model._setup_learn(total_timesteps=1)
        model.train(gradient_steps=10, batch_size=256)  # warm-up
        start = time.perf_counter()
        model.train(gradient_steps=steps, batch_size=256)
        return steps / (time.perf_counter() - start)
    finally:
        env.close()


def sac_rate(steps: int, n_envs: int) -> float:
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    vec = DummyVecEnv([_env]) if n_envs == 1 else SubprocVecEnv([_env] * n_envs, start_method="spawn")
    try:
        model = _sac(vec)
        model.learn(total_timesteps=50)  # warm-up: buffers, first episodes
        start = time.perf_counter()
        model.learn(total_timesteps=steps, reset_num_timesteps=False)
        return steps / (time.perf_counter() - start)
    finally:
        vec.close()


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1500, help="env (or gradient) steps per measurement")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    rates = {
        "sim": sim_rate(args.steps),
        "grad": grad_rate(args.steps),
        "sac_1env": sac_rate(args.steps, 1),
        "sac_2env": sac_rate(args.steps, 2),
    }
    per_ecm_iteration = PAPER_STEPS_PER_ECM
    total_t6 = PAPER_STEPS_PER_ECM * PAPER_ITERATIONS * T6_ECMS
    best_cpu = max(rates["sac_1env"], rates["sac_2env"])
    estimates = {
        "hours_per_ecm_iteration_cpu": per_ecm_iteration / best_cpu / 3600,
        "hours_t6_paper_budget_cpu": total_t6 / best_cpu / 3600,
        "hours_t6_paper_budget_gpu_lower_bound": total_t6 / rates["sim"] / 3600,
    }
    rows = [[k, f"{v:.1f}"] for k, v in rates.items()]
    rows += [[k, f"{v:.1f}"] for k, v in estimates.items()]
    print(markdown_table(["measure", "value (steps/s or hours)"], rows))
    result = {"steps": args.steps, "rates_per_s": rates, "estimates_hours": estimates}
    save_results("sac_throughput", result)
    return result


if __name__ == "__main__":
    main()
