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
* ``--residual`` trains SAC on a residual over the *frozen* clone (Silver et al. 2018, Johannink
  et al. 2019), written as one SB3 SAC actor twice as wide: each hidden layer is ``[clone |
  residual]`` with the cross blocks at 0, the mean head reads both halves, and gradient masks keep
  the clone's weights, the cross blocks and the head's bias fixed. The residual's columns of the
  head start at 0, so the deterministic actor starts as the clone (checked: ``residual_start``)
  and the artifact stays a plain SAC zip the runtime loads. The spread head starts at
  ``--explore-std`` (0.2 when unset);
* ``--awac λ`` replaces SAC's actor update by AWAC's (Nair et al. 2020, eq. 7-8): the actor
  maximises the log-likelihood of the replay buffer's own actions, each weighted by
  ``min(exp(A(s, a) / λ), 20)`` with ``A = Q(s, a) − Q(s, π(s))`` from SAC's critics, so it can only
  move towards actions it has seen do better. SAC's critic update is unchanged; its own actor
  step is switched off by freezing the actor, and a callback takes one AWAC step per env step;
* ``--layer-norm`` puts a LayerNorm after every hidden layer of both critics and their targets
  (Ball et al. 2023, RLPD: it bounds how far the critic extrapolates to actions it has not seen);
* ``--demo-ratio R`` fills a second buffer with the clone's own successful episodes before SAC
  (``--demo-episodes`` rollouts at the clone's exploration spread, their env steps counted in
  ``wall_s`` and ``demo_env_steps``) and draws a share R of every SAC minibatch from it (RLPD's
  symmetric sampling at R = 0.5); ``--utd G`` takes G gradient steps per env step;
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

END_SIGNALS = ("eef_object_xy_dist", "eef_object_dz", "gripper_opening", "grasped", "object_height_above_start")
"""Signals read where a failed evaluation episode ends: which part of the ECM's termination it missed."""

DEMO_SEED_OFFSET = 20_000
"""The clone's demo episodes (``--demo-ratio``) run training-range seeds this far past the learner's own."""


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
    ends: list[dict[str, float]] = []
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
            if not info.get("is_success"):
                signals = env.task_env.signals()
                ends.append({k: round(float(signals[k]), 4) for k in END_SIGNALS if k in signals})
    finally:
        env.close()
    return {
        "successes": successes,
        "episodes": episodes,
        "mean_return": float(np.mean(returns)),
        "mean_steps": float(np.mean(steps)),
        "failed_ends": ends,
    }


def count_episode(step_locals: dict[str, Any], stats: dict[str, int]) -> None:
    """Count an episode of SAC's own (and whether it succeeded) when this env step ended one."""
    dones = step_locals.get("dones")
    if dones is not None and bool(dones[0]):
        stats["episodes"] += 1
        stats["successes"] += int(bool(step_locals["infos"][0].get("is_success")))


def bc_regulariser(demos: Any, weight: float, stats: dict[str, int]) -> Any:
    """Callback: one ``weight``-scaled BC step on a demonstration minibatch after each env step."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    obs = torch.as_tensor(demos.obs)
    act = torch.as_tensor(demos.action)
    generator = torch.Generator().manual_seed(0)

    class BcTerm(BaseCallback):
        def _on_step(self) -> bool:
            count_episode(self.locals, stats)
            if weight > 0 and self.num_timesteps >= self.model.learning_starts:
                idx = torch.randint(len(obs), (256,), generator=generator)
                loss = torch.nn.functional.mse_loss(self.model.actor(obs[idx], deterministic=True), act[idx])
                self.model.actor.optimizer.zero_grad()
                (weight * loss).backward()
                self.model.actor.optimizer.step()
            return True

    return BcTerm()


AWAC_MAX_WEIGHT = 20.0
"""Cap on AWAC's weight ``exp(A / λ)``, so one over-estimated action cannot dominate a batch."""


def awac_actor(lam: float, stats: dict[str, int]) -> Any:
    """Callback: one AWAC actor step (module docstring, ``--awac``) after each env step."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    class AwacActor(BaseCallback):
        def _on_training_start(self) -> None:
            for p in self.model.actor.parameters():
                p.requires_grad_(False)  # SAC's own actor step then changes nothing

        def _on_step(self) -> bool:
            count_episode(self.locals, stats)
            model = self.model
            if model.num_timesteps < model.learning_starts or model.replay_buffer.size() == 0:
                return True
            data = model.replay_buffer.sample(model.batch_size)
            actor, critic = model.actor, model.critic
            with torch.no_grad():
                q_data = torch.cat(critic(data.observations, data.actions), dim=1).min(dim=1, keepdim=True)[0]
                a_pi, _ = actor.action_log_prob(data.observations)
                q_pi = torch.cat(critic(data.observations, a_pi), dim=1).min(dim=1, keepdim=True)[0]
                weight = torch.exp((q_data - q_pi) / lam).clamp(max=AWAC_MAX_WEIGHT)
            for p in actor.parameters():
                p.requires_grad_(True)
            mean, log_std, kwargs = actor.get_action_dist_params(data.observations)
            log_prob = actor.action_dist.proba_distribution(mean, log_std, **kwargs).log_prob(data.actions)
            loss = -(weight * log_prob.reshape(-1, 1)).mean()
            actor.optimizer.zero_grad()
            loss.backward()
            actor.optimizer.step()
            for p in actor.parameters():
                p.requires_grad_(False)
            return True

        def _on_training_end(self) -> None:
            for p in self.model.actor.parameters():
                p.requires_grad_(True)

    return AwacActor()


def layer_norm_critics(model: Any) -> None:
    """Rebuild both critics and their targets with a LayerNorm after every hidden layer (``--layer-norm``)."""
    import torch

    def with_norms(seq: Any) -> Any:
        layers: list[Any] = []
        for m in seq:
            layers.append(m)
            if isinstance(m, torch.nn.Linear) and m is not seq[-1]:
                layers.append(torch.nn.LayerNorm(m.out_features))
        return torch.nn.Sequential(*layers)

    for critic in (model.critic, model.critic_target):
        for k, q in enumerate(list(critic.q_networks)):
            normed = with_norms(q)
            critic.q_networks[k] = normed
            critic.add_module(f"qf{k}", normed)
    model.critic_target.load_state_dict(model.critic.state_dict())
    model.critic.optimizer = model.critic.optimizer_class(
        model.critic.parameters(), lr=model.lr_schedule(1), **model.critic.optimizer_kwargs
    )
    model.critic_target.set_training_mode(False)


def collect_clone_successes(model: Any, env: Any, episodes: int, first_seed: int) -> tuple[Any, int, int]:
    """A replay buffer of ``model``'s stochastic actor's successful episodes in ``env`` (shaped rewards).

    Returns the buffer, the successful episodes and the env steps spent."""
    import numpy as np
    from stable_baselines3.common.buffers import ReplayBuffer

    buffer = ReplayBuffer(50_000, env.observation_space, env.action_space, device="cpu", n_envs=1)
    good, steps = 0, 0
    for k in range(episodes):
        obs, _ = env.reset(seed=first_seed + k)
        rows, done, info = [], False, {}
        while not done:
            action, _ = model.predict(obs, deterministic=False)
            nxt, reward, terminated, truncated, info = env.step(action)
            rows.append((obs, nxt, action, reward, terminated, truncated))
            obs, done = nxt, terminated or truncated
            steps += 1
        if info.get("is_success"):
            good += 1
            for o, n, a, r, term, trunc in rows:
                buffer.add(
                    np.asarray(o)[None],
                    np.asarray(n)[None],
                    np.asarray(a)[None],
                    np.array([r], dtype=np.float32),
                    np.array([term]),
                    [{"TimeLimit.truncated": bool(trunc)}],
                )
    return buffer, good, steps


def symmetric_sampling(model: Any, demo: Any, ratio: float) -> None:
    """Draw a share ``ratio`` of each of ``model``'s minibatches from ``demo`` (``--demo-ratio``)."""
    import torch
    from stable_baselines3.common.type_aliases import ReplayBufferSamples

    online = model.replay_buffer
    own_sample = online.sample

    def sample(batch_size: int, env: Any = None) -> Any:
        from_demo = round(batch_size * ratio)
        a = own_sample(batch_size - from_demo, env=env)
        b = demo.sample(from_demo, env=env)
        # fields a buffer does not fill (SB3's n-step ``discounts``) are None on both sides
        return ReplayBufferSamples(*(None if x is None else torch.cat([x, y]) for x, y in zip(a, b, strict=True)))

    online.sample = sample


def residual_over(clone: Any, env: Any, sac: Any, explore_std: float) -> Any:
    """A SAC model whose actor is ``clone``'s actor plus a trainable residual (see ``--residual``)."""
    import torch

    from capevo.learner.neural_seed import new_sac

    src = [m for m in clone.actor.latent_pi if isinstance(m, torch.nn.Linear)]
    hidden = [m.out_features for m in src]
    wide = new_sac(
        env,
        seed=sac.seed,
        policy_kwargs={"net_arch": {"pi": [2 * n for n in hidden], "qf": hidden}},
        **sac.sac_kwargs(),
    )
    dst = [m for m in wide.actor.latent_pi if isinstance(m, torch.nn.Linear)]
    masks: list[tuple[Any, Any]] = []
    with torch.no_grad():
        for k, (s, d) in enumerate(zip(src, dst, strict=True)):
            o, i = s.out_features, s.in_features
            train_w, train_b = torch.zeros_like(d.weight), torch.zeros_like(d.bias)
            if k == 0:  # the first layer reads the observation: both halves see all of it
                d.weight[:o] = s.weight
                train_w[o:] = 1.0
            else:
                d.weight[:o, :i] = s.weight
                d.weight[:o, i:] = 0.0
                d.weight[o:, :i] = 0.0
                train_w[o:, i:] = 1.0
            d.bias[:o] = s.bias
            train_b[o:] = 1.0
            masks += [(d.weight, train_w), (d.bias, train_b)]
        o = hidden[-1]
        mu = wide.actor.mu
        mu.weight[:, :o] = clone.actor.mu.weight
        mu.weight[:, o:] = 0.0
        mu.bias.copy_(clone.actor.mu.bias)
        train_mu = torch.zeros_like(mu.weight)
        train_mu[:, o:] = 1.0
        masks += [(mu.weight, train_mu), (mu.bias, torch.zeros_like(mu.bias))]
        wide.actor.log_std.weight.zero_()
        wide.actor.log_std.bias.fill_(math.log(explore_std))
    for param, mask in masks:
        param.register_hook(lambda grad, mask=mask: grad * mask)
    return wide


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
    clone = model
    if args.residual:
        model = residual_over(clone, model.get_env(), sac, args.explore_std or 0.2)
        model.set_logger(silent_logger())
    elif args.explore_std is not None:
        with torch.no_grad():
            model.actor.log_std.weight.zero_()
            model.actor.log_std.bias.fill_(math.log(args.explore_std))
    if args.layer_norm:
        layer_norm_critics(model)
    if args.utd > 1:
        model.gradient_steps = args.utd
    demo_buffer = None
    if args.demo_ratio:
        demo_env = make_env(DEMO_SEED_OFFSET)
        shaped_demo_env = ShapedReward(
            _potential_wrapper(sac.gamma)(demo_env) if args.potential else demo_env, preset.shaping, dt=env.control_dt
        )
        demo_buffer, good, spent = collect_clone_successes(model, shaped_demo_env, args.demo_episodes, 0)
        demo_env.close()
        if good == 0:
            raise SystemExit("the clone succeeded in none of its demo episodes; nothing to sample")
        symmetric_sampling(model, demo_buffer, args.demo_ratio)
    row: dict[str, Any] = {
        "name": args.name,
        "settings": {k: v for k, v in vars(args).items() if k != "name"},
        "demo_steps": len(demos),
        "bc_loss": [cloned.loss_before, cloned.loss_after],
        "after_bc": evaluate(clone, make_env, args.eval_episodes),
    }
    if demo_buffer is not None:
        row["demo_episodes"] = {"successful": good, "of": args.demo_episodes, "env_steps": spent}
    if args.residual:
        row["residual_start"] = evaluate(model, make_env, args.eval_episodes)
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
    before = [q.detach().clone() for q in model.actor.parameters()]
    model.learn(
        total_timesteps=steps_left,
        callback=awac_actor(args.awac, stats) if args.awac else bc_regulariser(demos, args.bc_weight, stats),
        reset_num_timesteps=not args.critic_warmup,
    )
    env.close()
    row["sac_training_episodes"] = stats
    row["after_sac"] = evaluate(model, make_env, args.eval_episodes)
    # how far SAC's (or AWAC's) actor updates moved the actor's weights (L2 over all of them)
    row["actor_change"] = float(
        sum(float((q.detach() - b).pow(2).sum()) for q, b in zip(model.actor.parameters(), before, strict=True)) ** 0.5
    )
    if args.residual:
        head = model.actor.mu.weight.detach()
        half = head.shape[1] // 2
        row["head_norm"] = {"clone": float(head[:, :half].norm()), "residual": float(head[:, half:].norm())}
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
    parser.add_argument("--layer-norm", action="store_true", help="LayerNorm in the critics (RLPD)")
    parser.add_argument("--demo-ratio", type=float, default=0.0, help="minibatch share from the clone's successes")
    parser.add_argument("--demo-episodes", type=int, default=20, help="clone rollouts collected for --demo-ratio")
    parser.add_argument("--utd", type=int, default=1, help="gradient steps per env step")
    parser.add_argument("--residual", action="store_true", help="train a residual over the frozen clone")
    parser.add_argument("--awac", type=float, default=None, metavar="LAMBDA", help="AWAC's actor update, temperature λ")
    args = parser.parse_args(argv)
    if args.awac is not None and not args.awac > 0:
        raise SystemExit("--awac needs a temperature > 0")
    if args.awac and args.bc_weight:
        raise SystemExit("--awac and --bc-weight are two actor updates; choose one")
    if not 0 <= args.demo_ratio < 1:
        raise SystemExit("--demo-ratio must be in [0, 1)")
    if args.utd < 1:
        raise SystemExit("--utd must be >= 1")
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
                for k in (
                    "name",
                    "after_bc",
                    "residual_start",
                    "after_critic_warmup",
                    "sac_training_episodes",
                    "after_sac",
                    "demo_episodes",
                    "head_norm",
                )
                if k in row
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
