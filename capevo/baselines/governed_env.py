"""The whole task as one gymnasium env, run the way the runtime runs it (issue 20, paper §4.1).

The baselines that learn one policy for a whole task (Agent Modification, SPiRL, SkiMo) act in
:class:`GovernedTaskEnv`. Everything that makes a comparison with ours fair is the runtime's own
code, not a copy of it:

* the task is :func:`capevo.runtime.tasks.make_task`'s environment, with the paper's
  perturbations (:class:`capevo.runtime.tasks.Perturbations`: object ±5 cm, observation noise
  σ 0.01 m, dropped actions p 0.05) unless ``perturbations=False``;
* every action goes through the governor of the same Φ the runtime resolves
  (:func:`capevo.runtime.envelope.resolve_phi`, :func:`capevo.runtime.episode.make_governor`);
  ⊥ becomes :func:`capevo.runtime.governance.hold_action`. With ``governance=False`` the
  governor runs in its counting mode (the runtime's governance-off, H3): actions pass unchanged
  and ``info["intervened"]`` says governance *would* have changed them;
* every executed step is graded by the independent
  :class:`~capevo.runtime.safety_monitor.SafetyMonitor` with the paper's limits, on the action
  the robot really got (zeros when the task dropped it), exactly as
  :func:`capevo.runtime.episode.run_episode_detailed` grades it.

What differs from the runtime's episode loop is only what an ECM-free method has no use for:
there is no decision policy, no ECM invoker, no trace. The step is the loop's "govern, judge,
step" part (its steps 4 and 5), composed from the same pieces.

Observation: the task's flat float32 observation (its ``observation_keys`` concatenated, noisy
positions); with ``handoff_signals=True`` followed by the exact simulator signals our
decomposition's hand-off predicates read (:attr:`TaskSpec.handoff_signals`: ``grasped``,
distances, ``success``), so that a method without ECMs can get the same information ours hands
off on (issue 20's fairness: "the baselines get the same signals ... or the report names the
asymmetry"). Action: ``[-1, 1]^d`` with ``d`` the task's action dimension (T6: 12); actions are
clipped to the box before governance, as :class:`capevo.learner.ecm_env.EcmEnv` does. Reward:
the task env's reward. ``terminated``: the task's success (robosuite's ``_check_success``,
latched); ``truncated``: the horizon.

``info`` after every step holds the task's (``is_success``, ``success_now``,
``actuation_dropped``) and ``unsafe`` (the monitor graded the step unsafe), ``unsafe_axes``
(which limits: ``box``, ``cap``, ``force``, ``non_finite``), ``unsafe_reasons`` (the monitor's
lines), ``intervened`` (governance changed the action, or would have when off), ``rejected`` (it
answered ⊥), ``constraints`` (the constraints that intervened), ``interventions`` (their
:class:`~capevo.runtime.governance.Intervention` records) and ``action`` (the action executed,
before a drop).

Traces: :func:`evaluate_policy` given ``trace`` writes its episodes to one MCAP file with the
runtime's record types (:mod:`capevo.runtime.traces`): ``/env/step`` (``ecm`` is the policy's
label, ``version`` its iteration), ``/governance/intervention`` (reasons prefixed ``not
enforced:`` when governance is off, as the runtime writes them), ``/safety/unsafe`` and
``/episode/summary`` (an empty capability set: no ECM ran). Training steps are not traced.

Invariants:
1. ``env_steps`` is the number of :meth:`GovernedTaskEnv.step` calls since construction
   (resets are not steps); :func:`evaluate_policy` returns the sum of its episodes' steps.
2. With ``governance=True`` the executed action is the governor's answer (the hold action on
   ⊥); with ``governance=False`` it is the clipped proposal, always.
3. ``info["unsafe"]`` is the safety monitor's verdict on the executed step; governance plays no
   part in it.
4. Episode ``k`` after ``reset(seed=s)`` runs task seed ``s + k``; so a policy's held-out
   evaluation on given seeds, and a training run seeded with ``s``, are reproducible.
5. Observations are float32 of the shape of ``observation_space``; :func:`evaluate_policy` with a
   deterministic policy returns equal results for equal seeds.
6. A trace of :func:`evaluate_policy` holds one ``/env/step`` per step taken, one
   ``/safety/unsafe`` per unsafe step and one ``/episode/summary`` per seed, agreeing with the
   returned results.
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from capevo.baselines.base import CellSpec, EpisodeResult, IterationRecord
from capevo.errors import Invalid
from capevo.records import CapabilitySet
from capevo.runtime.envelope import PhiChoice, resolve_phi
from capevo.runtime.episode import key_state, make_governor
from capevo.runtime.evaluator import check_seeds
from capevo.runtime.governance import hold_action
from capevo.runtime.safety_monitor import SafetyMonitor
from capevo.runtime.state import RobotState
from capevo.runtime.tasks import Perturbations, TaskEnv, make_task, task_spec
from capevo.runtime.traces import (
    NOT_ENFORCED_PREFIX,
    EnvStep,
    EpisodeSummary,
    TraceMetadata,
    TraceSink,
    TraceWriter,
    UnsafeStep,
)
from capevo.runtime.traces import Intervention as TraceIntervention

UNSPECIFIED_IDENTITY = "unspecified"
"""The traces' agent identity hash: a monolithic policy has no persistent agent."""


class GovernedTaskEnv(gym.Env[np.ndarray, np.ndarray]):
    """One task, every action governed and every step graded (see the module docstring).

    Args:
        task: Task id or name (``"T1"`` .. ``"T6"``).
        phi: The envelope: ``"task"`` (the runtime's default), ``"paper"``, a Φ YAML path or a
            :class:`~capevo.runtime.governance.Phi`.
        governance: Enforce Φ; False runs the governor in counting mode (nothing changed).
        perturbations: The paper's perturbations on (False: the clean task).
        horizon: Episode length; None for the task's default.
        handoff_signals: Append the hand-off predicates' exact signals to the observation.

    Raises:
        Invalid: an unknown task, a bad Φ choice or horizon.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 - gymnasium's class attribute

    def __init__(
        self,
        task: str,
        *,
        phi: PhiChoice = "task",
        governance: bool = True,
        perturbations: bool = True,
        horizon: int | None = None,
        handoff_signals: bool = False,
    ) -> None:
        spec = task_spec(task)
        self._extra = spec.handoff_signals if handoff_signals else ()
        # Resolved before the simulator is built: a bad choice costs nothing.
        envelope = resolve_phi(phi, spec)
        self.task_env: TaskEnv = make_task(
            spec.name,
            perturbations=Perturbations() if perturbations else Perturbations.none(),
            horizon=horizon,
            terminate_on_success=True,
        )
        try:
            self.governor = make_governor(self.task_env, envelope, enforce=bool(governance))
            self.monitor = SafetyMonitor(self.task_env)
        except BaseException:
            self.task_env.close()
            raise
        self.phi = envelope
        self.governance = bool(governance)
        self.horizon = self.task_env.horizon
        self.observation_space = self.task_env.observation_space
        if self._extra:
            base = self.task_env.observation_space
            self.observation_space = gym.spaces.Box(
                low=np.concatenate([base.low, np.full(len(self._extra), -np.inf)]).astype(np.float32),
                high=np.concatenate([base.high, np.full(len(self._extra), np.inf)]).astype(np.float32),
                dtype=np.float32,
            )
        self.action_space = self.task_env.action_space
        self._layout = spec.action_layout
        self._dropped = np.zeros(self._layout.dim)
        self._last_action: tuple[float, ...] | None = None
        self._next_seed: int | None = None
        self._closed = False
        self.env_steps = 0
        """Every step taken since construction (the budget is counted from this)."""
        self.last_state: RobotState | None = None
        """The robot state the last step's action was governed in (before the step)."""

    @property
    def task_spec(self) -> Any:
        """The task's :class:`~capevo.runtime.tasks.TaskSpec`."""
        return self.task_env.task_spec

    @property
    def obs_dict(self) -> dict[str, np.ndarray]:
        """The last observation as the task's dict (for scripted controllers)."""
        return self.task_env.obs_dict

    def signals(self) -> dict[str, float]:
        """The task's named signals of the current state (exact, not perturbed)."""
        return self.task_env.signals()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode: task seed ``seed``, else the one after the previous episode's.

        Returns:
            ``(observation, info)``.

        Raises:
            Invalid: a bad seed, or the env is closed.
        """
        if self._closed:
            raise Invalid("this governed task env is closed")
        super().reset(seed=seed)
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise Invalid(f"seed must be a non-negative integer, got {seed!r}", details={"field": "seed"})
            self._next_seed = int(seed)
        # Never seeded: the task env's own streams continue (its first reset draws OS entropy).
        obs, info = self.task_env.reset(seed=self._next_seed)
        if self._next_seed is not None:
            self._next_seed += 1
        self.governor.new_episode()
        self._last_action = None
        return self._observed(obs), dict(info)

    def _observed(self, obs: np.ndarray) -> np.ndarray:
        if not self._extra:
            return obs
        signals = self.task_env.signals()
        extra = np.array([signals[name] for name in self._extra], dtype=np.float32)
        return np.concatenate([obs, extra]).astype(np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Clip, govern, step, grade (the runtime loop's steps 4 and 5).

        Returns:
            ``(observation, reward, terminated, truncated, info)``; see the module docstring.

        Raises:
            Invalid: an action of the wrong shape, the env closed, or the episode over.
        """
        if self._closed:
            raise Invalid("this governed task env is closed")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (self._layout.dim,):
            raise Invalid(
                f"{self.task_spec.name}: action shape {a.shape} != ({self._layout.dim},)", details={"field": "action"}
            )
        proposed = np.clip(a, -1.0, 1.0)
        state = self.last_state = self.task_env.robot_state()
        governed, ivs = self.governor(state, proposed)
        rejected = governed is None or any(iv.result is None for iv in ivs)
        executed = np.asarray(
            hold_action(self._layout, self._last_action) if governed is None else governed, dtype=np.float64
        )
        obs, reward, terminated, truncated, info = self.task_env.step(executed)
        self.env_steps += 1
        self._last_action = tuple(executed.tolist())
        # Graded on what the robot really got: the task replaced a dropped action by zeros.
        verdict = self.monitor.judge(self._dropped if info.get("actuation_dropped") else executed)
        info = dict(info)
        info["unsafe"] = verdict.unsafe
        info["unsafe_axes"] = verdict.broken
        info["unsafe_reasons"] = verdict.reasons
        info["intervened"] = bool(ivs)
        info["rejected"] = bool(ivs) and rejected
        info["constraints"] = tuple(iv.constraint for iv in ivs)
        info["interventions"] = ivs
        info["action"] = executed.astype(np.float32)
        return self._observed(obs), float(reward), bool(terminated), bool(truncated), info

    def close(self) -> None:
        """Release the simulator. Idempotent."""
        if not self._closed:
            self._closed = True
            self.task_env.close()


def evaluate_policy(
    task: str,
    act: Callable[[np.ndarray], np.ndarray],
    seeds: Sequence[int],
    *,
    phi: PhiChoice = "task",
    governance: bool = True,
    perturbations: bool = True,
    horizon: int | None = None,
    trace: str | os.PathLike[str] | None = None,
    label: str = "policy",
    version: int = 0,
    handoff_signals: bool = False,
    on_reset: Callable[[], None] | None = None,
) -> tuple[tuple[EpisodeResult, ...], int]:
    """Run one episode per seed with the deterministic policy ``act`` in a fresh :class:`GovernedTaskEnv`.

    Args:
        task: Task id or name.
        act: Flat float32 observation -> action.
        seeds: The episodes' task seeds (for a held-out evaluation, :meth:`CellSpec.eval_seeds`).
        phi: As :class:`GovernedTaskEnv`.
        governance: As :class:`GovernedTaskEnv`.
        perturbations: As :class:`GovernedTaskEnv`.
        horizon: As :class:`GovernedTaskEnv`.
        trace: An MCAP file to write the episodes to (see the module docstring); None writes none.
        label: The trace's name for the policy (``/env/step``'s ``ecm``; the run's worker id).
        version: The trace's version of the policy (``/env/step``'s ``version``), e.g. the iteration.
        handoff_signals: As :class:`GovernedTaskEnv` (the policy was trained with them).
        on_reset: Called after each episode's reset, before its first action: a policy with memory
            (a skill that runs H actions open-loop, SPiRL's and SkiMo's) starts every episode afresh.

    Returns:
        One :class:`EpisodeResult` per seed, in order, and the env steps they took.

    Raises:
        Invalid: bad seeds (none, negative, not integers), or what :class:`GovernedTaskEnv` raises.
        Conflict: ``trace`` exists already.
    """
    seed_list = check_seeds(seeds)
    env = GovernedTaskEnv(
        task,
        phi=phi,
        governance=governance,
        perturbations=perturbations,
        horizon=horizon,
        handoff_signals=handoff_signals,
    )
    results: list[EpisodeResult] = []
    with contextlib.ExitStack() as stack:
        stack.callback(env.close)
        sink: TraceSink | None = None
        if trace is not None:
            metadata = TraceMetadata.collect(
                run_id=f"{label}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{uuid.uuid4().hex[:8]}",
                task=env.task_spec.name,
                capability_set=CapabilitySet(revision=0, active={}),
                phi_hash=env.phi.hash,
                agent_identity_hash=UNSPECIFIED_IDENTITY,
                seeds=seed_list,
                worker_id=label,
            )
            sink = stack.enter_context(TraceWriter(Path(trace), metadata))
        for episode, seed in enumerate(seed_list):
            results.append(
                _episode(env, act, seed, sink=sink, episode=episode, label=label, version=version, on_reset=on_reset)
            )
    return tuple(results), env.env_steps


def held_out_record(
    cell: CellSpec,
    act: Callable[[np.ndarray], np.ndarray],
    *,
    iteration: int,
    env_steps_train: int,
    delta_pi: float,
    started: float,
    notes: Sequence[str],
    workdir: str | os.PathLike[str],
    label: str,
    horizon: int | None,
    **evaluate_kwargs: Any,
) -> IterationRecord:
    """One iteration's record of a method without ECMs: its held-out evaluation on
    ``cell.eval_seeds()`` (traced to ``traces/eval-NNN.mcap`` in ``workdir``) and what it spent.

    ``started`` is the iteration's ``time.perf_counter()`` at its start; ``evaluate_kwargs`` go to
    :func:`evaluate_policy` (``handoff_signals``, ``on_reset``).
    """
    episodes, eval_steps = evaluate_policy(
        cell.task,
        act,
        cell.eval_seeds(),
        phi=cell.phi,
        governance=cell.governance,
        perturbations=cell.perturbations,
        horizon=horizon,
        trace=Path(workdir) / "traces" / f"eval-{iteration:03d}.mcap",
        label=label,
        version=iteration,
        **evaluate_kwargs,
    )
    return IterationRecord(
        iteration=iteration,
        episodes=episodes,
        env_steps_train=env_steps_train,
        env_steps_eval=eval_steps,
        delta_pi=delta_pi,
        wall_s=time.perf_counter() - started,
        notes="; ".join(notes),
    )


def _episode(
    env: GovernedTaskEnv,
    act: Callable[[np.ndarray], np.ndarray],
    seed: int,
    *,
    sink: TraceSink | None,
    episode: int,
    label: str,
    version: int,
    on_reset: Callable[[], None] | None = None,
) -> EpisodeResult:
    """One seeded episode of ``act``, traced to ``sink`` when given."""
    started = time.perf_counter()
    obs, info = env.reset(seed=seed)
    if on_reset is not None:
        on_reset()
    reward = 0.0
    steps = unsafe = intervened = interventions = 0
    done = False
    while not done:
        next_obs, r, terminated, truncated, info = env.step(act(obs))
        if np.isfinite(r):
            reward += r
        unsafe += info["unsafe"]
        intervened += info["intervened"]
        interventions += len(info["interventions"])
        done = terminated or truncated
        if sink is not None:
            executed = tuple(info["action"].tolist())
            for iv in info["interventions"]:
                sink.write_intervention(
                    TraceIntervention(
                        episode=episode,
                        step=steps,
                        constraint=iv.constraint,
                        original_action=iv.original,
                        result_action=(iv.result if env.governance else executed),
                        reason=iv.reason if env.governance else NOT_ENFORCED_PREFIX + iv.reason,
                        enforced=env.governance,
                    )
                )
            if info["unsafe"]:
                sink.write_unsafe_step(
                    UnsafeStep(episode=episode, step=steps, broken=info["unsafe_axes"], reasons=info["unsafe_reasons"])
                )
            state = env.last_state
            sink.write_env_step(
                EnvStep(
                    episode=episode,
                    step=steps,
                    ecm=label,
                    version=version,
                    obs=obs,
                    action=executed,
                    reward=float(r),
                    next_obs=next_obs,
                    terminated=terminated,
                    truncated=truncated,
                    is_success=bool(info["is_success"]),
                    key_state=key_state(state.arms) if state is not None else {},
                )
            )
        obs = next_obs
        steps += 1
    result = EpisodeResult(
        seed=seed,
        success=bool(info["is_success"]),
        reward=reward,
        steps=steps,
        unsafe_steps=unsafe,
        interventions=intervened,
        strict_success=env.task_env.strict_success,
    )
    if sink is not None:
        sink.write_episode_summary(
            EpisodeSummary(
                episode=episode,
                seed=seed,
                success=result.success,
                total_reward=reward,
                steps=steps,
                interventions=interventions,
                unsafe_steps=unsafe,
                capability_set={},
                duration_s=time.perf_counter() - started,
            )
        )
    return result
