"""Reinforcement learning for neural ECMs: SAC (stable-baselines3, CPU), warm-started from the
active version.

Warm start: when the parent (active) version is a SAC policy, the new model is built with the
parent's policy architecture and gets *all* its parameters (actor, critics, target critics, the
optimizers' states and the entropy coefficient) by :func:`capevo.learner.neural_seed.warm_start`,
which unpickles nothing from the artifact. When the parent is a code ECM there are no
weights; the actor is then first distilled from the parent's behaviour (behaviour cloning on
``distill_episodes`` rollouts of the parent in the training environment) so RL starts from what
the robot already does, not from a random policy.

Random-init start (issue 19): when the parent is a randomly initialised neural version 0 (origin
``manual``) and a ``bc`` learner is given, the actor is first behaviour-cloned on that learner's
demonstrations (the scripted reference's rollouts and the current set's successful traces), with
the DAgger rounds of ``distill`` (:meth:`capevo.learner.bc.BcLearner.clone`), so SAC fine-tunes a
policy that already roughly does the job instead of exploring from nothing. Every later update of
that lineage (continuing from the latest candidate) clones again before SAC, on every
demonstration row gathered so far (kept in the learner's state, as the ``il`` learner keeps them).
Without that, a lineage whose SAC lost every check handed the gate its first clone again and
again: a 12-iteration T1 run re-submitted the same ``pick.reach`` actor in iterations 1-5 while
the ``il`` learner's clones kept improving (``results/evolution/T1-rl``).

Check (``SacConfig.check_episodes``): SAC on T1 undid its cloned warm start within 5,000 steps
(``results/evolution/T1-rl``), so the learner runs its deterministic actor on a few training
episodes before and after SAC and keeps the actor from before SAC when SAC's does worse there.

Continuation (issue 19): with a ``state_dir`` (:mod:`capevo.learner.continuation`) the learner
continues from its own latest candidate (all its parameters) and its replay buffer, whether or
not the gate promoted that candidate, so SAC updates add up across iterations. A continued
model skips SAC's random warm-up (``learning_starts``): its buffer already holds experience.

Training runs in the ECM's own step of the task (:class:`~capevo.learner.ecm_env.EcmEnv`: the
predecessors run at their active versions, governance on) with the paper's reward shaping on
top of the task's dense reward (:class:`~capevo.learner.reward.ShapedReward`). Optionally the
replay buffer is first filled with this ECM's transitions from traces (:func:`prefill_replay`).

Defaults follow the paper: γ = 0.99, τ = 0.005, learning rate 3·10⁻⁴, automatic entropy
tuning; buffer and batch come from the preset (:mod:`capevo.learner.presets`).

Invariants:
1. After :func:`build_sac` with a SAC parent the model's policy ``state_dict`` equals the
   parent's exactly.
2. Every candidate artifact loads with the runtime's neural loader against the ECM's interface.
3. ``SacConfig.to_dict()`` is JSON-able and is what the provenance's ``config_hash`` covers
   (with the environment, shaping and request fields).
"""

from __future__ import annotations

import copy
import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.learner.base import Candidate, LearnRequest, config_hash
from capevo.learner.bc import (
    BcConfig,
    BcLearner,
    BcReport,
    behaviour_clone,
    collect_demos,
    default_learner_id,
    ecm_controller,
    input_columns,
    neural_candidate,
    parent_artifact_of,
    task_trace_files,
    torch_threads,
)
from capevo.learner.continuation import LearnerState
from capevo.learner.ecm_env import EcmEnv, EcmEnvConfig, EcmTarget, make_ecm_env, target_for
from capevo.learner.neural_seed import new_sac, sac_policy_kwargs, silent_logger, warm_start
from capevo.learner.reward import RewardShaping, ShapedReward
from capevo.records import Kind, Origin, Provenance
from capevo.registry.api import Registry
from capevo.runtime.tasks import task_spec

log = logging.getLogger(__name__)


def _check_int(name: str, value: object, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise Invalid(f"{name} must be an integer >= {low}, got {value!r}", details={"field": name})


def _check_unit(name: str, value: object) -> None:
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    if not ok or not 0 < value <= 1:
        raise Invalid(f"{name} must be a number in (0, 1], got {value!r}", details={"field": name})


@dataclass(frozen=True, slots=True, kw_only=True)
class SacConfig:
    """SAC settings (hashed into provenance).

    Args:
        total_steps: Environment steps of training.
        buffer_size: Replay buffer capacity.
        batch_size: Minibatch size of each gradient step.
        learning_starts: Steps collected before the first gradient step.
        learning_rate: Adam step size of actor, critics and entropy coefficient.
        gamma: Discount γ.
        tau: Target network update rate τ.
        train_freq: Environment steps between updates.
        gradient_steps: Gradient steps per update.
        ent_coef: ``"auto"`` (tuned) or a fixed entropy coefficient.
        net_arch: Hidden layers of a fresh policy (a SAC parent keeps its own).
        seed: Seeds weights, exploration and the first training episode.
        check_episodes: Episodes of the learner's own check (0: none). When the actor starts
            from learned weights (a clone, a distilled code parent, a neural parent or the
            learner's latest candidate), the deterministic actor runs this many episodes of the
            ECM's step before and after SAC, on training seeds SAC's episodes do not reach
            (:data:`CHECK_SEED_OFFSET`); if SAC's actor reaches the ECM's termination in fewer of
            them, the actor falls back to its weights from before SAC (the critics and the
            replay buffer keep what SAC learned). A learner should not hand the gate a policy
            that it has itself seen do worse than the one it started from.

    Raises:
        Invalid: a value out of range.
    """

    total_steps: int = 5_000
    buffer_size: int = 100_000
    batch_size: int = 256
    learning_starts: int = 500
    learning_rate: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005
    train_freq: int = 1
    gradient_steps: int = 1
    ent_coef: str | float = "auto"
    net_arch: tuple[int, ...] = (256, 256)
    seed: int = 0
    check_episodes: int = 0

    def __post_init__(self) -> None:
        _check_int("total_steps", self.total_steps, 1)
        _check_int("check_episodes", self.check_episodes, 0)
        _check_int("buffer_size", self.buffer_size, 1)
        _check_int("batch_size", self.batch_size, 1)
        _check_int("learning_starts", self.learning_starts, 0)
        _check_int("train_freq", self.train_freq, 1)
        _check_int("gradient_steps", self.gradient_steps, 1)
        _check_int("seed", self.seed, 0)
        _check_unit("learning_rate", self.learning_rate)
        _check_unit("gamma", self.gamma)
        _check_unit("tau", self.tau)
        if isinstance(self.ent_coef, str):
            if not (self.ent_coef == "auto" or self.ent_coef.startswith("auto_")):
                raise Invalid(
                    f"ent_coef must be 'auto' or a number, got {self.ent_coef!r}", details={"field": "ent_coef"}
                )
        elif isinstance(self.ent_coef, bool) or not isinstance(self.ent_coef, (int, float)) or not self.ent_coef > 0:
            raise Invalid(f"ent_coef must be 'auto' or a positive number, got {self.ent_coef!r}")
        if not self.net_arch or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in self.net_arch):
            raise Invalid(
                f"net_arch must be positive layer sizes, got {self.net_arch!r}", details={"field": "net_arch"}
            )

    def to_dict(self) -> dict[str, Any]:
        return {
            "total_steps": self.total_steps,
            **self.sac_kwargs(),
            "net_arch": list(self.net_arch),
            "seed": self.seed,
            "check_episodes": self.check_episodes,
        }

    def sac_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``stable_baselines3.SAC`` (besides policy, env, seed)."""
        return {
            "buffer_size": self.buffer_size,
            "batch_size": self.batch_size,
            "learning_starts": self.learning_starts,
            "learning_rate": self.learning_rate,
            "gamma": self.gamma,
            "tau": self.tau,
            "train_freq": self.train_freq,
            "gradient_steps": self.gradient_steps,
            "ent_coef": self.ent_coef,
        }


# --- warm start ----------------------------------------------------------------------------


def build_sac(env: Any, config: SacConfig, *, parent_artifact: bytes | None = None) -> Any:
    """A SAC model for ``env``; warm-started from ``parent_artifact`` (a SAC zip) when given.

    Raises:
        Invalid: the parent is not a SAC policy of the environment's spaces.
    """
    kwargs = sac_policy_kwargs(parent_artifact) if parent_artifact is not None else None
    model = new_sac(env, net_arch=config.net_arch, seed=config.seed, policy_kwargs=kwargs, **config.sac_kwargs())
    if parent_artifact is not None:
        from capevo.runtime.ecm.neural import load_sb3_policy

        loaded = load_sb3_policy(parent_artifact)
        want = (int(env.observation_space.shape[0]), int(env.action_space.shape[0]))
        if (loaded.observation_dim, loaded.action_dim) != want:
            raise Invalid(
                f"warm start: the parent observes {loaded.observation_dim} and acts in {loaded.action_dim}, "
                f"the ECM's environment has {want[0]} and {want[1]}",
                details={"field": "parent"},
            )
        warm_start(model, parent_artifact)
    return model


# --- experience from traces ------------------------------------------------------------------


def prefill_replay(
    model: Any,
    paths: Sequence[str],
    *,
    task: str,
    target: EcmTarget,
    shaping: RewardShaping,
    dt: float,
) -> int:
    """Add ``target``'s transitions from trace files of ``task`` to the replay buffer.

    Rewards get the same shaping as online steps except retries (not in traces); the success
    bonus goes to the step where the task first reported success; ``done`` is the trace's
    ``terminated``. Rows leaving the ECM (the next one took over) bootstrap as if cut off.

    Returns:
        Transitions added.
    """
    from capevo.runtime.traces import export_transitions

    files = task_trace_files(paths, task)
    if not files:
        return 0
    rows = export_transitions(files, ecms=[target.name], allow_incomplete=True)
    if len(rows) == 0:
        return 0
    cols = input_columns(task_spec(task), target.interface.inputs, rows.obs.shape[1])
    obs = rows.obs[:, cols]
    next_obs = rows.next_obs[:, cols]
    ok = (
        np.all(np.isfinite(obs), axis=1)
        & np.all(np.isfinite(next_obs), axis=1)
        & np.all(np.isfinite(rows.action), axis=1)
        & np.isfinite(rows.reward)
    )
    first_success = rows.is_success & ~np.concatenate([[False], rows.is_success[:-1]])
    added = 0
    for i in np.flatnonzero(ok):
        reward = float(rows.reward[i]) + shaping.step_bonus(
            newly_succeeded=bool(first_success[i]), dt=dt, new_retries=0
        )
        model.replay_buffer.add(
            obs[i : i + 1],
            next_obs[i : i + 1],
            np.clip(rows.action[i : i + 1], -1.0, 1.0),
            np.array([reward], dtype=np.float32),
            np.array([bool(rows.terminated[i])]),
            [{"TimeLimit.truncated": bool(rows.truncated[i])}],
        )
        added += 1
    return added


# --- training ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class TrainReport:
    """What one SAC run did."""

    steps: int
    seconds: float
    episodes: int
    successes: int
    mean_return: float | None
    prefilled: int = 0
    distill: BcReport | None = None

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "seconds": self.seconds,
            "steps_per_second": self.steps_per_second,
            "episodes": self.episodes,
            "successes": self.successes,
            "mean_return": self.mean_return,
            "prefilled": self.prefilled,
            "distill": self.distill.to_dict() if self.distill is not None else None,
        }


CHECK_SEED_OFFSET = 400
"""First check episode, counted from the learner's training seed (:class:`EcmEnv` invariant 3):
SAC's own episodes, the scripted demonstrations and DAgger's rounds of one update stay below it at
the presets' budgets, and each iteration's training window holds 500 (``training_seed_window``)."""


@dataclass(frozen=True, slots=True)
class ActorCheck:
    """The deterministic actor on the learner's check episodes: the ECM's own success."""

    successes: int
    episodes: int
    env_steps: int

    def to_dict(self) -> dict[str, int]:
        return {"successes": self.successes, "episodes": self.episodes, "env_steps": self.env_steps}


def check_actor(model: Any, env: EcmEnv, *, episodes: int, first_seed: int) -> ActorCheck:
    """Run ``model``'s deterministic actor for ``episodes`` episodes of ``env`` from ``first_seed``.

    ``env_steps`` counts every simulated step, the predecessors' before the ECM takes over too.
    """
    successes = 0
    steps_before = env.env_steps
    for k in range(episodes):
        obs, info = env.reset(seed=first_seed + k)
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        successes += bool(info.get("is_success"))
    return ActorCheck(successes=successes, episodes=episodes, env_steps=env.env_steps - steps_before)


def check_note(check: Mapping[str, Any]) -> str:
    """Words for a learner's check record (``notes["check"]`` of an ``rl`` candidate)."""
    before, after = check["before"], check["after"]
    kept = "SAC's" if check["actor"] == "sac" else "the one before SAC"
    return (
        f"check {before['successes']}/{before['episodes']} before SAC, "
        f"{after['successes']}/{after['episodes']} after: the candidate's actor is {kept}"
    )


PROGRESS_EVERY = 10
"""Environment steps between two calls of a training progress callback."""


def _episode_callback(
    stats: dict[str, Any],
    should_stop: Callable[[], bool] | None,
    progress: Callable[[int, int], Any] | None,
    total: int,
) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class _Episodes(BaseCallback):
        """Counts finished episodes, their successes and returns."""

        def __init__(self) -> None:
            super().__init__()
            self._ret = 0.0

        def _on_step(self) -> bool:
            rewards = self.locals.get("rewards")
            if rewards is not None:
                self._ret += float(np.asarray(rewards).reshape(-1)[0])
            dones = np.asarray(self.locals.get("dones", [False])).reshape(-1)
            if bool(dones[0]):
                info = self.locals.get("infos", [{}])[0]
                stats["episodes"] += 1
                stats["successes"] += int(bool(info.get("is_success", False)))
                stats["returns"].append(self._ret)
                self._ret = 0.0
            stats["steps"] = self.num_timesteps
            if progress is not None and (self.num_timesteps % PROGRESS_EVERY == 0 or self.num_timesteps >= total):
                progress(self.num_timesteps, total)
            return not (should_stop is not None and should_stop())

    return _Episodes()


def train_sac(
    model: Any,
    total_steps: int,
    *,
    progress_bar: bool = False,
    should_stop: Callable[[], bool] | None = None,
    progress: Callable[[int, int], Any] | None = None,
) -> TrainReport:
    """Run ``model.learn`` for ``total_steps`` environment steps (fewer if ``should_stop`` says so).

    Args:
        model: A SAC model with its environment.
        total_steps: Steps to take.
        progress_bar: Show SB3's (tqdm + rich) progress bar on stderr.
        should_stop: Polled after every step; True ends training.
        progress: Called as ``progress(steps_done, total_steps)`` every
            :data:`PROGRESS_EVERY` steps and at the last one.

    Returns:
        Steps taken, wall time, finished episodes, successes and their mean return.
    """
    import warnings

    stats: dict[str, Any] = {"episodes": 0, "successes": 0, "returns": [], "steps": 0}
    started = time.perf_counter()
    model.set_logger(silent_logger())
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*rich is experimental.*")
        model.learn(
            total_timesteps=total_steps,
            callback=_episode_callback(stats, should_stop, progress, total_steps),
            progress_bar=progress_bar,
        )
    seconds = time.perf_counter() - started
    returns = stats["returns"]
    return TrainReport(
        steps=int(stats["steps"]),
        seconds=seconds,
        episodes=stats["episodes"],
        successes=stats["successes"],
        mean_return=float(np.mean(returns)) if returns else None,
    )


# --- the learner ---------------------------------------------------------------------------


def _warm_start_note(continued: bool, neural_parent: bool, distilled: BcReport | None) -> str:
    """Where the candidate's training started, for its notes."""
    if continued:
        return "latest candidate, cloned again" if distilled is not None else "latest candidate"
    if distilled is not None:
        return "cloned" if neural_parent else "distilled"
    return "weights" if neural_parent else "random"


class SacLearner:
    """SAC learner (modality ``rl``) for neural ECMs.

    Args:
        config: SAC settings.
        env_config: The training environment (budgets, governance, perturbations, seeds).
        shaping: Reward shaping coefficients α, β, γ.
        registry: Loads the parent's artifact and the predecessors of later ECMs.
        distill: Behaviour cloning settings for distilling a code parent (default 20 epochs).
        distill_episodes: Rollouts of a code parent to distil from (0: a code parent's
            replacement starts from random weights).
        traces: Trace files or directories whose transitions of this ECM prefill the replay
            buffer (the request's outcomes' traces are added).
        learner_id: Recorded in provenance; default a unique id.
        progress_bar: Show SB3's progress bar while training.
        make_env: Builds the training environment (default :func:`make_ecm_env`).
        should_stop: Polled every step; True ends training early (the caller should then not
            publish the result).
        torch_threads: CPU threads for torch while learning (None: leave as is). On a small
            shared CPU, 1 is several times faster than torch's default for these networks.
        progress: Called as ``progress(steps_done, total_steps)`` during training.
        bc: Behaviour cloning learner whose demonstrations start a randomly initialised parent
            (None: SAC starts from the random weights).
        state_dir: Where this learner keeps its latest candidate and replay buffer between
            updates, per ECM (None: every update starts from the parent).
        env_step_budget: Env steps one :meth:`learn` may simulate in all (issue 20's budget),
            counted as :attr:`EcmEnv.env_steps` counts them: the clone's demonstrations and
            DAgger's rounds come first (give :attr:`bc` the same budget to cap them), and SAC
            trains on what is left. It stops while one more reset's predecessors
            (``prefix_budget`` steps each) still fit, so the budget is never overrun, and up to
            that many steps may stay unspent. No check runs under a budget: its episodes after
            SAC cannot be cut short. None: SAC takes ``config.total_steps`` agent steps. The
            candidate's ``notes["env_steps"]`` records what each part spent either way.

    Raises:
        Invalid: bad settings.
    """

    modality = "rl"

    def __init__(
        self,
        *,
        config: SacConfig | None = None,
        env_config: EcmEnvConfig | None = None,
        shaping: RewardShaping | None = None,
        registry: Registry | None = None,
        distill: BcConfig | None = None,
        distill_episodes: int = 5,
        traces: Sequence[str] = (),
        learner_id: str | None = None,
        progress_bar: bool = False,
        make_env: Callable[[str, EcmTarget], EcmEnv] | None = None,
        should_stop: Callable[[], bool] | None = None,
        torch_threads: int | None = None,
        progress: Callable[[int, int], Any] | None = None,
        bc: BcLearner | None = None,
        state_dir: str | os.PathLike[str] | None = None,
        env_step_budget: int | None = None,
    ) -> None:
        if env_step_budget is not None:
            _check_int("env_step_budget", env_step_budget, 1)
        self.env_step_budget = env_step_budget
        self.bc = bc
        self.state_dir = Path(state_dir) if state_dir is not None else None
        self.should_stop = should_stop
        self.progress = progress
        self.torch_threads = torch_threads
        self.config = config or SacConfig()
        self.env_config = env_config or EcmEnvConfig()
        self.shaping = shaping or RewardShaping()
        self.registry = registry
        self.distill = distill if distill is not None else BcConfig(epochs=20, net_arch=self.config.net_arch)
        _check_int("distill_episodes", distill_episodes, 0)
        self.distill_episodes = distill_episodes
        self.traces = tuple(str(t) for t in traces)
        self.learner_id = learner_id or default_learner_id(self.modality)
        self.progress_bar = progress_bar
        self._make_env = make_env
        self.last_model: Any = None
        self.last_dagger: dict[str, Any] | None = None
        self.last_clone_steps = 0

    def _check(self, model: Any, env: EcmEnv | None) -> ActorCheck | None:
        if env is None:
            return None
        first = self.env_config.seed + CHECK_SEED_OFFSET
        return check_actor(model, env, episodes=self.config.check_episodes, first_seed=first)

    def _env(self, task: str, target: EcmTarget) -> EcmEnv:
        if self._make_env is not None:
            return self._make_env(task, target)
        return make_ecm_env(task, target, registry=self.registry, config=self.env_config)

    def _distil(self, env: EcmEnv, model: Any, request: LearnRequest, artifact: bytes) -> BcReport | None:
        """Clone a code parent's behaviour into the actor; None when nothing could be collected."""
        from capevo.runtime.ecm import load_ecm

        if self.distill_episodes == 0:
            return None
        loaded = load_ecm(request.parent, artifact)
        try:
            controller = ecm_controller(loaded, layout=task_spec(request.task).action_layout)
            demos = collect_demos(
                env,
                controller,
                episodes=self.distill_episodes,
                only_successful=False,
                source=f"{request.ecm}@{request.parent.version}",
                should_stop=self.should_stop,
            )
        finally:
            loaded.close()
        if len(demos) == 0:
            log.warning("%s: the parent produced no steps to distil; RL starts from random weights", request.ecm)
            return None
        report = behaviour_clone(model, demos, self.distill)
        log.info(
            "%s: distilled the parent from %d steps: loss %.4f -> %.4f",
            request.ecm,
            report.samples,
            report.loss_before,
            report.loss_after,
        )
        return report

    def provenance(self, request: LearnRequest, traces: Sequence[str]) -> Provenance:
        config = {
            "learner": "sac",
            "sac": self.config.to_dict(),
            "env": self.env_config.to_dict(),
            "shaping": self.shaping.to_dict(),
            "distill": self.distill.to_dict() if request.parent.kind is not Kind.NEURAL else None,
            "distill_episodes": self.distill_episodes if request.parent.kind is not Kind.NEURAL else 0,
            "task": request.task,
            "ecm": request.ecm,
            "parent": request.parent.version,
        }
        return Provenance(learner_id=self.learner_id, config_hash=config_hash(config), traces=tuple(traces))

    def learn(self, request: LearnRequest, *, parent_artifact: bytes | None = None) -> Candidate:
        """Train SAC for ``request.ecm`` from its parent and return the candidate (origin ``rl``).

        Raises:
            Invalid: a parent that cannot warm-start (neural but not SAC, other spaces), or a
                result that does not load.
            NotFound: a predecessor of the ECM has no active version.
        """
        with torch_threads(self.torch_threads):
            return self._learn(request, parent_artifact)

    def _cloned(
        self, model: Any, request: LearnRequest, target: EcmTarget, state: LearnerState | None
    ) -> BcReport | None:
        """Clone :attr:`bc`'s demonstrations into the actor, with the DAgger rounds of
        :attr:`distill`, on every row ``state`` keeps (:meth:`BcLearner.clone_keeping`)."""
        if self.bc is None:
            return None
        try:
            demos = self.bc.gather(request, target)
        except Invalid as exc:  # no scripted reference and no successful trace yet (T4-T6)
            log.warning("%s: nothing to clone (%s); SAC starts from the actor as it is", request.ecm, exc.message)
            return None
        self.last_clone_steps = demos.env_steps
        demos, report, self.last_dagger = self.bc.clone_keeping(
            model, request, target, demos, state, config=self.distill
        )
        log.info(
            "%s: cloned %d demonstration steps (%s) into the actor: loss %.4f -> %.4f",
            request.ecm,
            report.samples,
            demos.source,
            report.loss_before,
            report.loss_after,
        )
        return report

    def _train(self, model: Any, env: EcmEnv, spent: int) -> TrainReport:
        """SAC's training: ``config.total_steps`` agent steps, or, under :attr:`env_step_budget`,
        until ``env`` has simulated what the budget leaves after ``spent``."""
        if self.env_step_budget is None:
            return train_sac(
                model,
                self.config.total_steps,
                progress_bar=self.progress_bar,
                should_stop=self.should_stop,
                progress=self.progress,
            )
        # an episode that ends resets at once, and the reset drives the predecessors
        reset_reserve = len(env.predecessors) * env.config.prefix_budget
        left = self.env_step_budget - spent
        if left - reset_reserve <= 0:
            log.warning("%s: the clone and the check spent the env-step budget; no SAC steps", self.learner_id)
            return TrainReport(steps=0, seconds=0.0, episodes=0, successes=0, mean_return=None)
        start = env.env_steps
        outer = self.should_stop

        def spent_or_stopped() -> bool:
            return env.env_steps - start + reset_reserve >= left or (outer is not None and outer())

        return train_sac(
            model, left, progress_bar=self.progress_bar, should_stop=spent_or_stopped, progress=self.progress
        )

    def _learn(self, request: LearnRequest, parent_artifact: bytes | None) -> Candidate:
        from capevo.learner.experience import trace_paths

        target = target_for(request.task, request.ecm, request.parent)
        artifact = parent_artifact_of(request, self.registry, parent_artifact)
        neural_parent = request.parent.kind is Kind.NEURAL
        if neural_parent and artifact is None:
            raise Invalid(f"{request.ecm}: the parent's weights are needed; give a registry or parent_artifact")
        state = LearnerState(self.state_dir, request.ecm) if self.state_dir is not None else None
        latest = state.latest() if state is not None else None
        env = self._env(request.task, target)
        try:
            shaped = ShapedReward(env, self.shaping, dt=env.control_dt)
            start = latest if latest is not None else (artifact if neural_parent else None)
            model = build_sac(shaped, self.config, parent_artifact=start)
            distilled = None
            self.last_dagger = None
            self.last_clone_steps = 0
            kept = 0
            if latest is not None and state is not None:
                kept = state.load_replay(model)
                if kept:
                    model.learning_starts = 0
            if latest is None and not neural_parent and artifact is not None:
                distilled = self._distil(env, model, request, artifact)
            elif neural_parent and (latest is not None or request.parent.origin is Origin.MANUAL):
                # every update of a lineage that began at a random v0 clones again, on all the
                # rows gathered so far: its check then starts SAC from the best clone yet
                distilled = self._cloned(model, request, target, state)
            paths = [*self.traces, *trace_paths(request.outcomes)]
            prefilled = (
                prefill_replay(model, paths, task=request.task, target=target, shaping=self.shaping, dt=env.control_dt)
                if paths
                else 0
            )
            learned_start = latest is not None or distilled is not None or request.parent.origin is not Origin.MANUAL
            checked = self.config.check_episodes and learned_start and self.env_step_budget is None
            check_env = self._env(request.task, target) if checked else None
            dagger_steps = int((self.last_dagger or {}).get("env_steps") or 0)
            try:
                before = self._check(model, check_env)
                actor_before = copy.deepcopy(model.actor.state_dict()) if before is not None else None
                # the SAC environment has already run a code parent's distillation rollouts
                spent = env.env_steps + self.last_clone_steps + dagger_steps + (before.env_steps if before else 0)
                sac_started = env.env_steps
                report = self._train(model, env, spent)
                sac_steps = env.env_steps - sac_started
                stopped = self.should_stop is not None and self.should_stop()
                after = None if stopped else self._check(model, check_env)
            finally:
                if check_env is not None:
                    check_env.close()
            check = None
            if before is not None and after is not None:
                keep_sac = after.successes >= before.successes
                if not keep_sac:
                    model.actor.load_state_dict(actor_before)
                check = {"before": before.to_dict(), "after": after.to_dict(), "actor": "sac" if keep_sac else "start"}
                log.info("%s: %s", request.ecm, check_note(check))
            report = TrainReport(
                steps=report.steps,
                seconds=report.seconds,
                episodes=report.episodes,
                successes=report.successes,
                mean_return=report.mean_return,
                prefilled=prefilled,
                distill=distilled,
            )
            if state is not None:
                state.save_replay(model)
            env_total = env.env_steps + self.last_clone_steps + dagger_steps
            env_total += sum(c.env_steps for c in (before, after) if c is not None)
        finally:
            env.close()
        self.last_model = model
        log.info(
            "%s: SAC %d steps in %.1fs (%.1f steps/s), %d episodes, %d successes",
            request.ecm,
            report.steps,
            report.seconds,
            report.steps_per_second,
            report.episodes,
            report.successes,
        )
        used = task_trace_files(paths, request.task) if paths else []
        candidate = neural_candidate(
            model,
            target,
            request=request,
            origin=Origin.RL,
            provenance=self.provenance(request, [str(p) for p in used]),
            notes={
                "learner": self.learner_id,
                "modality": self.modality,
                "warm_start": _warm_start_note(latest is not None, neural_parent, distilled),
                "replay_kept": kept,
                "train": report.to_dict(),
                "dagger": self.last_dagger,
                "check": check,
                "env_steps": {
                    "distill": sac_started,
                    "clone": self.last_clone_steps,
                    "dagger": dagger_steps,
                    "check": sum(c.env_steps for c in (before, after) if c is not None),
                    "sac": sac_steps,
                    "total": env_total,
                },
            },
        )
        if state is not None:
            state.save_latest(candidate.artifact)
        return candidate
