"""SPiRL: skill priors from offline play, SAC in skill space regularised by the prior (issue 20, paper §4.1).

The paper's SPiRL baseline ("offline skill priors with downstream RL that fine-tunes a
skill-conditioned policy", §4.1 Baselines) after Pertsch et al., CoRL 2020:

1. **Offline data** (SPiRL: task-agnostic prior experience): :mod:`capevo.baselines.offline_data`
   collects ``offline_episodes`` episodes of scripted and random play in the cell's governed env,
   once per cell (reused when the file is there). Their env steps are this method's starting
   knowledge, reported in iteration 1's ``notes``, not part of any iteration's budget.
2. **Skill pre-training** (SPiRL §3.2): :class:`~capevo.baselines.skills.SkillVAE`
   over H = 10-step action windows of that data, with the state-conditioned skill prior
   ``p(z|s)``, for ``pretrain_steps`` Adam steps. Then the decoder and the prior are frozen.
3. **Downstream RL** (SPiRL §3.3): :class:`~capevo.baselines.skills.SkillSAC`: a
   high-level policy ``π(z|s)`` (initialised as the prior) picks a skill every H steps, the
   frozen decoder turns it into H actions, rewards are summed over the skill, and the policy is
   regularised by ``KL(π ‖ p)`` with an automatically tuned temperature.

Every iteration (:class:`~capevo.baselines.skills.SkillMethod`'s loop) takes exactly
``budget.env_steps_per_iteration`` env steps in the governed env (a skill cut at the end of an
iteration finishes at the start of the next), with ``updates_per_skill`` gradient updates per
finished skill once ``learning_starts`` skills are stored, then the held-out evaluation on
:meth:`CellSpec.eval_seeds` with the policy's mean skill, decoded open-loop (its trace:
``traces/eval-NNN.mcap``), then ``emit``.

Δπ (issue 20: "Δπ counts the frozen pre-trained part; name which tensors"): the relative change
(:func:`capevo.agent.policy_drift`) of ``vae.decoder.*`` (the skills) and ``vae.prior.*`` (the
skill prior) since the end of pre-training. They are frozen downstream, so Δπ is 0 by
construction, as the paper reports for SPiRL ("each of these methods deliberately freezes the
agent's decision policy", §4.4). The high-level policy (``sac.actor.*``) does move; its drift is
reported in every record's ``notes`` and not counted.

Simplified for CPU budgets (besides :mod:`capevo.baselines.skills`'): the data is tens of
episodes, not SPiRL's hundreds of thousands of steps; pre-training is thousands of steps, not
SPiRL's hundreds of epochs; one update per skill, networks of 128 units. With the CI budgets
(tens of steps per iteration) only the accounting can be checked, not learning.

Invariants:
1. Each record's ``env_steps_train`` is the env steps the iteration took, and equals the budget.
2. Each record's episodes are the held-out evaluation on ``cell.eval_seeds()``, in order.
3. ``delta_pi`` is measured over the frozen tensors named above, so it is 0.0.
4. An unknown or bad option raises :class:`Invalid` naming it, before any simulator is built.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from capevo.agent import policy_drift
from capevo.baselines.base import CellSpec
from capevo.baselines.offline_data import OfflineData
from capevo.baselines.skills import (
    MAX_REPLAY,
    Replay,
    Segments,
    SkillAgent,
    SkillMethod,
    SkillOptions,
    SkillSAC,
    SkillStep,
    SkillVAE,
    fit_vae,
    flat,
)

KNOWLEDGE = "offline play data (scripted references with action noise on T1-T3, random play)"
FROZEN_TENSORS: tuple[str, ...] = ("vae.decoder.", "vae.prior.")
"""The ``state_dict`` prefixes Δπ is measured over: the frozen skills and skill prior."""
POLICY_TENSORS: tuple[str, ...] = ("sac.actor.",)
"""The high-level policy's tensors: they move, and their drift is reported in the notes."""


class Spirl(SkillMethod):
    """The SPiRL baseline (see the module docstring).

    Options (``cell.options``; :class:`~capevo.baselines.skills.SkillOptions`): ``offline_episodes``,
    ``offline_noise``, ``offline_dir``, ``pretrain_steps``, ``hidden``, ``learning_starts``,
    ``batch_size``, ``updates_per_skill``, ``target_kl``, ``torch_threads``.
    """

    name: ClassVar[str] = "spirl"
    knowledge: ClassVar[str] = KNOWLEDGE
    delta_tensors: ClassVar[tuple[str, ...]] = FROZEN_TENSORS

    def _pretrain(self, cell: CellSpec, data: OfflineData, seg: Segments, opts: SkillOptions) -> SkillAgent:
        import torch

        vae = SkillVAE(data.obs.shape[1], data.action.shape[1], hidden=opts.hidden)
        vae.set_normaliser(data.obs)
        before = vae.reconstruction_error(seg)
        fit_vae(vae, seg, steps=opts.pretrain_steps, seed=cell.seed)
        after = vae.reconstruction_error(seg)
        for p in vae.parameters():
            p.requires_grad_(False)
        sac = SkillSAC(vae, hidden=opts.hidden, target_kl=opts.target_kl)
        modules = torch.nn.ModuleDict({"vae": vae, "sac": sac})
        _, actor0 = flat(modules, POLICY_TENSORS)
        replay = Replay(
            vae.obs_dim, vae.z_dim, capacity=min(MAX_REPLAY, cell.budget.env_steps_per_iteration * cell.iterations)
        )
        rng = np.random.default_rng(cell.seed)
        updates = [0]

        def learn(step: SkillStep) -> None:
            replay.add(step.obs, step.z, step.reward, step.next_obs, step.terminal)
            if replay.size >= max(1, opts.learning_starts):
                for _ in range(opts.updates_per_skill):
                    sac.update(replay.sample(opts.batch_size, rng))
                    updates[0] += 1

        def progress() -> str:
            moved = policy_drift(actor0, flat(modules, POLICY_TENSORS)[1])
            return (
                f"{updates[0]} SAC updates so far, {replay.size} skills stored; the high-level policy "
                f"(sac.actor.*, not counted in Δπ) moved {moved:.4g}"
            )

        return SkillAgent(
            modules=modules,
            setup=(
                f"skill VAE and prior pre-trained {opts.pretrain_steps} steps on {len(seg)} windows "
                f"(reconstruction MSE {before:.4g} -> {after:.4g})"
            ),
            explore=lambda obs: sac.act(obs, deterministic=False),
            exploit=lambda obs: sac.act(obs, deterministic=True),
            learn=learn,
            progress=progress,
        )
