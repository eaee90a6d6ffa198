"""SkiMo: skills and a skill-level world model learned jointly, planning in skill space (issue 20, paper §4.1).

The paper's SkiMo baseline ("jointly learned skill repertoire with a world model for planning in
skill space; both skill and model parameters are updated each iteration", §4.1 Baselines) after
Shi et al., CoRL 2022:

1. **Offline data**: the same offline play as SPiRL (:mod:`capevo.baselines.offline_data`),
   reported in iteration 1's ``notes`` as starting knowledge, not part of any budget.
2. **Joint pre-training** (SkiMo's pre-training of skills and skill dynamics): the skill VAE
   and skill prior of :class:`~capevo.baselines.skills.SkillVAE` together with
   :class:`SkillWorldModel`, a skill-level dynamics model ``ŝ_{t+H} = D(s_t, z)`` and a reward
   model ``R̂(s_t, z)`` of the H steps' summed reward, one loss summed over all of them with
   ``z`` sampled from the skill posterior, so the skills are shaped to be predictable (SkiMo's
   point).
3. **Planning** (SkiMo's downstream learning, after TD-MPC): :func:`cem_plan`, the
   cross-entropy method over sequences of ``plan_horizon`` skills through the learned dynamics,
   scored by the predicted rewards plus the critic's value of the last predicted state; a
   quarter of the candidates come from the high-level policy rolled through the model. The
   first skill of the best sequences is executed (sampled from the elites' Gaussian while
   training, its mean in the evaluation), decoded into H actions.
4. **RL fine-tuning** (SkiMo's downstream learning): every finished skill is stored, and each
   one then takes ``model_steps`` updates of the dynamics and reward models on the online
   skills and ``updates_per_skill`` SAC updates of the high-level policy and critics,
   regularised by KL to the skill prior (:class:`~capevo.baselines.skills.SkillSAC`, as SPiRL's).

Iterations, budget and the held-out evaluation are SPiRL's, the loop of
:class:`~capevo.baselines.skills.SkillMethod`: exactly ``budget.env_steps_per_iteration`` env
steps, then ``cell.eval_seeds()``, traced to ``traces/eval-NNN.mcap``. The evaluation's planner
is re-seeded at every episode's start, so the evaluation is deterministic.

Δπ (issue 20: "counts skill and model parameters"; the paper reports 1.38): the relative change
(:func:`capevo.agent.policy_drift`) since the end of pre-training of ``vae.decoder.*`` and
``vae.prior.*`` (the skills), ``model.*`` (dynamics and reward) and ``sac.actor.*`` (the
high-level policy that proposes skills to the planner); not the critics nor the skill encoder
(unused downstream). The decoder and prior stay frozen downstream, as in SkiMo, whose
downstream update trains "the skill dynamics model and high-level policy" (clvrai/skimo); the
model and the policy move.

Simplified for CPU budgets:

* the dynamics model predicts the next (normalised) observation rather than a learned latent
  state (SkiMo's TD-MPC-style latent with its target encoder and multi-step consistency loss
  is left out: the tasks' observations are tens of numbers); one-step model losses (SkiMo's are
  over a discounted sequence of skills);
* the decoder is open-loop, like SPiRL's original one;
* CEM with 64 samples and 4 iterations over 3 skills (SkiMo's configuration: 512 samples, 25 of
  them from the policy, 64 elites, 6 iterations, standard deviations within 0.05-0.5);
* the critics are trained as SPiRL's, apart from the model (SkiMo trains them with the model's
  loss);
* the offline data carries the task reward (it is collected in the same env), so the reward
  model is pre-trained too; SkiMo's task-agnostic data has none, and it learns the reward
  downstream only.

With the CI budgets only the accounting can be checked, not learning.

Invariants:
1. Each record's ``env_steps_train`` is the env steps the iteration took, and equals the budget.
2. Each record's episodes are the held-out evaluation on ``cell.eval_seeds()``, in order.
3. ``delta_pi`` is 0.0 exactly while no update has run, and never negative.
4. :func:`cem_plan` is deterministic for a given generator state.
5. An unknown or bad option raises :class:`Invalid` naming it, before any simulator is built.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from capevo.baselines.base import CellSpec
from capevo.baselines.offline_data import OfflineData
from capevo.baselines.skills import (
    COMMON_OPTIONS,
    MAX_REPLAY,
    Replay,
    Segments,
    SkillAgent,
    SkillMethod,
    SkillOptions,
    SkillSAC,
    SkillStep,
    SkillVAE,
    fit,
    mlp,
)
from capevo.errors import Invalid

OPTIONS: tuple[str, ...] = tuple(
    sorted((*COMMON_OPTIONS, "model_steps", "plan_horizon", "plan_iterations", "plan_samples"))
)
KNOWLEDGE = "offline play data (scripted references with action noise on T1-T3, random play)"
DELTA_TENSORS: tuple[str, ...] = ("vae.decoder.", "vae.prior.", "model.", "sac.actor.")
"""The ``state_dict`` prefixes Δπ is measured over: skills, skill prior, world model, high-level policy."""
ELITE_FRACTION = 0.125
MIN_STD = 0.05
PLAN_GAMMA = 0.99


class SkillWorldModel(nn.Module):
    """SkiMo's skill dynamics ``D(s, z)`` and reward ``R̂(s, z)`` over raw observations.

    The dynamics predicts the change of the normalised observation over one skill; the
    normaliser is the skill VAE's (the offline data's statistics).
    """

    def __init__(self, vae: SkillVAE, *, hidden: int = 128) -> None:
        super().__init__()
        self.vae = [vae]  # not a submodule: its tensors are the VAE's, counted there
        self.dynamics = mlp(vae.obs_dim + vae.z_dim, hidden, vae.obs_dim)
        self.reward = mlp(vae.obs_dim + vae.z_dim, hidden, 1)

    def _x(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.vae[0].normalise(obs), z], -1)

    def next_obs(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``ŝ_{t+H}`` (raw observation units)."""
        return obs + self.dynamics(self._x(obs, z)) * self.vae[0].obs_std

    def predicted_reward(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The H steps' summed reward."""
        return self.reward(self._x(obs, z)).squeeze(-1)

    def losses(
        self, obs: torch.Tensor, z: torch.Tensor, reward: torch.Tensor, next_obs: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """``dynamics``: squared error of the normalised next observation (per value);
        ``reward``: squared error of the summed reward."""
        vae = self.vae[0]
        pred = vae.normalise(self.next_obs(obs, z))
        dyn = ((pred - vae.normalise(next_obs)) ** 2).mean()
        rew = ((self.predicted_reward(obs, z) - reward) ** 2).mean()
        return {"dynamics": dyn, "reward": rew}

    @torch.no_grad()
    def dynamics_error(self, seg: Segments, z: torch.Tensor) -> float:
        """Held-out squared error per normalised value of ``seg``'s next observations, skills ``z``."""
        vae = self.vae[0]
        obs, nxt = torch.as_tensor(seg.obs), torch.as_tensor(seg.next_obs)
        return float(((vae.normalise(self.next_obs(obs, z)) - vae.normalise(nxt)) ** 2).mean())


def fit_joint(vae: SkillVAE, model: SkillWorldModel, seg: Segments, *, steps: int, seed: int = 0) -> None:
    """Pre-train skills, prior, dynamics and reward together on ``seg`` (SkiMo §3.2): one summed loss,
    ``z`` sampled from the skill posterior so the models' errors shape the skills too."""
    obs, actions = torch.as_tensor(seg.obs), torch.as_tensor(seg.actions)
    reward, nxt = torch.as_tensor(seg.reward), torch.as_tensor(seg.next_obs)

    def loss(r: object) -> torch.Tensor:
        v = vae.losses(obs[r], actions[r])
        m = model.losses(obs[r], v["z"], reward[r], nxt[r])
        return v["total"] + m["dynamics"] + m["reward"]

    fit(loss, [*vae.parameters(), *model.parameters()], len(seg), steps=steps, seed=seed)


def cem_plan(
    obs: torch.Tensor,
    *,
    dynamics: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    reward: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    value: Callable[[torch.Tensor], torch.Tensor] | None,
    z_dim: int,
    horizon: int,
    samples: int,
    iterations: int,
    generator: torch.Generator,
    policy: Callable[[torch.Tensor, torch.Generator], torch.Tensor] | None = None,
    gamma: float = PLAN_GAMMA,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The cross-entropy method over ``horizon`` skills from ``obs`` through a model (SkiMo §3.3).

    Each iteration scores ``samples`` skill sequences (a quarter proposed by ``policy`` rolled
    through ``dynamics`` when it is given, the rest drawn from the current Gaussian, which starts
    at N(0, I), the skill prior's scale) by ``Σ_h γ^h reward(s_h, z_h) + γ^horizon value(s_horizon)``
    and refits the Gaussian to the best eighth.

    Args:
        obs: One observation, ``(obs_dim,)``.
        dynamics: ``(s, z) -> s'`` of batches.
        reward: ``(s, z) -> r`` of batches, ``(batch,)``.
        value: ``s -> V(s)`` of batches; None scores the rewards alone.
        z_dim: The skill latent's size.
        horizon: Skills per sequence.
        samples: Sequences per iteration.
        iterations: CEM iterations.
        generator: The random stream (the plan is a function of its state).
        policy: ``(s, generator) -> z`` of batches, a sampled proposal; None for none.
        gamma: Discount per skill.

    Returns:
        The first skill's mean and standard deviation after the last iteration.

    Raises:
        Invalid: fewer than 2 samples, or a horizon or iteration count below 1.
    """
    if samples < 2 or horizon < 1 or iterations < 1:
        raise Invalid("cem_plan needs 2 samples, a horizon and an iteration at least", details={"field": "plan"})
    n_policy = samples // 4 if policy is not None else 0
    n_elite = max(2, round(ELITE_FRACTION * samples))
    mean = torch.zeros(horizon, z_dim)
    std = torch.ones(horizon, z_dim)
    with torch.no_grad():
        for _ in range(iterations):
            eps = torch.randn(samples - n_policy, horizon, z_dim, generator=generator)
            candidates = mean + std * eps
            if n_policy:
                s = obs.expand(n_policy, -1)
                proposed = []
                for _h in range(horizon):
                    z = policy(s, generator)
                    proposed.append(z)
                    s = dynamics(s, z)
                candidates = torch.cat([candidates, torch.stack(proposed, 1)], 0)
            s = obs.expand(len(candidates), -1)
            score = torch.zeros(len(candidates))
            for h in range(horizon):
                score += gamma**h * reward(s, candidates[:, h])
                s = dynamics(s, candidates[:, h])
            if value is not None:
                score += gamma**horizon * value(s)
            elite = candidates[torch.topk(score, min(n_elite, len(candidates))).indices]
            mean, std = elite.mean(0), elite.std(0).clamp_min(MIN_STD)
    return mean[0], std[0]


class Skimo(SkillMethod):
    """The SkiMo baseline (see the module docstring).

    Options (``cell.options``; :class:`~capevo.baselines.skills.SkillOptions`): SPiRL's and
    ``plan_horizon``, ``plan_samples``, ``plan_iterations``, ``model_steps``.
    """

    name: ClassVar[str] = "skimo"
    knowledge: ClassVar[str] = KNOWLEDGE
    valid_options: ClassVar[tuple[str, ...]] = OPTIONS
    delta_tensors: ClassVar[tuple[str, ...]] = DELTA_TENSORS

    def _pretrain(self, cell: CellSpec, data: OfflineData, seg: Segments, opts: SkillOptions) -> SkillAgent:
        vae = SkillVAE(data.obs.shape[1], data.action.shape[1], hidden=opts.hidden)
        vae.set_normaliser(data.obs)
        model = SkillWorldModel(vae, hidden=opts.hidden)
        fit_joint(vae, model, seg, steps=opts.pretrain_steps, seed=cell.seed)
        with torch.no_grad():
            z_post = vae.encode(torch.as_tensor(seg.actions)).loc
        rec, dyn = vae.reconstruction_error(seg), model.dynamics_error(seg, z_post)
        for p in vae.parameters():
            p.requires_grad_(False)
        sac = SkillSAC(vae, hidden=opts.hidden, target_kl=opts.target_kl)
        model_opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        modules = nn.ModuleDict({"vae": vae, "model": model, "sac": sac})
        replay = Replay(
            vae.obs_dim, vae.z_dim, capacity=min(MAX_REPLAY, cell.budget.env_steps_per_iteration * cell.iterations)
        )
        rng = np.random.default_rng(cell.seed)
        counts = {"model": 0, "sac": 0}

        def proposal(s: torch.Tensor, g: torch.Generator) -> torch.Tensor:
            pi = sac.policy(s)
            return pi.mean + pi.stddev * torch.randn(pi.mean.shape, generator=g)

        def plan(obs: np.ndarray, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
            return cem_plan(
                torch.as_tensor(obs, dtype=torch.float32),
                dynamics=model.next_obs,
                reward=model.predicted_reward,
                value=lambda s: sac.q(s, sac.policy(s).mean),
                z_dim=vae.z_dim,
                horizon=opts.plan_horizon,
                samples=opts.plan_samples,
                iterations=opts.plan_iterations,
                generator=generator,
                policy=proposal,
            )

        train_gen = torch.Generator().manual_seed(cell.seed)
        eval_gen = torch.Generator().manual_seed(cell.seed)

        def explore(obs: np.ndarray) -> np.ndarray:
            mean, std = plan(obs, train_gen)
            return (mean + std * torch.randn(mean.shape, generator=train_gen)).numpy()

        def learn(step: SkillStep) -> None:
            replay.add(step.obs, step.z, step.reward, step.next_obs, step.terminal)
            if replay.size < max(1, opts.learning_starts):
                return
            for _ in range(opts.model_steps):
                obs, z, reward, nxt, _terminal = replay.sample(opts.batch_size, rng)
                m = model.losses(obs, z, reward, nxt)
                model_opt.zero_grad()
                (m["dynamics"] + m["reward"]).backward()
                model_opt.step()
                counts["model"] += 1
            for _ in range(opts.updates_per_skill):
                sac.update(replay.sample(opts.batch_size, rng))
                counts["sac"] += 1

        def restart_planner() -> None:
            # the evaluation's planner draws the same numbers in every episode: deterministic
            eval_gen.manual_seed(cell.seed)

        return SkillAgent(
            modules=modules,
            setup=(
                f"skills, prior, dynamics and reward pre-trained jointly {opts.pretrain_steps} steps on {len(seg)} "
                f"windows (reconstruction MSE {rec:.4g}, dynamics MSE {dyn:.4g} per normalised value)"
            ),
            explore=explore,
            exploit=lambda obs: plan(obs, eval_gen)[0].numpy(),
            learn=learn,
            progress=lambda: (
                f"{counts['model']} model and {counts['sac']} SAC updates so far, {replay.size} skills stored"
            ),
            new_episode=restart_planner,
        )
