"""SPiRL: skill priors from offline play, SAC in skill space regularised by the prior (issue 20, paper §4.1).

The paper's SPiRL baseline ("offline skill priors with downstream RL that fine-tunes a
skill-conditioned policy", §4.1 Baselines) after Pertsch et al., CoRL 2020:

1. **Offline data** (SPiRL §3, §5.1: task-agnostic play): :mod:`capevo.baselines.offline_data`
   collects ``offline_episodes`` episodes of scripted and random play in the cell's governed env,
   once per cell (reused when the file is there). Their env steps are this method's starting
   knowledge, reported in iteration 1's ``notes``, not part of any iteration's budget.
2. **Skill pre-training** (SPiRL §3.1-3.2, eq. 1-2): :class:`~capevo.baselines.skills.SkillVAE`
   over H = 10-step action windows of that data, with the state-conditioned skill prior
   ``p(z|s)``, for ``pretrain_steps`` Adam steps. Then the decoder and the prior are frozen.
3. **Downstream RL** (SPiRL §3.3, eq. 4-5): :class:`~capevo.baselines.skills.SkillSAC`: a
   high-level policy ``π(z|s)`` (initialised as the prior) picks a skill every H steps, the
   frozen decoder turns it into H actions, rewards are summed over the skill, and the policy is
   regularised by ``KL(π ‖ p)`` with an automatically tuned temperature.

Every iteration takes exactly ``budget.env_steps_per_iteration`` env steps in the governed env
(a skill cut at the end of an iteration finishes at the start of the next), one gradient update
per finished skill once ``learning_starts`` skills are stored, then the held-out evaluation on
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

import contextlib
import time
from pathlib import Path
from typing import ClassVar

from capevo.baselines.base import CellSpec, Emit, IterationRecord
from capevo.baselines.governed_env import GovernedTaskEnv, evaluate_policy
from capevo.baselines.skills import COMMON_OPTIONS, SkillOptions
from capevo.runtime.tasks import task_spec

OPTIONS: tuple[str, ...] = COMMON_OPTIONS
KNOWLEDGE = "offline play data (scripted references with noise + random play; steps in iteration 1's notes)"
FROZEN_TENSORS: tuple[str, ...] = ("vae.decoder.", "vae.prior.")
"""The ``state_dict`` prefixes Δπ is measured over: the frozen skills and skill prior."""
POLICY_TENSORS: tuple[str, ...] = ("sac.actor.",)


class Spirl:
    """The SPiRL baseline (see the module docstring)."""

    name: ClassVar[str] = "spirl"
    knowledge: ClassVar[str] = KNOWLEDGE

    def options(self, cell: CellSpec) -> SkillOptions:
        """The cell's options.

        Raises:
            Invalid: an unknown option or a bad value.
        """
        return SkillOptions.parse(self.name, cell.options, OPTIONS)

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit) -> None:
        """Run ``cell`` for ``cell.iterations`` iterations, emitting a record after each.

        Raises:
            Invalid: a bad option, or offline data without one H-step window.
        """
        import numpy as np
        import torch

        from capevo.agent import policy_drift
        from capevo.baselines.am import TRAIN_SEEDS_PER_CELL
        from capevo.baselines.skills import (
            Replay,
            SkillActor,
            SkillRunner,
            SkillSAC,
            SkillStep,
            SkillVAE,
            cell_offline_data,
            decoder_of,
            fit_vae,
            flat,
            segments,
        )
        from capevo.learner.bc import torch_threads
        from capevo.learner.presets import TRAIN_SEED_BASE

        opts = self.options(cell)
        budget = cell.budget.env_steps_per_iteration
        horizon = cell.budget.horizon if cell.budget.horizon is not None else task_spec(cell.task).default_horizon
        workdir = Path(workdir)
        workdir.mkdir(parents=True, exist_ok=True)
        with contextlib.ExitStack() as stack:
            stack.enter_context(torch_threads(opts.torch_threads))
            torch.manual_seed(cell.seed)
            data = cell_offline_data(cell, workdir, opts, horizon=horizon)
            seg = segments(data)
            vae = SkillVAE(data.obs.shape[1], data.action.shape[1], hidden=opts.hidden)
            vae.set_normaliser(data.obs)
            rec_before = vae.reconstruction_error(seg)
            fit_vae(vae, seg, steps=opts.pretrain_steps, seed=cell.seed)
            rec_after = vae.reconstruction_error(seg)
            for p in vae.parameters():
                p.requires_grad_(False)
            sac = SkillSAC(vae, hidden=opts.hidden, target_kl=opts.target_kl)
            both = torch.nn.ModuleDict({"vae": vae, "sac": sac})
            torch.save(both.state_dict(), workdir / "pretrained.pt")
            _, theta0 = flat(both, FROZEN_TENSORS)
            _, actor0 = flat(both, POLICY_TENSORS)
            setup = (
                f"{data.describe()}; skill VAE pre-trained {opts.pretrain_steps} steps on {len(seg)} windows "
                f"(reconstruction MSE {rec_before:.4g} -> {rec_after:.4g}); "
                f"Δπ over {', '.join(p + '*' for p in FROZEN_TENSORS)} ({len(theta0)} values, frozen)"
            )
            env = GovernedTaskEnv(
                cell.task, phi=cell.phi, governance=cell.governance, perturbations=cell.perturbations, horizon=horizon
            )
            stack.callback(env.close)
            decode = decoder_of(vae)
            runner = SkillRunner(env, decode, seed=TRAIN_SEED_BASE + TRAIN_SEEDS_PER_CELL * cell.seed)
            replay = Replay(vae.obs_dim, vae.z_dim, capacity=max(1, budget * cell.iterations))
            rng = np.random.default_rng(cell.seed)
            updates = 0

            def learn(step: SkillStep) -> None:
                nonlocal updates
                replay.add(step.obs, step.z, step.reward, step.next_obs, step.terminal)
                if replay.size >= max(1, opts.learning_starts):
                    for _ in range(opts.updates_per_skill):
                        sac.update(replay.sample(opts.batch_size, rng))
                        updates += 1

            actor = SkillActor(lambda o: sac.act(o, deterministic=True), decode)
            for iteration in range(1, cell.iterations + 1):
                started = time.perf_counter()
                before, updates_before = env.env_steps, updates
                runner.run(budget, lambda o: sac.act(o, deterministic=False), learn)
                spent = env.env_steps - before
                torch.save(both.state_dict(), workdir / f"iteration-{iteration:03d}.pt")
                delta = policy_drift(theta0, flat(both, FROZEN_TENSORS)[1])
                notes = [setup] if iteration == 1 else []
                notes.append(
                    f"{updates - updates_before} SAC updates, {replay.size} skills stored; high-level policy "
                    f"(sac.actor.*, not counted) moved {policy_drift(actor0, flat(both, POLICY_TENSORS)[1]):.4g}"
                )
                episodes, eval_steps = evaluate_policy(
                    cell.task,
                    actor,
                    cell.eval_seeds(),
                    phi=cell.phi,
                    governance=cell.governance,
                    perturbations=cell.perturbations,
                    horizon=horizon,
                    trace=workdir / "traces" / f"eval-{iteration:03d}.mcap",
                    label=self.name,
                    version=iteration,
                    on_reset=actor.reset,
                )
                emit(
                    IterationRecord(
                        iteration=iteration,
                        episodes=episodes,
                        env_steps_train=spent,
                        env_steps_eval=eval_steps,
                        delta_pi=delta,
                        wall_s=time.perf_counter() - started,
                        notes="; ".join(notes),
                    )
                )
