"""The learned skill space SPiRL and SkiMo share: a skill VAE with a state-conditioned prior, SAC in skill space.

Both baselines (issue 20; :mod:`capevo.baselines.spirl`, :mod:`capevo.baselines.skimo`) act
through skills: a latent ``z`` chosen every ``H`` steps and decoded into ``H`` actions. This
module holds what they share; each method's docstring says what it adds.

:class:`SkillVAE` follows SPiRL (Pertsch et al., CoRL 2020), §3.1-3.2:

* a skill encoder ``q(z | a_{0:H-1})`` and a decoder ``p(a_{0:H-1} | z)`` over H-step action
  sequences (H = 10, ``z`` 10-dimensional, as SPiRL's and SkiMo's configurations), trained
  with the β-VAE objective: the reconstruction error plus ``β · KL(q(z|a) ‖ N(0, I))``;
* a skill prior ``p(z | s_0)`` trained jointly with ``KL(sg(q(z|a)) ‖ p(z|s_0))``, the encoder's
  posterior held fixed (the "stop gradient" of SPiRL §3.2), so the prior follows the skills and
  does not shape them.

Simplified for CPU budgets: the encoder and decoder are MLPs over the flattened sequence (SPiRL
uses LSTMs); the decoder is open-loop, ``z`` alone gives all H actions (SPiRL's original model;
its closed-loop variant and SkiMo condition the decoder on the state too); the reconstruction
loss is the squared error (a Gaussian of fixed variance, as SPiRL's); observations are
normalised by the offline data's mean and standard deviation, stored with the model.

:class:`SkillSAC` follows SPiRL §3.3 (skill-prior-regularised RL, its Algorithm 1): soft actor-critic whose policy
``π(z | s)`` picks a skill every H steps, rewarded with the H steps' summed reward, with the
entropy term replaced by the divergence from the prior, ``−α · KL(π(z|s) ‖ p(z|s))``, and ``α``
tuned to hold that divergence near a target δ (SPiRL's automatic temperature). The policy starts
as a copy of the prior (as in SPiRL). Twin critics with Polyak-averaged targets (SAC). Why not
stable-baselines3's SAC, as AM uses: SB3 regularises by the policy's entropy and has no hook for
a learned, state-conditioned prior; replacing its loss would mean patching its internals.

:class:`SkillRunner` runs skills in a :class:`~capevo.baselines.governed_env.GovernedTaskEnv`
for exactly a number of env steps: a skill cut by the end of an iteration's budget continues at
the start of the next, so every stored transition is a whole skill (H steps, or fewer when the
episode ended first).

:class:`SkillMethod` is the iteration loop both run (offline data, pre-training through the
method's hook, then per iteration: the budget's steps, checkpoint, Δπ, held-out evaluation,
``emit``); :class:`SkillOptions` their options.

What is learned and what is hand-written: every network here is learned; H, the sizes, β, δ and
the learning rates are set by hand (SPiRL's values where it gives them, otherwise named here).

Invariants:
1. :meth:`SkillRunner.run` takes exactly the steps asked for (``env.env_steps`` grows by them).
2. A stored transition's ``steps`` is between 1 and H; it is H unless the episode ended inside it.
3. :meth:`SkillVAE.decode` returns actions in [-1, 1] of shape ``(batch, H, action_dim)``.
4. Training a :class:`SkillVAE` or updating a :class:`SkillSAC` never changes a tensor the
   caller froze (``requires_grad`` False).
5. :meth:`SkillMethod.run` parses every option before it builds a simulator or collects data;
   each record's ``env_steps_train`` equals the budget and its episodes run on ``cell.eval_seeds()``.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn
from torch.distributions import Normal, kl_divergence

from capevo.agent import policy_drift
from capevo.baselines.base import CellSpec, Emit
from capevo.baselines.governed_env import GovernedTaskEnv, held_out_record
from capevo.baselines.offline_data import OfflineData, offline_data, offline_settings
from capevo.errors import Invalid
from capevo.learner.bc import torch_threads
from capevo.learner.presets import TRAIN_SEED_BASE
from capevo.runtime.tasks import task_spec

HORIZON = 10
"""H, the skill length (SPiRL: 10)."""
Z_DIM = 10
"""The skill latent's size (SPiRL: 10)."""
BETA = 5e-4
"""β of the VAE's KL term (SPiRL's kitchen configuration, ``kl_div_weight``, clvrai/spirl)."""
MAX_REPLAY = 1_000_000
"""Skill transitions kept at most (the oldest are overwritten beyond it; AM's SAC keeps as many steps)."""
TRAIN_SEEDS_PER_CELL = 10_000
"""Training episodes of cell seed ``s`` run task seeds from ``TRAIN_SEED_BASE + TRAIN_SEEDS_PER_CELL * s``,
as AM's (:data:`capevo.baselines.am.TRAIN_SEEDS_PER_CELL`): every method trains on the same seeds."""
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
OBS_CLIP = 10.0
"""Normalised observations are clipped to ±OBS_CLIP (SB3 VecNormalize's default ``clip_obs``)."""


def mlp(inputs: int, hidden: int, outputs: int, layers: int = 2) -> nn.Sequential:
    """``layers`` hidden ReLU layers of ``hidden`` units."""
    mods: list[nn.Module] = []
    width = inputs
    for _ in range(layers):
        mods += [nn.Linear(width, hidden), nn.ReLU()]
        width = hidden
    mods.append(nn.Linear(width, outputs))
    return nn.Sequential(*mods)


def gaussian(params: torch.Tensor) -> Normal:
    """A diagonal Gaussian from a network's output ``[mean, log_std]``."""
    mean, log_std = params.chunk(2, dim=-1)
    return Normal(mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).exp())


def kl(p: Normal, q: Normal) -> torch.Tensor:
    """``KL(p ‖ q)`` summed over the latent's dimensions."""
    return kl_divergence(p, q).sum(-1)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Segments:
    """H-step windows of offline or online data, one row per window.

    ``obs`` is the state the skill starts in, ``actions`` its H executed actions, ``reward`` their
    summed reward, ``next_obs`` the state after them, ``done`` whether the episode ended with
    the window's last step, ``episode`` the window's episode.
    """

    obs: np.ndarray
    actions: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    done: np.ndarray
    episode: np.ndarray

    def __len__(self) -> int:
        return len(self.obs)

    def take(self, rows: np.ndarray) -> Segments:
        return Segments(
            obs=self.obs[rows],
            actions=self.actions[rows],
            reward=self.reward[rows],
            next_obs=self.next_obs[rows],
            done=self.done[rows],
            episode=self.episode[rows],
        )

    def split(self, held_out: float, *, seed: int) -> tuple[Segments, Segments]:
        """Training and held-out windows, split by whole episodes (no episode on both sides).

        Raises:
            Invalid: fewer than two episodes, or ``held_out`` not in (0, 1).
        """
        episodes = np.unique(self.episode)
        if len(episodes) < 2 or not 0.0 < held_out < 1.0:
            raise Invalid(f"cannot hold out {held_out} of {len(episodes)} episodes", details={"field": "held_out"})
        rng = np.random.default_rng(seed)
        n = min(len(episodes) - 1, max(1, round(held_out * len(episodes))))
        out = rng.choice(episodes, size=n, replace=False)
        mask = np.isin(self.episode, out)
        return self.take(np.flatnonzero(~mask)), self.take(np.flatnonzero(mask))


def segments(data: OfflineData, horizon: int = HORIZON) -> Segments:
    """Every window of ``horizon`` consecutive steps that lies within one episode.

    Raises:
        Invalid: no episode is ``horizon`` steps long.
    """
    n = data.env_steps
    starts = [
        t for t in range(n - horizon + 1) if data.episode[t] == data.episode[t + horizon - 1]
    ]  # rows of an episode are contiguous (offline_data invariant 1)
    if not starts:
        raise Invalid(f"no episode of the offline data is {horizon} steps long", details={"field": "offline_data"})
    idx = np.asarray(starts)[:, None] + np.arange(horizon)[None, :]
    return Segments(
        obs=data.obs[idx[:, 0]],
        actions=data.action[idx],
        reward=data.reward[idx].sum(axis=1),
        next_obs=data.next_obs[idx[:, -1]],
        done=data.done[idx[:, -1]],
        episode=data.episode[idx[:, 0]],
    )


class SkillVAE(nn.Module):
    """SPiRL's skill VAE with a state-conditioned prior (see the module docstring).

    Args:
        obs_dim: The task's flat observation length.
        action_dim: The task's action dimension.
        horizon: H.
        z_dim: The latent's size.
        hidden: Hidden units of every MLP.
    """

    def __init__(self, obs_dim: int, action_dim: int, *, horizon: int = HORIZON, z_dim: int = Z_DIM, hidden: int = 128):
        super().__init__()
        self.obs_dim, self.action_dim, self.horizon, self.z_dim = obs_dim, action_dim, horizon, z_dim
        self.encoder = mlp(horizon * action_dim, hidden, 2 * z_dim)
        self.decoder = mlp(z_dim, hidden, horizon * action_dim)
        self.prior = mlp(obs_dim, hidden, 2 * z_dim)
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))

    def set_normaliser(self, obs: np.ndarray) -> None:
        """Normalise observations by the mean and standard deviation of ``obs`` (the offline data)."""
        o = torch.as_tensor(obs, dtype=torch.float32)
        self.obs_mean.copy_(o.mean(0))
        self.obs_std.copy_(o.std(0).clamp_min(1e-3))

    def normalise(self, obs: torch.Tensor) -> torch.Tensor:
        # clipped, as SB3 VecNormalize clips: a dimension almost constant in the offline data must
        # not blow up on a state outside it
        return ((obs - self.obs_mean) / self.obs_std).clamp(-OBS_CLIP, OBS_CLIP)

    def encode(self, actions: torch.Tensor) -> Normal:
        """``q(z | a_{0:H-1})`` of ``(batch, H, action_dim)`` actions."""
        return gaussian(self.encoder(actions.flatten(1)))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """The H actions of skills ``z``: ``(batch, H, action_dim)`` in [-1, 1]."""
        return torch.tanh(self.decoder(z)).view(-1, self.horizon, self.action_dim)

    def prior_of(self, obs: torch.Tensor) -> Normal:
        """``p(z | s)`` of raw observations."""
        return gaussian(self.prior(self.normalise(obs)))

    def losses(self, obs: torch.Tensor, actions: torch.Tensor, *, beta: float = BETA) -> dict[str, torch.Tensor]:
        """SPiRL's terms: ``rec`` (squared error summed over the H actions, batch mean), ``kl`` to
        N(0, I), ``prior`` (``KL(sg(q) ‖ p(z|s))``) and their sum ``total``; ``z`` the posterior sample."""
        q = self.encode(actions)
        z = q.rsample()
        rec = ((self.decode(z) - actions) ** 2).sum((1, 2)).mean()
        kl_n = kl(q, Normal(torch.zeros_like(q.loc), torch.ones_like(q.scale))).mean()
        q_sg = Normal(q.loc.detach(), q.scale.detach())
        prior = kl(q_sg, self.prior_of(obs)).mean()
        return {"rec": rec, "kl": kl_n, "prior": prior, "total": rec + beta * kl_n + prior, "z": z}

    @torch.no_grad()
    def reconstruction_error(self, seg: Segments) -> float:
        """Mean squared error per action value of reconstructing ``seg``'s actions from the posterior mean."""
        actions = torch.as_tensor(seg.actions)
        return float(((self.decode(self.encode(actions).loc) - actions) ** 2).mean())


def batches(n: int, batch: int, steps: int, generator: np.random.Generator) -> Iterator[np.ndarray]:
    """``steps`` random minibatches of row indices of ``n`` rows (with replacement across batches)."""
    for _ in range(steps):
        yield generator.integers(0, n, size=min(batch, n))


def fit(
    loss: Callable[[np.ndarray], torch.Tensor],
    params: list[nn.Parameter],
    n: int,
    *,
    steps: int,
    batch: int = 128,
    lr: float = 1e-3,
    seed: int = 0,
) -> None:
    """``steps`` Adam steps on ``loss(rows)`` of random minibatches of ``n`` rows (offline pre-training)."""
    opt = torch.optim.Adam([p for p in params if p.requires_grad], lr=lr)
    for rows in batches(n, batch, steps, np.random.default_rng(seed)):
        opt.zero_grad()
        loss(rows).backward()
        opt.step()


def fit_vae(vae: SkillVAE, seg: Segments, *, steps: int, batch: int = 128, lr: float = 1e-3, seed: int = 0) -> None:
    """Pre-train ``vae`` (encoder, decoder, prior) on ``seg`` (SPiRL §3.2: the VAE's and the prior's losses, summed)."""
    obs, actions = torch.as_tensor(seg.obs), torch.as_tensor(seg.actions)
    fit(
        lambda r: vae.losses(obs[r], actions[r])["total"],
        list(vae.parameters()),
        len(seg),
        steps=steps,
        batch=batch,
        lr=lr,
        seed=seed,
    )


class Replay:
    """Skill-level transitions ``(s, z, R, s', terminal)`` in memory: up to ``capacity``, then the
    oldest are overwritten. The arrays grow by doubling, so a large capacity costs memory only
    when the skills are there (a run stores about one per H env steps)."""

    def __init__(self, obs_dim: int, z_dim: int, capacity: int) -> None:
        self.capacity = max(1, capacity)
        n = min(self.capacity, 1024)
        self.obs = np.zeros((n, obs_dim), np.float32)
        self.z = np.zeros((n, z_dim), np.float32)
        self.reward = np.zeros(n, np.float32)
        self.next_obs = np.zeros((n, obs_dim), np.float32)
        self.terminal = np.zeros(n, np.float32)
        self.size = self.pos = 0

    def _grow(self) -> None:
        n = min(self.capacity, 2 * len(self.obs))
        for name in ("obs", "z", "reward", "next_obs", "terminal"):
            old = getattr(self, name)
            new = np.zeros((n, *old.shape[1:]), old.dtype)
            new[: len(old)] = old
            setattr(self, name, new)

    def add(self, obs: np.ndarray, z: np.ndarray, reward: float, next_obs: np.ndarray, terminal: bool) -> None:
        if self.pos == len(self.obs) and len(self.obs) < self.capacity:
            self._grow()
        self.pos %= self.capacity
        i = self.pos
        self.obs[i], self.z[i], self.reward[i], self.next_obs[i], self.terminal[i] = obs, z, reward, next_obs, terminal
        self.pos += 1
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch: int, generator: np.random.Generator) -> tuple[torch.Tensor, ...]:
        rows = generator.integers(0, self.size, size=batch)
        return tuple(torch.as_tensor(a[rows]) for a in (self.obs, self.z, self.reward, self.next_obs, self.terminal))


class SkillSAC(nn.Module):
    """SAC over skills regularised by KL to the skill prior (SPiRL §3.3; see the module docstring).

    Args:
        vae: The skill model whose prior regularises the policy and whose normaliser the
            networks use; it is not changed here.
        hidden: Hidden units of the actor and critics.
        gamma: Discount per skill (SPiRL's and SkiMo's 0.99).
        target_kl: δ, the divergence from the prior the temperature holds the policy near (SPiRL's
            kitchen configuration: 5; SkiMo's: 1).
        lr: Adam's learning rate (SAC's 3e-4).
        tau: Polyak coefficient of the target critics (SAC's 0.005).
    """

    def __init__(
        self,
        vae: SkillVAE,
        *,
        hidden: int = 128,
        gamma: float = 0.99,
        target_kl: float = 5.0,
        lr: float = 3e-4,
        tau: float = 0.005,
    ) -> None:
        super().__init__()
        self.vae = [vae]  # a list: not a submodule, so its tensors are neither saved nor updated here
        obs_dim, z_dim = vae.obs_dim, vae.z_dim
        self.actor = copy.deepcopy(vae.prior)  # SPiRL: the policy starts as the prior
        for p in self.actor.parameters():
            p.requires_grad_(True)
        self.q1, self.q2 = mlp(obs_dim + z_dim, hidden, 1), mlp(obs_dim + z_dim, hidden, 1)
        self.q1_target, self.q2_target = copy.deepcopy(self.q1), copy.deepcopy(self.q2)
        for p in [*self.q1_target.parameters(), *self.q2_target.parameters()]:
            p.requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.zeros(()))
        self.gamma, self.target_kl, self.tau = gamma, target_kl, tau
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr)
        self.critic_opt = torch.optim.Adam([*self.q1.parameters(), *self.q2.parameters()], lr=lr)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=lr)

    def policy(self, obs: torch.Tensor) -> Normal:
        """``π(z | s)`` of raw observations."""
        return gaussian(self.actor(self.vae[0].normalise(obs)))

    def q(self, obs: torch.Tensor, z: torch.Tensor, *, target: bool = False) -> torch.Tensor:
        """``min(Q1, Q2)(s, z)``."""
        x = torch.cat([self.vae[0].normalise(obs), z], -1)
        q1, q2 = (self.q1_target, self.q2_target) if target else (self.q1, self.q2)
        return torch.min(q1(x), q2(x)).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: np.ndarray, *, deterministic: bool) -> np.ndarray:
        pi = self.policy(torch.as_tensor(obs, dtype=torch.float32)[None])
        return (pi.mean if deterministic else pi.sample())[0].numpy()

    def update(self, batch: tuple[torch.Tensor, ...]) -> dict[str, float]:
        """One gradient step of critics, actor and temperature on ``(s, z, R, s', terminal)``."""
        obs, z, reward, next_obs, terminal = batch
        vae = self.vae[0]
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            pi_next = self.policy(next_obs)
            z_next = pi_next.sample()
            soft = self.q(next_obs, z_next, target=True) - alpha * kl(pi_next, vae.prior_of(next_obs))
            target = reward + self.gamma * (1.0 - terminal) * soft
        x = torch.cat([vae.normalise(obs), z], -1)
        critic_loss = ((self.q1(x).squeeze(-1) - target) ** 2).mean() + ((self.q2(x).squeeze(-1) - target) ** 2).mean()
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()
        pi = self.policy(obs)
        with torch.no_grad():
            prior = vae.prior_of(obs)
        divergence = kl(pi, prior)
        actor_loss = (alpha * divergence - self.q(obs, pi.rsample())).mean()
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        alpha_loss = -(self.log_alpha * (divergence.detach() - self.target_kl)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()
        with torch.no_grad():
            for net, tgt in ((self.q1, self.q1_target), (self.q2, self.q2_target)):
                for p, t in zip(net.parameters(), tgt.parameters(), strict=True):
                    t.mul_(1.0 - self.tau).add_(self.tau * p)
        return {
            "critic": float(critic_loss.detach()),
            "actor": float(actor_loss.detach()),
            "kl": float(divergence.detach().mean()),
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class SkillStep:
    """One finished skill in the env."""

    obs: np.ndarray
    z: np.ndarray
    reward: float
    next_obs: np.ndarray
    terminal: bool
    """The episode ended in success (no bootstrapping past it); a horizon cut is not terminal."""
    steps: int
    episode_over: bool


class SkillRunner:
    """Runs skills in a governed env for an exact number of env steps (see the module docstring).

    Args:
        env: The training env.
        decode: ``z`` -> its H actions, ``(H, action_dim)``.
        seed: The first episode's task seed (later episodes run the following seeds).
    """

    def __init__(self, env: GovernedTaskEnv, decode: Callable[[np.ndarray], np.ndarray], *, seed: int) -> None:
        self.env, self.decode = env, decode
        self.obs, _ = env.reset(seed=seed)
        self._queue: list[np.ndarray] = []
        self._start: np.ndarray = self.obs
        self._z = np.zeros(0, np.float32)
        self._reward = 0.0
        self._steps = 0
        self.episodes = 0
        self.successes = 0

    def run(self, steps: int, choose: Callable[[np.ndarray], np.ndarray], on_skill: Callable[[SkillStep], Any]) -> None:
        """Take exactly ``steps`` env steps, choosing a skill with ``choose(obs)`` whenever none runs.

        ``on_skill`` gets every skill that finishes (within these steps).
        """
        for _ in range(steps):
            if not self._queue:
                self._z = np.asarray(choose(self.obs), dtype=np.float32)
                self._queue = list(self.decode(self._z))
                self._start, self._reward, self._steps = self.obs, 0.0, 0
            obs, reward, terminated, truncated, info = self.env.step(self._queue.pop(0))
            self._reward += reward if np.isfinite(reward) else 0.0
            self._steps += 1
            self.obs = obs
            over = terminated or truncated
            if over or not self._queue:
                on_skill(
                    SkillStep(
                        obs=self._start,
                        z=self._z,
                        reward=self._reward,
                        next_obs=obs,
                        terminal=bool(terminated),
                        steps=self._steps,
                        episode_over=over,
                    )
                )
                self._queue = []
            if over:
                self.episodes += 1
                self.successes += bool(info.get("is_success"))
                self.obs, _ = self.env.reset()


class SkillActor:
    """A deterministic whole-task policy for :func:`~capevo.baselines.governed_env.evaluate_policy`:
    every H steps ``choose(obs)`` picks a skill, whose decoded actions then run open-loop.

    Pass :meth:`reset` as ``evaluate_policy``'s ``on_reset`` so every episode starts a new skill.
    """

    def __init__(self, choose: Callable[[np.ndarray], np.ndarray], decode: Callable[[np.ndarray], np.ndarray]):
        self.choose, self.decode = choose, decode
        self._queue: list[np.ndarray] = []

    def reset(self) -> None:
        self._queue = []

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        if not self._queue:
            self._queue = list(self.decode(self.choose(obs)))
        return self._queue.pop(0)


def decoder_of(vae: SkillVAE) -> Callable[[np.ndarray], np.ndarray]:
    """``z`` (numpy) -> its H actions (numpy, float32)."""

    @torch.no_grad()
    def decode(z: np.ndarray) -> np.ndarray:
        return vae.decode(torch.as_tensor(z, dtype=torch.float32)[None])[0].numpy()

    return decode


def flat(module: nn.Module, prefixes: tuple[str, ...]) -> tuple[tuple[str, ...], list[float]]:
    """The names of ``module``'s ``state_dict`` entries under ``prefixes`` and their values,
    flattened and concatenated in ``state_dict`` order (θ of Δπ)."""
    state = module.state_dict()
    names = tuple(k for k in state if k.startswith(prefixes) and state[k].is_floating_point())
    return names, torch.cat([state[k].detach().flatten() for k in names]).tolist()


COMMON_OPTIONS: tuple[str, ...] = (
    "batch_size",
    "hidden",
    "learning_starts",
    "offline_dir",
    "offline_episodes",
    "offline_noise",
    "pretrain_steps",
    "target_kl",
    "torch_threads",
    "updates_per_skill",
)


@dataclass(frozen=True, slots=True, kw_only=True)
class SkillOptions:
    """The options SPiRL and SkiMo share (a cell's ``options``), and SkiMo's planner's.

    Args:
        offline_episodes: Episodes of offline play (:mod:`capevo.baselines.offline_data`).
        offline_noise: σ of the noise on the scripted references' actions in the offline play.
        offline_dir: A directory to keep the offline data in, shared by the cells that name it
            (same task, seed and settings: one collection); None keeps it in the cell's directory.
        pretrain_steps: Adam steps of the offline pre-training (minibatches of 128 windows).
        hidden: Hidden units of every network.
        learning_starts: Skill transitions stored before the first gradient update.
        batch_size: Skill transitions per gradient update.
        updates_per_skill: Gradient updates per finished skill (SAC's one per step, at the skill level).
        target_kl: δ of the temperature (SPiRL's kitchen configuration: 5).
        torch_threads: CPU threads torch uses while the cell runs.
        plan_horizon: SkiMo: skills planned ahead.
        plan_samples: SkiMo: CEM samples per iteration (a quarter of them from the policy), 2 at least.
        plan_iterations: SkiMo: CEM iterations.
        model_steps: SkiMo: model fine-tuning steps per finished skill.

    Raises:
        Invalid: a value out of range, naming the option.
    """

    offline_episodes: int = 20
    offline_noise: float = 0.3
    offline_dir: str | None = None
    pretrain_steps: int = 2000
    hidden: int = 128
    learning_starts: int = 32
    batch_size: int = 64
    updates_per_skill: int = 1
    target_kl: float = 5.0
    torch_threads: int = 1
    plan_horizon: int = 3
    plan_samples: int = 64
    plan_iterations: int = 4
    model_steps: int = 1

    def __post_init__(self) -> None:
        for name in (
            "offline_episodes",
            "pretrain_steps",
            "hidden",
            "learning_starts",
            "batch_size",
            "updates_per_skill",
            "torch_threads",
            "plan_horizon",
            "plan_samples",
            "plan_iterations",
            "model_steps",
        ):
            value = getattr(self, name)
            low = {"pretrain_steps": 0, "learning_starts": 0, "model_steps": 0, "plan_samples": 2}.get(name, 1)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= 10**7:
                raise Invalid(
                    f"option {name} must be an integer from {low} to {10**7}, got {value!r}",
                    details={"field": f"options.{name}"},
                )
        for name in ("offline_noise", "target_kl"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1e3:
                raise Invalid(
                    f"option {name} must be a number from 0 to 1000, got {value!r}",
                    details={"field": f"options.{name}"},
                )
        if self.offline_dir is not None and (not isinstance(self.offline_dir, str) or not self.offline_dir):
            raise Invalid("option offline_dir must be a directory path", details={"field": "options.offline_dir"})

    @classmethod
    def parse(cls, method: str, options: Any, valid: tuple[str, ...]) -> SkillOptions:
        """Parse a cell's ``options`` for ``method``, which takes the options ``valid``.

        Raises:
            Invalid: an option ``method`` does not know (naming it and listing the valid ones), or a bad value.
        """
        unknown = sorted(k for k in options if k not in valid)
        if unknown:
            raise Invalid(
                f"{method}: unknown option {unknown[0]!r}; valid: {', '.join(valid)}",
                details={"field": f"options.{unknown[0]}", "valid": list(valid)},
            )
        return cls(**dict(options))


def cell_offline_data(cell: CellSpec, workdir: Path, opts: SkillOptions, *, horizon: int) -> OfflineData:
    """The cell's offline play data: ``workdir/offline.npz``, or in ``opts.offline_dir`` under a
    name made of the task, the seed and a hash of the settings (so cells with equal settings share it).

    Raises:
        Conflict, Corrupt: as :func:`~capevo.baselines.offline_data.offline_data`.
    """
    settings = offline_settings(
        cell.task,
        episodes=opts.offline_episodes,
        seed=cell.seed,
        noise=opts.offline_noise,
        phi=cell.phi,
        governance=cell.governance,
        perturbations=cell.perturbations,
        horizon=horizon,
    )
    if opts.offline_dir is None:
        return offline_data(Path(workdir) / "offline.npz", settings)
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]
    return offline_data(Path(opts.offline_dir) / f"{settings['task']}-s{cell.seed}-{digest}.npz", settings)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SkillAgent:
    """What a skill method builds from its pre-training, for :meth:`SkillMethod.run`'s loop.

    ``modules`` holds every tensor (``vae`` among them), saved as the checkpoints and read for
    Δπ; ``explore`` and ``exploit`` choose a skill for an observation while training and in the
    evaluation; ``learn`` takes every finished training skill; ``new_episode`` is called at
    every evaluation episode's start; ``progress`` describes the updates so far; ``setup`` is
    iteration 1's note on the pre-training.
    """

    modules: nn.ModuleDict
    setup: str
    explore: Callable[[np.ndarray], np.ndarray]
    exploit: Callable[[np.ndarray], np.ndarray]
    learn: Callable[[SkillStep], None]
    progress: Callable[[], str]
    new_episode: Callable[[], None] = lambda: None


class SkillMethod:
    """The iteration loop SPiRL and SkiMo share; a method fills in :meth:`_pretrain` (the hook).

    :meth:`run` parses the options, gets the offline data (:func:`cell_offline_data`), cuts it
    into H-step windows, lets :meth:`_pretrain` build the method's :class:`SkillAgent`, and then
    per iteration: exactly ``budget.env_steps_per_iteration`` training env steps through a
    :class:`SkillRunner`, a checkpoint (``iteration-NNN.pt``; ``pretrained.pt`` before the
    first), Δπ over :attr:`delta_tensors` against the end of pre-training, the held-out
    evaluation on :meth:`CellSpec.eval_seeds` (traced to ``traces/eval-NNN.mcap``) and ``emit``.
    Iteration 1's ``wall_s`` includes collecting the offline data and pre-training; its notes
    give both separately.
    """

    name: ClassVar[str]
    knowledge: ClassVar[str]
    valid_options: ClassVar[tuple[str, ...]] = COMMON_OPTIONS
    delta_tensors: ClassVar[tuple[str, ...]]

    @classmethod
    def knowledge_of(cls, options: Mapping[str, Any]) -> str:
        """What a cell with ``options`` starts from (the report's fairness column).

        Raises:
            Invalid: as :meth:`SkillOptions.parse`.
        """
        opts = SkillOptions.parse(cls.name, options, cls.valid_options)
        return (
            f"offline play data: {opts.offline_episodes} episodes of scripted references with action noise "
            f"σ {opts.offline_noise:g} (T1-T3) and random play, collected in the governed env before iteration 1"
        )

    def options(self, cell: CellSpec) -> SkillOptions:
        """The cell's options.

        Raises:
            Invalid: an unknown option or a bad value.
        """
        return SkillOptions.parse(self.name, cell.options, self.valid_options)

    def _pretrain(self, cell: CellSpec, data: OfflineData, seg: Segments, opts: SkillOptions) -> SkillAgent:
        """Learn from the offline data; return the agent the loop runs (the method's hook)."""
        raise NotImplementedError

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit) -> None:
        """Run ``cell`` for ``cell.iterations`` iterations, emitting a record after each.

        Raises:
            Invalid: a bad option, or offline data without one H-step window.
            Conflict, Corrupt: as :func:`cell_offline_data`.
        """
        opts = self.options(cell)
        budget = cell.budget.env_steps_per_iteration
        horizon = cell.budget.horizon if cell.budget.horizon is not None else task_spec(cell.task).default_horizon
        workdir = Path(workdir)
        workdir.mkdir(parents=True, exist_ok=True)
        with contextlib.ExitStack() as stack:
            stack.enter_context(torch_threads(opts.torch_threads))
            torch.manual_seed(cell.seed)
            started = time.perf_counter()
            data = cell_offline_data(cell, workdir, opts, horizon=horizon)
            collected = time.perf_counter()
            seg = segments(data)
            agent = self._pretrain(cell, data, seg, opts)
            vae = agent.modules["vae"]
            for p in vae.parameters():  # the skills and the prior are frozen downstream
                p.requires_grad_(False)
            pretrained = time.perf_counter()
            torch.save(agent.modules.state_dict(), workdir / "pretrained.pt")
            _, theta0 = flat(agent.modules, self.delta_tensors)
            setup = (
                f"{data.describe()}, {collected - started:.1f} s; {agent.setup}, {pretrained - collected:.1f} s "
                f"(both in this iteration's wall_s); Δπ over {', '.join(p + '*' for p in self.delta_tensors)} "
                f"({len(theta0)} values)"
            )
            env = GovernedTaskEnv(
                cell.task, phi=cell.phi, governance=cell.governance, perturbations=cell.perturbations, horizon=horizon
            )
            stack.callback(env.close)
            decode = decoder_of(vae)
            runner = SkillRunner(env, decode, seed=TRAIN_SEED_BASE + TRAIN_SEEDS_PER_CELL * cell.seed)
            actor = SkillActor(agent.exploit, decode)

            def new_episode() -> None:
                actor.reset()
                agent.new_episode()

            for iteration in range(1, cell.iterations + 1):
                if iteration > 1:
                    started = time.perf_counter()
                before = env.env_steps
                runner.run(budget, agent.explore, agent.learn)
                spent = env.env_steps - before
                torch.save(agent.modules.state_dict(), workdir / f"iteration-{iteration:03d}.pt")
                delta = policy_drift(theta0, flat(agent.modules, self.delta_tensors)[1])
                notes = [setup] if iteration == 1 else []
                notes.append(agent.progress())
                emit(
                    held_out_record(
                        cell,
                        actor,
                        iteration=iteration,
                        env_steps_train=spent,
                        delta_pi=delta,
                        started=started,
                        notes=notes,
                        workdir=workdir,
                        label=self.name,
                        horizon=horizon,
                        on_reset=new_episode,
                    )
                )
