"""The execution manager: one episode of a task, ECM by ECM, every action through governance.

Each environment step:

1. No ECM running -> ask the decision policy π_A (:meth:`DecisionPolicy.decide`) with the
   task's signals and how the previous ECM ended; trace the choice to ``/plan``. A decision
   of ``ecm=None`` ends the episode there (its reason is traced); nothing holds still until
   the horizon.
2. The running ECM ends, before it is called, when its descriptor's termination predicate
   holds over ``env.signals()`` (an empty predicate never ends an ECM: "no condition" is not
   "done"). Then π_A decides again within the same step.
3. Call the ECM through its :class:`~capevo.runtime.ecm.EcmInvoker` (inputs marshalled per
   its interface, per-call timeout, exceptions/NaN/wrong shapes classified, recovery: retry,
   fall back to the previous version, or hold still). Its own ``done()`` or an exhausted step
   budget ends it (π_A decides again within the step); a failure that recovery could not mend
   executes the invoker's safe hold this step and then ends it as ``failed``. Every call is
   traced to ``/ecm/invocation``.
4. Govern the action with ``env.robot_state()``: R(a, Φ) = a | a′ | ⊥; on ⊥ hold still
   (:func:`~capevo.runtime.governance.hold_action`). Interventions go to
   ``/governance/intervention`` with ``enforced`` set to the governor's mode (counting mode
   writes them too, with the action that really ran as ``result_action`` and the reason
   prefixed ``not enforced:``). An invocation whose ECM's ``done()`` held is traced with
   outcome ``terminated``.
5. Step the environment, then grade the step with the episode's
   :class:`~capevo.runtime.safety_monitor.SafetyMonitor` (issue 18: ``unsafe`` is decided from
   the simulator's ground truth by code that shares nothing with the governor, so governance
   never grades itself); trace ``/env/step``. The monitor is handed the action that really
   ran: the governed one, or zeros when the task's actuation-failure perturbation dropped it
   (``info["actuation_dropped"]``).

The horizon (``truncated``) or success (``terminated``) also ends the episode; the state it
ends in was graded with its last step. ``/episode/summary`` closes it.

Invariants:
1. Nothing an ECM does (raise, hang in the sandbox, return NaN or a wrong shape, fail to
   marshal its inputs) propagates out of :func:`run_episode`; it is traced and counted.
2. Every executed action went through the governor; with an enforcing governor whose Φ caps
   the pose delta at or below the monitor's ``action_cap``, the monitor's action axes
   (``cap``, ``non_finite``) never fire.
3. The loaded capability set changes only in ``capabilities.begin_episode()``, called once
   before the reset: never in the middle of an ECM's execution.
4. ``outcome.steps`` equals the number of ``/env/step`` records written for the episode;
   ``outcome.interventions`` the number of ``/governance/intervention`` records;
   ``outcome.ecm_failures`` the number of invocation records with a failure outcome.
5. The policy is consulted at most ``max_decisions_per_step`` times without an env step in
   between; past that the episode ends (a policy that keeps choosing finished ECMs cannot
   spin forever).
6. ``outcome.unsafe_steps`` (and the ``/episode/summary`` record's) is the number of env steps
   whose :class:`~capevo.runtime.safety_monitor.SafetyVerdict` is unsafe; governance's
   :func:`~capevo.runtime.governance.unsafe_reasons` plays no part in it.
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ParamSpec, Protocol

import numpy as np

from capevo.errors import CapevoError, Invalid
from capevo.records import EcmVersion
from capevo.registry.predicates import predicate_holds
from capevo.runtime.ecm import FAILURES, EcmInvoker, Status, StepResult
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.governance import Governor, Phi, hold_action
from capevo.runtime.policy import Decision, DecisionContext, DecisionPolicy, StepEnd
from capevo.runtime.safety_monitor import SafetyLimits, SafetyMonitor, SafetyVerdict
from capevo.runtime.state import ActionLayout, RobotState
from capevo.runtime.traces import (
    NOT_ENFORCED_PREFIX,
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    PlanStep,
    TraceSink,
    UnsafeStep,
)
from capevo.runtime.traces import Intervention as TraceIntervention
from capevo.runtime.traces import Outcome as TraceOutcome

log = logging.getLogger(__name__)

DEFAULT_STEP_BUDGET = 200
DEFAULT_TIMEOUT_S = 0.5
MAX_DECISIONS_PER_STEP = 8
INTERRUPTED = "interrupted"
END_PLAN_ECM = ""
"""``ecm`` of the ``/plan`` record that traces the policy ending the episode."""

_TRACE_OUTCOME: Mapping[Status, TraceOutcome] = {
    Status.OK: TraceOutcome.OK,
    Status.TERMINATED: TraceOutcome.TERMINATED,
    Status.EXCEPTION: TraceOutcome.EXCEPTION,
    Status.TIMEOUT: TraceOutcome.TIMEOUT,
    Status.NAN: TraceOutcome.NAN,
    Status.BAD_SHAPE: TraceOutcome.BAD_SHAPE,
    Status.BUDGET_EXHAUSTED: TraceOutcome.BUDGET_EXHAUSTED,
}


class EpisodeEnv(Protocol):
    """What the loop needs of a task environment (:class:`~capevo.runtime.tasks.TaskEnv`)."""

    @property
    def task_spec(self) -> Any: ...

    @property
    def obs_dict(self) -> Mapping[str, np.ndarray]: ...

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]: ...

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]: ...

    def signals(self) -> dict[str, float]: ...

    def robot_state(self) -> RobotState: ...


class Capabilities(Protocol):
    """What the loop needs of the loaded ECMs (:class:`~capevo.runtime.capabilities.LoadedCapabilitySet`)."""

    @property
    def revision(self) -> int: ...

    @property
    def versions(self) -> dict[str, int]: ...

    @property
    def records(self) -> Mapping[str, EcmVersion]: ...

    def begin_episode(self) -> Sequence[Any]: ...

    def make_invoker(
        self, name: str, *, step_budget: int | None, timeout_s: float, default_gripper: float = 0.0
    ) -> EcmInvoker: ...


@dataclass(frozen=True, slots=True, kw_only=True)
class Activation:
    """One execution of one ECM within an episode."""

    ecm: str
    version: int
    start_step: int
    steps: int
    end: str
    """A :class:`StepEnd` value, or ``interrupted`` when the episode ended while it ran."""
    reason: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeRun:
    """Everything :func:`run_episode_detailed` learned about one episode."""

    outcome: EpisodeOutcome
    end_reason: str
    """``success``, ``horizon``, ``policy: <reason>``, ``stopped`` or ``no progress: ...``."""
    activations: tuple[Activation, ...]
    swaps: tuple[Any, ...] = ()
    """What ``capabilities.begin_episode()`` applied before the episode."""
    intervened_steps: int = 0
    """Steps where governance modified or rejected the action (or would have, when not enforced)."""
    rejected_steps: int = 0
    """Steps where governance answered ⊥ (or would have)."""
    unsafe_reasons: tuple[str, ...] = field(default_factory=tuple)
    """The first few unsafe-step reasons (the safety monitor's), for reports."""
    unsafe_by_constraint: Mapping[str, int] = field(default_factory=dict)
    """Unsafe steps per limit the safety monitor grades (``box``, ``cap``, ``force``,
    ``non_finite``); a step breaking two limits counts for both."""


def make_governor(env: Any, phi: Phi, *, enforce: bool = True) -> Governor:
    """R for ``env``'s action layout, with each arm's action frame read from the simulator.

    Also sets ``env.sense_proximity`` to whether ``phi`` reads proximity pairs, so an env
    governed by an envelope that does not (the paper's) skips the distance queries.

    Args:
        env: A :class:`~capevo.runtime.tasks.TaskEnv`.
        phi: The envelope.
        enforce: False for the evaluation-only counting mode.
    """
    from capevo.runtime.governance.robosuite_state import action_frames

    frames = action_frames(env.robosuite_env.robots)
    env.sense_proximity = phi.reads_proximity
    return phi.governor(env.task_spec.action_layout, enforce=enforce, frames=frames)


class _Running:
    __slots__ = (
        "attempt",
        "ecm",
        "end_after_step",
        "input_keys",
        "invoker",
        "record",
        "start_step",
        "steps",
        "termination",
    )

    def __init__(self, record: EcmVersion, invoker: EcmInvoker, start_step: int) -> None:
        self.record = record
        self.ecm = record.name
        self.invoker = invoker
        self.start_step = start_step
        self.steps = 0
        self.end_after_step: StepEnd | None = None
        self.input_keys = tuple(s.name for s in record.interface.inputs)
        self.termination = record.descriptor.termination


def _ecm_input(obs: Mapping[str, np.ndarray], keys: tuple[str, ...]) -> np.ndarray | tuple[()]:
    """The flat input an ECM with inputs ``keys`` saw, for its invocation record: the values of
    each key ``obs`` has, in order, flattened, as one read-only float32 array (``()`` for none)."""
    parts = [obs[k] for k in keys if k in obs]
    if not parts:
        return ()
    flat = np.concatenate(parts, axis=None, dtype=np.float32)
    flat.flags.writeable = False
    return flat


def key_state(arms: Sequence[Any]) -> dict[str, tuple[float, ...]]:
    """An env step's key state: each arm's end-effector position and force."""
    out: dict[str, tuple[float, ...]] = {}
    for i, arm in enumerate(arms):
        out[f"arm{i}_eef_pos"] = arm.eef_pos
        out[f"arm{i}_eef_force"] = arm.eef_force
    return out


def run_episode_detailed(
    env: EpisodeEnv,
    capabilities: Capabilities,
    policy: DecisionPolicy,
    governor: Governor,
    sink: TraceSink | None,
    *,
    seed: int,
    step_budget_per_ecm: int | None = DEFAULT_STEP_BUDGET,
    episode: int = 0,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    max_decisions_per_step: int = MAX_DECISIONS_PER_STEP,
    trace_path: str | None = None,
    should_stop: Callable[[], bool] | None = None,
    apply_swaps: bool = True,
    safety_limits: SafetyLimits | None = None,
) -> EpisodeRun:
    """Run one seeded episode of ``env``'s task with the loaded ECMs (see the module docstring).

    Args:
        env: The task environment (reused across episodes; reset here with ``seed``).
        capabilities: The loaded ECMs; ``begin_episode()`` is called first (hot swaps).
        policy: π_A, consulted whenever no ECM is running.
        governor: R(a, Φ) for the env's layout (see :func:`make_governor`). A counting
            governor (``enforce=False``) lets actions through.
        sink: Where trace records go; None writes none.
        seed: Fixes the episode's instance.
        step_budget_per_ecm: Steps one ECM activation may take; None for unlimited.
        episode: Episode index within the run (trace records carry it).
        timeout_s: Per-call compute limit of each ECM call.
        max_decisions_per_step: Policy calls allowed without an env step in between.
        trace_path: Recorded in the outcome.
        should_stop: Polled once per step; True ends the episode (``end_reason`` ``stopped``).
        apply_swaps: Call ``capabilities.begin_episode()`` first; False when the caller just
            did (e.g. to start a new trace file for a new capability set).
        safety_limits: The hard limits the safety monitor grades each step against; default
            the paper's (:class:`~capevo.runtime.safety_monitor.SafetyLimits`).

    Returns:
        The :class:`EpisodeRun`; its ``outcome`` is what evaluators return.

    Raises:
        Invalid: the policy chose an ECM that is not loaded, a bad argument, or an env the
            safety monitor cannot judge (not a task environment).
        CapevoError: whatever the policy or the environment raised (never what an ECM did).
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise Invalid(f"seed must be a non-negative integer, got {seed!r}", details={"field": "seed"})
    if max_decisions_per_step < 1:
        raise Invalid("max_decisions_per_step must be >= 1", details={"field": "max_decisions_per_step"})
    monitor = SafetyMonitor(env, safety_limits)  # type: ignore[arg-type]  # not a TaskEnv: Invalid
    swaps = tuple(capabilities.begin_episode()) if apply_swaps else ()
    spec = env.task_spec
    layout: ActionLayout = spec.action_layout
    dropped_action = (0.0,) * layout.dim
    enforce = governor.enforce
    governor.new_episode()
    records = capabilities.records
    versions = capabilities.versions
    revision = capabilities.revision

    started = time.perf_counter()
    obs, info = env.reset(seed=seed)
    # Traces keep the env's own (fresh, float32) observation arrays: read-only, so a record
    # can never change after it is written, and no tuple round trip (see traces.FloatVector).
    obs_t = _read_only(obs)
    attempts: Counter[str] = Counter()
    activations: list[Activation] = []
    running: _Running | None = None
    prev_ecm: str | None = None
    prev_end = StepEnd.STARTED
    plan_step = 0
    steps = 0
    total_reward = 0.0
    interventions = 0
    intervened_steps = 0
    rejected_steps = 0
    unsafe_steps = 0
    unsafe_examples: list[str] = []
    unsafe_by: Counter[str] = Counter()
    failures = 0
    success = bool(info.get("is_success", False))
    last_action: tuple[float, ...] | None = None
    end_reason = ""
    signals: dict[str, float] | None = None

    def current_signals() -> dict[str, float]:
        nonlocal signals
        if signals is None:
            signals = env.signals()
        return signals

    def finish(run: _Running, end: StepEnd | str, reason: str) -> None:
        nonlocal running, prev_ecm, prev_end
        activations.append(
            Activation(
                ecm=run.ecm,
                version=run.record.version,
                start_step=run.start_step,
                steps=run.steps,
                end=str(getattr(end, "value", end)),
                reason=reason,
            )
        )
        if isinstance(end, StepEnd):
            prev_ecm, prev_end = run.ecm, end
        running = None

    def count_unsafe(verdict: SafetyVerdict, where: str) -> None:
        nonlocal unsafe_steps
        unsafe_steps += 1
        unsafe_by.update(verdict.broken)
        if len(unsafe_examples) < 5:
            unsafe_examples.append(f"{where}: {'; '.join(verdict.reasons)}")

    def write_calls(run: _Running, result: StepResult) -> None:
        nonlocal failures
        if sink is None:
            failures += sum(1 for a in result.attempts if a.status in FAILURES)
            return
        # An ECM that declares no inputs is traced with the whole flat observation.
        input_state = _ecm_input(env.obs_dict, run.input_keys) if run.input_keys else obs_t
        for a in result.attempts:
            if a.status in FAILURES:
                failures += 1
            sink.write_invocation(
                EcmInvocation(
                    episode=episode,
                    step=steps,
                    ecm=a.ecm,
                    version=a.version,
                    input_state=input_state,
                    output=a.action,
                    duration_s=a.duration_s,
                    outcome=_TRACE_OUTCOME[a.status],
                    error=a.error,
                )
            )

    while True:
        if should_stop is not None and should_stop():
            end_reason = "stopped"
            break
        # --- choose and call an ECM until one yields this step's action ---------------
        action: tuple[float, ...] | None = None
        decisions = 0
        source: tuple[str, int] = ("", 0)
        while action is None:
            if running is None:
                if decisions >= max_decisions_per_step:
                    end_reason = f"no progress: {decisions} decisions without an env step"
                    break
                decisions += 1
                decision: Decision = policy.decide(
                    DecisionContext(
                        task=spec.name,
                        signals=current_signals(),
                        previous_ecm=prev_ecm,
                        previous_end=prev_end,
                        capabilities=records,
                        attempts=dict(attempts),
                    )
                )
                if decision.ecm is None:
                    end_reason = f"policy: {decision.reason}" if decision.reason else "policy: ended"
                    if sink is not None:
                        sink.write_plan_step(
                            PlanStep(episode=episode, step=plan_step, ecm=END_PLAN_ECM, version=0, reason=end_reason)
                        )
                    break
                record = records.get(decision.ecm)
                if record is None:
                    raise Invalid(
                        f"the policy chose ECM {decision.ecm!r}, which is not loaded "
                        f"(loaded: {', '.join(sorted(records))})",
                        details={"field": "ecm", "ecm": decision.ecm},
                    )
                attempts[record.name] += 1
                if sink is not None:
                    sink.write_plan_step(
                        PlanStep(
                            episode=episode,
                            step=plan_step,
                            ecm=record.name,
                            version=record.version,
                            reason=decision.reason,
                        )
                    )
                plan_step += 1
                invoker = capabilities.make_invoker(record.name, step_budget=step_budget_per_ecm, timeout_s=timeout_s)
                running = _Running(record, invoker, steps)
            run = running
            termination = run.termination
            if termination.all and predicate_holds(termination, current_signals()):
                finish(run, StepEnd.TERMINATED, "termination predicate holds")
                continue
            try:
                result = run.invoker.step(env.obs_dict)
            except CapevoError as exc:
                # The observation does not fit the ECM's interface: the ECM cannot run here.
                failures += 1
                if sink is not None:
                    sink.write_invocation(
                        EcmInvocation(
                            episode=episode,
                            step=steps,
                            ecm=run.ecm,
                            version=run.record.version,
                            input_state=(),
                            output=None,
                            duration_s=0.0,
                            outcome=TraceOutcome.EXCEPTION,
                            error=str(exc)[:2000],
                        )
                    )
                action = hold_action(layout, last_action)
                source = (run.ecm, run.record.version)
                run.end_after_step = StepEnd.FAILED
                break
            write_calls(run, result)
            if result.action is None:
                if result.status is Status.BUDGET_EXHAUSTED:
                    finish(run, StepEnd.BUDGET_EXHAUSTED, f"step budget of {step_budget_per_ecm} used up")
                else:
                    finish(run, StepEnd.TERMINATED, "done() is true")
                continue
            action = result.action
            used = result.attempts[-1]
            source = (used.ecm, used.version)
            if result.aborted:
                run.end_after_step = StepEnd.FAILED
        if action is None:
            break

        # --- govern, judge, step ----------------------------------------------------------
        state = env.robot_state()
        governed, ivs = governor(state, action)
        if ivs:
            intervened_steps += 1
            interventions += len(ivs)
        if governed is None:
            rejected_steps += 1
            executed = hold_action(layout, last_action)
        elif governed is action:
            executed = action
            if ivs and any(iv.result is None for iv in ivs):
                rejected_steps += 1
        else:
            executed = tuple(governed)
        if ivs and sink is not None:
            for iv in ivs:
                if enforce:
                    result_action = None if iv.result is None else iv.result
                    reason = iv.reason
                else:
                    result_action = executed
                    reason = NOT_ENFORCED_PREFIX + iv.reason
                sink.write_intervention(
                    TraceIntervention(
                        episode=episode,
                        step=steps,
                        constraint=iv.constraint,
                        original_action=iv.original,
                        result_action=result_action,
                        reason=reason,
                        enforced=enforce,
                    )
                )
        next_obs, reward, terminated, truncated, info = env.step(np.asarray(executed, dtype=np.float64))
        # Graded on what the robot really got: the task replaced a dropped action by zeros.
        verdict = monitor.judge(dropped_action if info.get("actuation_dropped") else executed)
        if verdict.unsafe:
            count_unsafe(verdict, f"step {steps}")
            if sink is not None:
                sink.write_unsafe_step(
                    UnsafeStep(episode=episode, step=steps, broken=verdict.broken, reasons=verdict.reasons)
                )
        signals = None
        next_t = _read_only(next_obs)
        reward = float(reward)
        if math.isfinite(reward):
            total_reward += reward
        success = bool(info.get("is_success", success))
        if sink is not None:
            sink.write_env_step(
                EnvStep(
                    episode=episode,
                    step=steps,
                    ecm=source[0],
                    version=source[1],
                    obs=obs_t,
                    action=executed,
                    reward=reward,
                    next_obs=next_t,
                    terminated=bool(terminated),
                    truncated=bool(truncated),
                    is_success=success,
                    key_state=key_state(state.arms),
                )
            )
        obs_t = next_t
        steps += 1
        last_action = executed
        if running is not None:
            running.steps += 1
            if running.end_after_step is not None:
                finish(running, running.end_after_step, "failed; recovery held still")
        if terminated or truncated:
            end_reason = "success" if terminated else "horizon"
            break

    if running is not None:
        finish(running, INTERRUPTED, f"episode ended: {end_reason}")
    duration = time.perf_counter() - started
    outcome = EpisodeOutcome(
        seed=seed,
        success=success,
        reward=total_reward,
        steps=steps,
        duration_s=duration,
        interventions=interventions,
        unsafe_steps=unsafe_steps,
        ecm_failures=failures,
        capability_set=dict(versions),
        trace_path=trace_path,
        phi_hash=governor.phi.hash,
        intervened_steps=intervened_steps,
        strict_success=getattr(env, "strict_success", None),
    )
    if sink is not None:
        sink.write_episode_summary(
            EpisodeSummary(
                episode=episode,
                seed=seed,
                success=success,
                total_reward=total_reward,
                steps=steps,
                interventions=interventions,
                unsafe_steps=unsafe_steps,
                capability_set=dict(versions),
                duration_s=duration,
                revision=revision,
            )
        )
    log.debug("episode %d (seed %d) ended: %s after %d steps", episode, seed, end_reason, steps)
    return EpisodeRun(
        outcome=outcome,
        end_reason=end_reason,
        activations=tuple(activations),
        swaps=swaps,
        intervened_steps=intervened_steps,
        rejected_steps=rejected_steps,
        unsafe_reasons=tuple(unsafe_examples),
        unsafe_by_constraint=dict(unsafe_by),
    )


P = ParamSpec("P")


def _outcome_only(fn: Callable[P, EpisodeRun], *, name: str, doc: str) -> Callable[P, EpisodeOutcome]:
    """``fn`` returning only its run's ``outcome``: the same parameters, one definition of them."""

    @functools.wraps(fn)
    def outcome(*args: P.args, **kwargs: P.kwargs) -> EpisodeOutcome:
        return fn(*args, **kwargs).outcome

    outcome.__name__ = outcome.__qualname__ = name
    outcome.__doc__ = doc
    outcome.__signature__ = inspect.signature(fn).replace(return_annotation="EpisodeOutcome")  # type: ignore[attr-defined]
    return outcome


run_episode = _outcome_only(
    run_episode_detailed,
    name="run_episode",
    doc="""Run one seeded episode and return its outcome.

    Takes exactly the arguments of :func:`run_episode_detailed` and returns its ``outcome``
    (an :class:`~capevo.runtime.evaluation.EpisodeOutcome`).
    """,
)


def _read_only(values: np.ndarray) -> np.ndarray:
    values.flags.writeable = False
    return values
