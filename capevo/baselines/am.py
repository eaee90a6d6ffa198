"""Agent Modification (AM): one monolithic policy for the whole task, updated every iteration.

The paper's first baseline (§4.1 "Experimental Setup", Baselines: "a single monolithic PPO
policy updated each iteration; no ECMs"; issue 20). There is no persistent agent and no ECM: the
policy network *is* the agent's decision policy, so every update moves it, and Δπ (§4.4
"Identity Preservation") measures how far.

What is learned and what is hand-written: everything the policy does is learned, from random
weights (:attr:`AgentModification.knowledge`), by stable-baselines3's PPO (default, as the
paper) or SAC (option ``algo: sac``). Nothing of the task's structure reaches it except through
the task's dense reward and observation. With ``warm_start: bc`` it first clones the task's
version-0 code ECMs (:mod:`capevo.baselines.demos`), the same hand-written skills our method
starts from, so that the comparison with code ECMs does not rest on knowledge only one side had
(:class:`AgentModificationBC`, knowledge "random weights + BC from v0 skill demos").

It acts in :class:`~capevo.baselines.governed_env.GovernedTaskEnv`: the cell's task, Φ,
governance and perturbations, every step graded by the independent safety monitor, exactly as
ours runs.

What it sees, against ours (issue 20, "Fairness"): the task's flat observation (positions with
the perturbations' noise) and the task's dense reward (robosuite's shaped reward, computed from
the simulator's exact state). Ours hands off between ECMs on predicates over the task's exact
simulator signals (``TaskSpec.signals``: for T1 ``grasped`` and the can's height, for T6 the
peg-hole distances and angle, and ``success``). By default AM does not observe those signals, and
the report names that asymmetry; option ``handoff_signals: true`` appends exactly the signals
ours hands off on (``TaskSpec.handoff_signals``) to AM's observation, so that both sides see the
same information (not with ``warm_start: bc``: the v0 demonstrations' traces do not hold them).

One iteration:

1. ``learn`` for exactly ``budget.env_steps_per_iteration`` env steps, counted from
   ``env.env_steps`` (the steps recorded are those counted, never the requested number).
   PPO collects whole rollouts of ``n_steps``, so ``n_steps`` is the divisor of the budget
   nearest the ``n_steps`` option (SB3's 2048): every iteration is a whole number of
   rollouts. When an iteration's learning steps are not a multiple of it (only iteration 1
   with ``warm_start: bc``), the last rollout is cut at the budget and PPO does not train on
   it: those steps are spent, not used, and the record's ``notes`` say how many (SB3 also
   keeps the observation from before the cut step, so the next iteration's first action sees
   one stale observation). SAC stores every step and, after SB3's 100 random warm-up steps
   (``learning_starts``), takes one gradient step per env step: with fewer than 100 steps in
   all it does not train, and Δπ stays 0.
2. Save a checkpoint, ``checkpoints/iteration-NNN.zip`` (``iteration-000``: the initial weights);
   an interrupted PPO cell resumes from the last one (:meth:`AgentModification.run`).
3. The held-out evaluation: one episode per seed of :meth:`CellSpec.eval_seeds` with the
   deterministic policy (:func:`~capevo.baselines.governed_env.evaluate_policy`); its steps are
   ``env_steps_eval``, outside the budget. Its trace is ``traces/eval-NNN.mcap`` (the
   runtime's record types; ``/env/step``'s ``ecm`` is the method's name, ``version`` the
   iteration); training steps are not traced.
4. ``emit`` the :class:`~capevo.baselines.base.IterationRecord`.

Δπ (paper §4.1, Metrics; §4.4): ``‖θ_i − θ_0‖₂ / ‖θ_0‖₂`` by
:func:`capevo.agent.policy_drift`, θ the concatenation of the tensors that compute the
deterministic action (the decision), in ``state_dict`` order, and θ_0 the freshly initialised
weights (before any cloning):

* PPO: ``policy.mlp_extractor.policy_net.*`` and ``policy.action_net.*``; not ``log_std``
  (exploration noise only), ``mlp_extractor.value_net.*`` nor ``value_net.*`` (the critic);
* SAC: ``policy.actor.latent_pi.*`` and ``policy.actor.mu.*``; not ``actor.log_std.*``
  (exploration noise only), ``critic.*`` nor ``critic_target.*``.

Budget of the warm start: the demonstrations are env steps, so they are charged to iteration
1: it collects ``n`` v0 episodes first (``n = min(bc_episodes, budget // horizon)``, so they
cannot overrun the budget), clones, and learns for the rest of the budget. Iteration 1's
``env_steps_train`` includes the demonstration steps; its ``notes`` give them separately, with
the cloning loss before and after and the Δπ the cloning alone caused. Cloning reuses
:func:`capevo.learner.bc.behaviour_clone` (option ``bc_loss``: ``mse`` between the
deterministic action and the demonstrated one, the default, or ``nll``, which also fits the
exploration noise); for PPO through an adapter that shows it the actor under SAC's attribute
names (:func:`bc_view`).

Simplified for CPU budgets: one environment (no ``SubprocVecEnv``), no observation
normalisation, SB3's default hyperparameters except where named here (PPO's rollout length and
minibatch divide the budget and the rollout; SAC's replay buffer holds the whole run, at most
10^6 steps; the paper names no hyperparameters for its PPO). The paper's budget is 50,000 env
steps per ECM per iteration; the CI budgets of the tests (tens of steps) check the accounting
and Δπ and cannot show learning.

Invariants:
1. Each record's ``env_steps_train`` is the env steps the iteration took (``env.env_steps``
   before and after, plus the demonstrations in iteration 1), and equals the budget.
2. Each record's episodes are the held-out evaluation on ``cell.eval_seeds()``, in order.
3. ``delta_pi`` is 0.0 exactly for unchanged weights and never negative.
4. An unknown or bad option raises :class:`Invalid` naming it, before any simulator is built.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import numpy as np

from capevo.baselines.base import CellSpec, Emit
from capevo.baselines.governed_env import GovernedTaskEnv, held_out_record
from capevo.errors import Invalid
from capevo.learner.bc import LOSSES
from capevo.learner.neural_seed import silent_logger
from capevo.learner.presets import TRAIN_SEED_BASE
from capevo.runtime.tasks import task_spec

ALGOS: tuple[str, ...] = ("ppo", "sac")
WARM_STARTS: tuple[str, ...] = ("none", "bc")
OPTIONS: tuple[str, ...] = (
    "algo",
    "bc_epochs",
    "bc_episodes",
    "bc_loss",
    "handoff_signals",
    "n_steps",
    "net_arch",
    "torch_threads",
    "warm_start",
)
KNOWLEDGE = "random weights"
KNOWLEDGE_BC = "random weights + BC from v0 skill demos"
TRAIN_SEEDS_PER_CELL = 10_000
"""Training task seeds of cell seed ``s`` start at ``TRAIN_SEED_BASE + TRAIN_SEEDS_PER_CELL * s``:
at most about 1e9, far below the held-out evaluation seeds (:data:`capevo.baselines.base.HELD_OUT_SEED_BASE`)."""
DEMO_SEED_BASE = 1_500_000_000
"""Task seeds of the warm start's demonstration episodes: ``DEMO_SEED_BASE + 1000 * s + j``,
above every training seed and below the held-out ones."""
MAX_REPLAY = 1_000_000
PPO_MINIBATCH = 64
"""SB3's default PPO minibatch size."""
DECISION_TENSORS: Mapping[str, tuple[str, ...]] = {
    "ppo": ("mlp_extractor.policy_net.", "action_net."),
    "sac": ("actor.latent_pi.", "actor.mu."),
}
"""Per algorithm, the ``policy.state_dict()`` prefixes of the tensors Δπ is measured over."""


def _positive(name: str, value: object, *, high: int = 10**9) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= high:
        raise Invalid(
            f"am: option {name} must be an integer from 1 to {high}, got {value!r}",
            details={"field": f"options.{name}"},
        )
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class AmOptions:
    """The options of :class:`AgentModification` (a cell's ``options``).

    Args:
        algo: ``ppo`` (default, as the paper) or ``sac``.
        warm_start: ``none`` or ``bc`` (clone the task's v0 code ECMs before iteration 1).
        bc_episodes: Demonstration episodes of the warm start, at most (see the module docstring).
        bc_epochs: Passes of the cloning over the demonstrations.
        bc_loss: ``mse`` (the deterministic action; the exploration noise is left as it was) or
            ``nll`` (the demonstrated action's likelihood: fits the noise's spread as well).
        net_arch: Hidden layer sizes of the policy (and critic); None for SB3's default
            (PPO 64-64, SAC 256-256).
        n_steps: PPO's target rollout length (the budget's divisor nearest it is used).
        torch_threads: CPU threads torch uses while the cell runs.
        handoff_signals: Observe the exact signals our hand-off predicates read, too.

    Raises:
        Invalid: a value out of range, naming the option.
    """

    algo: str = "ppo"
    warm_start: str = "none"
    bc_episodes: int = 10
    bc_epochs: int = 50
    bc_loss: str = "mse"
    net_arch: tuple[int, ...] | None = None
    n_steps: int = 2048
    torch_threads: int = 1
    handoff_signals: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.handoff_signals, bool):
            raise Invalid(
                f"am: option handoff_signals must be true or false, got {self.handoff_signals!r}",
                details={"field": "options.handoff_signals"},
            )
        if self.handoff_signals and self.warm_start == "bc":
            raise Invalid(
                "am: option handoff_signals cannot go with warm_start bc (the v0 demonstrations hold no signals)",
                details={"field": "options.handoff_signals"},
            )
        for name, valid in (("algo", ALGOS), ("warm_start", WARM_STARTS), ("bc_loss", LOSSES)):
            value = getattr(self, name)
            if value not in valid:
                raise Invalid(
                    f"am: option {name} must be one of {', '.join(valid)}, got {value!r}",
                    details={"field": f"options.{name}", "valid": list(valid)},
                )
        _positive("bc_episodes", self.bc_episodes, high=10_000)
        _positive("bc_epochs", self.bc_epochs, high=100_000)
        _positive("n_steps", self.n_steps)
        _positive("torch_threads", self.torch_threads, high=256)
        if self.net_arch is not None:
            arch = self.net_arch
            if isinstance(arch, (str, bytes)) or not isinstance(arch, (tuple, list)) or not arch:
                raise Invalid(
                    f"am: option net_arch must be a list of layer sizes, got {arch!r}",
                    details={"field": "options.net_arch"},
                )
            object.__setattr__(self, "net_arch", tuple(_positive("net_arch", n, high=65_536) for n in arch))

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> AmOptions:
        """Parse a cell's ``options``.

        Raises:
            Invalid: an option AM does not know (naming it and listing the valid ones), or a bad value.
        """
        unknown = sorted(k for k in options if k not in OPTIONS)
        if unknown:
            raise Invalid(
                f"am: unknown option {unknown[0]!r}; valid: {', '.join(OPTIONS)}",
                details={"field": f"options.{unknown[0]}", "valid": list(OPTIONS)},
            )
        return cls(**dict(options))


def nearest_divisor(n: int, target: int) -> int:
    """The divisor of ``n`` (at least 2) nearest ``target`` on a log scale, the larger on a tie; ``n`` for ``n < 2``."""
    divisors = [d for i in range(1, math.isqrt(n) + 1) if n % i == 0 for d in (i, n // i) if d >= 2]
    return min(divisors, key=lambda d: (abs(math.log(d / target)), -d)) if divisors else n


def rollout_length(budget: int, target: int) -> int:
    """PPO's ``n_steps`` for ``budget`` steps per iteration: the divisor of ``budget`` nearest ``target``.

    Raises:
        Invalid: ``budget`` below 2 (PPO needs two steps per rollout).
    """
    if budget < 2:
        raise Invalid(
            f"budget.env_steps_per_iteration {budget} is too small for PPO (2 steps per rollout at least)",
            details={"field": "budget.env_steps_per_iteration"},
        )
    return nearest_divisor(budget, target)


def minibatch_size(n_steps: int) -> int:
    """PPO's minibatch for rollouts of ``n_steps``: a divisor near SB3's 64 when there is one
    from 16 to 256 (no truncated last minibatch), else ``min(64, n_steps)``."""
    size = nearest_divisor(n_steps, PPO_MINIBATCH)
    return size if 16 <= size <= 256 else min(PPO_MINIBATCH, n_steps)


def decision_names(model: Any, algo: str) -> tuple[str, ...]:
    """The ``policy.state_dict()`` names of the tensors Δπ is measured over (see the module docstring)."""
    prefixes = DECISION_TENSORS[algo]
    return tuple(k for k in model.policy.state_dict() if k.startswith(prefixes))


def decision_vector(model: Any, algo: str) -> list[float]:
    """θ: the decision tensors of ``model``, flattened and concatenated in ``state_dict`` order."""
    state = model.policy.state_dict()
    return np.concatenate([state[k].detach().cpu().numpy().ravel() for k in decision_names(model, algo)]).tolist()


def bc_view(model: Any, algo: str) -> Any:
    """``model`` as :func:`capevo.learner.bc.behaviour_clone` and ``imitation_loss`` take it.

    A SAC model is taken as it is. For PPO, an object with SAC's attribute names: ``actor`` is a
    torch module over ``mlp_extractor.policy_net``, ``action_net`` and ``log_std`` whose
    deterministic output is the Gaussian's mean (what PPO's deterministic ``predict`` returns
    before clipping to the action box) and whose ``get_action_dist_params`` and ``action_dist``
    are PPO's Gaussian, so the ``mse`` loss changes exactly the tensors Δπ measures and ``nll``
    the exploration noise's ``log_std`` as well.
    """
    if algo == "sac":
        return model
    import torch

    policy = model.policy

    class PpoActor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.policy_net = policy.mlp_extractor.policy_net
            self.action_net = policy.action_net
            self.log_std = policy.log_std
            self.action_dist = policy.action_dist

        def forward(self, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
            features = policy.extract_features(obs, policy.pi_features_extractor)
            return self.action_net(self.policy_net(features))

        def get_action_dist_params(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, dict]:
            return self(obs), self.log_std, {}

    return SimpleNamespace(
        actor=PpoActor(), policy=policy, observation_space=model.observation_space, action_space=model.action_space
    )


def _make_model(opts: AmOptions, env: GovernedTaskEnv, *, seed: int, budget: int, iterations: int) -> tuple[Any, str]:
    policy_kwargs: dict[str, Any] = {}
    if opts.net_arch is not None:
        policy_kwargs["net_arch"] = list(opts.net_arch)
    if opts.algo == "ppo":
        from stable_baselines3 import PPO

        n_steps = rollout_length(budget, opts.n_steps)
        model = PPO(
            "MlpPolicy",
            env,
            n_steps=n_steps,
            batch_size=minibatch_size(n_steps),
            policy_kwargs=policy_kwargs,
            seed=seed,
            device="cpu",
            verbose=0,
        )
        return model, f"ppo, n_steps {n_steps}, minibatch {model.batch_size}"
    from stable_baselines3 import SAC

    buffer = min(MAX_REPLAY, budget * iterations)
    model = SAC("MlpPolicy", env, buffer_size=buffer, policy_kwargs=policy_kwargs, seed=seed, device="cpu", verbose=0)
    return model, f"sac, replay {buffer}"


def _resume(
    model: Any, opts: AmOptions, env: GovernedTaskEnv, checkpoints: Path, after: int, *, seed: int
) -> tuple[Any, list[float]]:
    """The model of ``checkpoints/iteration-<after>.zip`` on ``env`` and θ_0 (``iteration-000``)."""
    if opts.algo != "ppo":
        raise Invalid("am resumes only with PPO (SAC's replay buffer is not saved)", details={"field": "options.algo"})
    path = checkpoints / f"iteration-{after:03d}.zip"
    if not path.is_file() or not (checkpoints / "iteration-000.zip").is_file():
        raise Invalid(f"am cannot resume after iteration {after}: {path} is missing", details={"field": "after"})
    cls = type(model)
    theta0 = decision_vector(cls.load(checkpoints / "iteration-000.zip", device="cpu"), opts.algo)
    resumed = cls.load(path, env=env, device="cpu")
    resumed.set_random_seed(seed)
    stale = checkpoints.parent / "traces" / f"eval-{after + 1:03d}.mcap"
    if stale.exists():  # the interrupted iteration's evaluation, cut short: kept, out of the way
        os.replace(stale, stale.with_name(f"eval-{after + 1:03d}.interrupted-{time.time_ns()}.mcap"))
    return resumed, theta0


def _stop_at(env: GovernedTaskEnv, limit: int) -> Any:
    """A PPO callback ending ``learn`` once ``env`` has taken ``limit`` steps in total.

    The step that reaches the limit and completes a rollout lets PPO train on it; one that
    reaches it inside a rollout ends ``learn`` there (SB3 then drops the partial rollout).
    """
    from stable_baselines3.common.callbacks import BaseCallback

    class StopAtBudget(BaseCallback):
        def _on_step(self) -> bool:
            if env.env_steps < limit:
                return True
            buffer = self.model.rollout_buffer
            # The buffer adds this step after the callback: full after it means a whole rollout.
            return buffer.pos + 1 >= buffer.buffer_size

    return StopAtBudget()


class AgentModification:
    """The AM baseline (see the module docstring): ``run`` one cell, emitting one record per iteration.

    Options (``cell.options``; :class:`AmOptions`): ``algo``, ``warm_start``, ``bc_episodes``,
    ``bc_epochs``, ``bc_loss``, ``net_arch``, ``n_steps``, ``torch_threads``.
    """

    name: ClassVar[str] = "am"
    knowledge: ClassVar[str] = KNOWLEDGE
    default_options: ClassVar[Mapping[str, Any]] = {}

    @classmethod
    def knowledge_of(cls, options: Mapping[str, Any]) -> str:
        """What a cell with ``options`` starts from (the report's fairness column).

        Raises:
            Invalid: as :meth:`AmOptions.from_options`.
        """
        opts = AmOptions.from_options({**cls.default_options, **options})
        return KNOWLEDGE_BC if opts.warm_start == "bc" else KNOWLEDGE

    def options(self, cell: CellSpec) -> AmOptions:
        """The cell's options over this method's defaults.

        Raises:
            Invalid: as :meth:`AmOptions.from_options`.
        """
        return AmOptions.from_options({**self.default_options, **cell.options})

    def resumes(self, cell: CellSpec) -> bool:
        """With PPO: its whole state is in a checkpoint (weights, optimiser, step count; a rollout
        never spans iterations). Not with SAC: its replay buffer is not saved."""
        try:
            return self.options(cell).algo == "ppo"
        except Invalid:
            return False

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit, after: int = 0) -> None:
        """Run ``cell``'s iterations ``after + 1 ..``, emitting a record after each.

        ``after`` > 0 continues an interrupted cell (PPO only, :meth:`resumes`) from
        ``checkpoints/iteration-<after>.zip``; θ_0 is read from ``iteration-000.zip``. The
        continuation starts a fresh episode and reseeds the random streams with the train seed
        plus ``after`` (an uninterrupted run would have continued its episode and streams), and
        the interrupted iteration's partial evaluation trace is kept beside, renamed
        ``eval-NNN.interrupted-<ns>.mcap``.

        Raises:
            Invalid: a bad option, a budget too small for the chosen algorithm or warm start, or
                ``after`` > 0 for SAC or without its checkpoint.
        """
        from capevo.agent import policy_drift
        from capevo.learner.bc import torch_threads

        opts = self.options(cell)
        budget = cell.budget.env_steps_per_iteration
        horizon = cell.budget.horizon if cell.budget.horizon is not None else task_spec(cell.task).default_horizon
        demo_episodes = 0
        if opts.warm_start == "bc":
            demo_episodes = min(opts.bc_episodes, budget // horizon)
            if demo_episodes == 0:
                raise Invalid(
                    f"am: warm_start bc needs one demonstration episode ({horizon} steps) within "
                    f"budget.env_steps_per_iteration ({budget})",
                    details={"field": "budget.env_steps_per_iteration"},
                )
        if opts.algo == "ppo":
            rollout_length(budget, opts.n_steps)  # a budget PPO cannot spend: Invalid before any simulator
        workdir = Path(workdir)
        checkpoints = workdir / "checkpoints"
        checkpoints.mkdir(parents=True, exist_ok=True)
        env = GovernedTaskEnv(
            cell.task,
            phi=cell.phi,
            governance=cell.governance,
            perturbations=cell.perturbations,
            horizon=horizon,
            handoff_signals=opts.handoff_signals,
        )
        with contextlib.ExitStack() as stack:
            stack.callback(env.close)
            stack.enter_context(torch_threads(opts.torch_threads))
            train_seed = TRAIN_SEED_BASE + TRAIN_SEEDS_PER_CELL * cell.seed
            model, setup = _make_model(opts, env, seed=train_seed, budget=budget, iterations=cell.iterations)
            if after:
                model, theta0 = _resume(model, opts, env, checkpoints, after, seed=train_seed + after)
            else:
                model.save(checkpoints / "iteration-000.zip")
                theta0 = decision_vector(model, opts.algo)
            setup += f"; Δπ over {', '.join(p + '*' for p in DECISION_TENSORS[opts.algo])} ({len(theta0)} values)"

            def act(obs: np.ndarray) -> np.ndarray:
                return model.predict(obs, deterministic=True)[0]

            for iteration in range(after + 1, cell.iterations + 1):
                started = time.perf_counter()
                notes = [setup] if iteration == 1 else []
                if iteration == after + 1 and after:
                    notes.append(f"resumed from checkpoints/iteration-{after:03d}.zip after an interruption")
                demo_steps = 0
                if iteration == 1 and demo_episodes:
                    demo_steps, note = self._warm_start(model, opts, cell, workdir, demo_episodes, horizon, theta0)
                    notes.append(note)
                before = env.env_steps
                learn_steps = budget - demo_steps
                if learn_steps > 0:
                    callback = _stop_at(env, before + learn_steps) if opts.algo == "ppo" else None
                    model.set_logger(silent_logger())
                    model.learn(total_timesteps=learn_steps, reset_num_timesteps=False, callback=callback)
                spent = env.env_steps - before
                if opts.algo == "ppo" and spent % model.n_steps:
                    notes.append(f"{spent % model.n_steps} steps of a partial rollout were spent and not trained on")
                model.save(checkpoints / f"iteration-{iteration:03d}.zip")
                delta = policy_drift(theta0, decision_vector(model, opts.algo))
                emit(
                    held_out_record(
                        cell,
                        act,
                        iteration=iteration,
                        env_steps_train=demo_steps + spent,
                        delta_pi=delta,
                        started=started,
                        notes=notes,
                        workdir=workdir,
                        label=self.name,
                        horizon=horizon,
                        handoff_signals=opts.handoff_signals,
                    )
                )

    @staticmethod
    def _warm_start(
        model: Any, opts: AmOptions, cell: CellSpec, workdir: Path, episodes: int, horizon: int, theta0: list[float]
    ) -> tuple[int, str]:
        """Collect the v0 demonstrations, clone them; returns their env steps and a note."""
        from capevo.agent import policy_drift
        from capevo.baselines.demos import v0_demos
        from capevo.learner.bc import BcConfig, behaviour_clone

        seeds = [DEMO_SEED_BASE + 1000 * cell.seed + j for j in range(episodes)]
        demos = v0_demos(
            cell.task,
            workdir,
            seeds=seeds,
            phi=cell.phi,
            governance=cell.governance,
            perturbations=cell.perturbations,
            horizon=horizon,
        )
        report = behaviour_clone(
            bc_view(model, opts.algo), demos.demos, BcConfig(epochs=opts.bc_epochs, loss=opts.bc_loss, seed=cell.seed)
        )
        model.save(workdir / "checkpoints" / "warm-start.zip")
        drift = policy_drift(theta0, decision_vector(model, opts.algo))
        return demos.env_steps, (
            f"warm start: {demos.env_steps} demonstration steps of the v0 code ECMs ({len(demos.outcomes)} episodes, "
            f"{demos.successes} successful) charged to this iteration's budget; BC {report.loss} "
            f"{report.loss_before:.4g} -> {report.loss_after:.4g} over {report.epochs} epochs; "
            f"Δπ of the cloning alone {drift:.4g}"
        )


class AgentModificationBC(AgentModification):
    """AM warm-started by behaviour cloning from the task's v0 code ECMs (``warm_start: bc``).

    The same method as :class:`AgentModification`, under its own name so a grid runs both as two
    rows with their own knowledge column (issue 20, "Fairness").
    """

    name: ClassVar[str] = "am-bc"
    knowledge: ClassVar[str] = KNOWLEDGE_BC
    default_options: ClassVar[Mapping[str, Any]] = {"warm_start": "bc"}

    def options(self, cell: CellSpec) -> AmOptions:
        opts = super().options(cell)
        if opts.warm_start != "bc":
            raise Invalid(
                f"am-bc: option warm_start is always bc, got {opts.warm_start!r} (use method am for no warm start)",
                details={"field": "options.warm_start"},
            )
        return opts
