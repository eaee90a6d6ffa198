"""Does SAC fine-tuning keep what behaviour cloning gave a neural ECM? (issue 19, modality ``rl``)

The ``rl`` modality clones a random-init ECM from the task's scripted reference and then trains
SAC on the shaped reward (:class:`capevo.learner.rl.SacLearner`). On T1 every such candidate was
rejected by the gate (``results/evolution/T1-rl``). This script isolates one update of
``pick.reach`` on T1 and measures the ECM's own success (its termination predicate) with the
deterministic actor on 10 training-range seeds that SAC never saw, three times: after cloning,
after an optional critic warm-up, and after SAC. Each flag turns on one remedy from the
literature, so a run shows which of them keeps the cloned skill:

* ``--bc-loss nll`` clones the actor's Gaussian (mean and spread), not only its mean;
* ``--explore-std S`` sets the cloned actor's exploration spread to ``S`` (instead of the random
  head's ~1, which makes SAC's own episodes a random walk);
* ``--ent-coef``, ``--learning-starts`` and ``--learning-rate`` are SAC's own settings;
* ``--critic-warmup N`` trains only the critics for the first N steps (actor frozen);
* ``--bc-weight λ`` adds ``λ·MSE(actor(s), a_demo)`` on a demonstration minibatch after each
  environment step (Nair et al. 2018's behaviour-cloning term, as a callback, so SB3's SAC update
  itself is unchanged);
* ``--potential`` feeds the task's dense reward as a potential difference ``γΦ(s') − Φ(s)``
  (Ng et al. 1999) instead of as a per-step reward. Added per step, a positive dense reward pays an
  ECM for *not* reaching its termination, which ends its episode.

It uses the ``cpu-small`` learner preset (5,000 SAC steps, 20 scripted demonstration episodes,
200 BC epochs) and the default envelope, as ``capevo evolve --modality rl`` does, in a scratch
registry with the random-init v0 of every T1 ECM.

    .venv/bin/python benchmarks/diag_sac_warm_start.py --name base
    .venv/bin/python benchmarks/diag_sac_warm_start.py --name all --bc-loss mse --explore-std 0.2 \\
        --ent-coef 0.001 --learning-starts 0 --critic-warmup 2000 --bc-weight 20 --potential

Each run appends one row to ``benchmarks/results/sac_warm_start.json`` and prints it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common

EVAL_SEED_OFFSET = 50_000
"""Evaluation episodes run training-range seeds this far past the learner's own."""


def _potential_wrapper(gamma: float) -> Any:
    import gymnasium as gym

    class PotentialReward(gym.Wrapper):  # type: ignore[type-arg]
        """The dense reward r_t = Φ(s_{t+1}) as γΦ(s') − Φ(s); Φ(s_0) is taken as Φ(s_1)."""

        def reset(self, **kwargs: Any) -> Any:
            self._previous: float | None = None
            return self.env.reset(**kwargs)

        def step(self, action: Any) -> Any:
            obs, reward, terminated, truncated, info = self.env.step(action)
            previous = reward if self._previous is None else self._previous
            self._previous = float(reward)
            return obs, gamma * float(reward) - previous, terminated, truncated, info

    return PotentialReward


def evaluate(model: Any, make_env: Any, episodes: int) -> dict[str, float]:
    """The deterministic actor's ECM success, mean task return and mean steps."""
    import numpy as np

    env = make_env(EVAL_SEED_OFFSET)
    successes, returns, steps = 0, [], []
    try:
        for k in range(episodes):
            obs, _ = env.reset(seed=k)
            total, done, t = 0.0, False, 0
            info: dict[str, Any] = {}
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, reward, terminated, truncated, info = env.step(action)
                total += float(reward)
                t += 1
                done = terminated or truncated
            successes += bool(info.get("is_success"))
            returns.append(total)
            steps.append(t)
    finally:
        env.close()
    return {
        "successes": successes,
        "episodes": episodes,
        "mean_return": float(np.mean(returns)),
        "mean_steps": float(np.mean(steps)),
    }


def bc_regulariser(demos: Any, weight: float, stats: dict[str, int]) -> Any:
    """Callback: one ``weight``-scaled BC step on a demonstration minibatch after each env step."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    obs = torch.as_tensor(demos.obs)
    act = torch.as_tensor(demos.action)
    generator = torch.Generator().manual_seed(0)

    class BcTerm(BaseCallback):
        def _on_step(self) -> bool:
            dones = self.locals.get("dones")
            if dones is not None and bool(dones[0]):
                stats["episodes"] += 1
                stats["successes"] += int(bool(self.locals["infos"][0].get("is_success")))
            if weight > 0 and self.num_timesteps >= self.model.learning_starts:
                idx = torch.randint(len(obs), (256,), generator=generator)
                loss = torch.nn.functional.mse_loss(self.model.actor(obs[idx], deterministic=True), act[idx])
                self.model.actor.optimizer.zero_grad()
                (weight * loss).backward()
                self.model.actor.optimizer.step()
            return True

    return BcTerm()


def run(args: argparse.Namespace, scratch: Path) -> dict[str, Any]:
    import torch

    from capevo.evolve.loop import ensure_v0
    from capevo.learner.base import LearnRequest
    from capevo.learner.bc import BcLearner, behaviour_clone
    from capevo.learner.ecm_env import make_ecm_env, target_for
    from capevo.learner.neural_seed import silent_logger
    from capevo.learner.presets import make_preset
    from capevo.learner.reward import ShapedReward
    from capevo.learner.rl import build_sac
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.tasks import task_spec

    torch.set_num_threads(1)
    registry = LocalRegistry(scratch / "registry")
    ensure_v0(registry, args.task, modality="rl")
    preset = make_preset(args.preset).with_seed(args.seed)
    env_config = dataclasses.replace(preset.env, seed=0, phi="task")
    parent = registry.get_version(args.ecm)
    target = target_for(args.task, args.ecm, parent)
    request = LearnRequest(task=task_spec(args.task).name, ecm=args.ecm, parent=parent, source="")

    def make_env(offset: int) -> Any:
        return make_ecm_env(args.task, target, registry=registry, config=dataclasses.replace(env_config, seed=offset))

    sac = dataclasses.replace(preset.sac, total_steps=args.steps)
    if args.ent_coef is not None:
        sac = dataclasses.replace(
            sac, ent_coef=args.ent_coef if args.ent_coef.startswith("auto") else float(args.ent_coef)
        )
    if args.learning_starts is not None:
        sac = dataclasses.replace(sac, learning_starts=args.learning_starts)
    if args.learning_rate is not None:
        sac = dataclasses.replace(sac, learning_rate=args.learning_rate)
    bc = dataclasses.replace(preset.bc, net_arch=sac.net_arch, loss=args.bc_loss)

    env = make_env(0)
    inner = _potential_wrapper(sac.gamma)(env) if args.potential else env
    model = build_sac(ShapedReward(inner, preset.shaping, dt=env.control_dt), sac)
    model.set_logger(silent_logger())
    started = time.perf_counter()
    demos = BcLearner(
        config=bc, env_config=env_config, registry=registry, scripted_episodes=preset.scripted_episodes
    ).gather(request, target)
    cloned = behaviour_clone(model, demos, bc)
    if args.explore_std is not None:
        with torch.no_grad():
            model.actor.log_std.weight.zero_()
            model.actor.log_std.bias.fill_(math.log(args.explore_std))
    row: dict[str, Any] = {
        "name": args.name,
        "settings": {k: v for k, v in vars(args).items() if k != "name"},
        "demo_steps": len(demos),
        "bc_loss": [cloned.loss_before, cloned.loss_after],
        "after_bc": evaluate(model, make_env, args.eval_episodes),
    }
    stats = {"episodes": 0, "successes": 0}
    steps_left = args.steps
    if args.critic_warmup:
        for p in model.actor.parameters():
            p.requires_grad_(False)
        model.learn(total_timesteps=args.critic_warmup, callback=bc_regulariser(demos, 0.0, stats))
        for p in model.actor.parameters():
            p.requires_grad_(True)
        row["after_critic_warmup"] = evaluate(model, make_env, args.eval_episodes)
        steps_left -= args.critic_warmup
    model.learn(
        total_timesteps=steps_left,
        callback=bc_regulariser(demos, args.bc_weight, stats),
        reset_num_timesteps=not args.critic_warmup,
    )
    env.close()
    row["sac_training_episodes"] = stats
    row["after_sac"] = evaluate(model, make_env, args.eval_episodes)
    row["wall_s"] = time.perf_counter() - started
    row["machine"] = _common.machine()
    row["date"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    registry.close()
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--name", required=True, help="label of this run in the results file")
    parser.add_argument("--task", default="T1")
    parser.add_argument("--ecm", default="pick.reach")
    parser.add_argument("--preset", default="cpu-small", help="learner preset (capevo.learner.presets)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--steps", type=int, default=5_000, help="SAC env steps (critic warm-up included)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--bc-loss", choices=("mse", "nll"), default="mse")
    parser.add_argument("--explore-std", type=float, default=None)
    parser.add_argument("--ent-coef", default=None, help="'auto', 'auto_0.01' or a number (default: the preset's)")
    parser.add_argument("--learning-starts", type=int, default=None)
    parser.add_argument("--learning-rate", type=float, default=None)
    parser.add_argument("--critic-warmup", type=int, default=0)
    parser.add_argument("--bc-weight", type=float, default=0.0)
    parser.add_argument("--potential", action="store_true")
    args = parser.parse_args(argv)
    if args.critic_warmup >= args.steps:
        raise SystemExit("--critic-warmup must be below --steps")
    with tempfile.TemporaryDirectory(prefix="capevo-sac-diag-") as scratch:
        row = run(args, Path(scratch))
    path = _common.RESULTS_DIR / "sac_warm_start.json"
    rows = json.loads(path.read_text()) if path.exists() else []
    rows.append(row)
    path.write_text(json.dumps(rows, indent=1) + "\n")
    print(
        json.dumps(
            {
                k: row[k]
                for k in ("name", "after_bc", "after_critic_warmup", "sac_training_episodes", "after_sac")
                if k in row
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
