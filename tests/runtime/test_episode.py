"""The episode loop on real robosuite T1 episodes with real code ECMs from a real registry.

Covers the invariants of :mod:`capevo.runtime.episode`: ECM failures never crash the loop
(1), governance on every action and zero unsafe steps under an enforcing governor (2), swaps
only at episode boundaries (3), trace counts equal outcome counts (4), the no-progress guard
(5), unsafe steps are the safety monitor's verdicts on what really ran (6:
``test_unsafe_is_the_monitors_verdict_on_the_action_that_really_ran``); plus the policy ending
an episode and recovery by fallback.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from runtime_support import (
    BAD_SHAPE,
    HANGS,
    NAN,
    OUT_OF_BOX,
    RAISES,
    REACH,
    REACH_DONE_AT_ONCE,
    publish,
    publish_pick,
)

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.errors import Invalid
from capevo.records import Origin
from capevo.registry.local import LocalRegistry
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.episode import END_PLAN_ECM, make_governor, run_episode, run_episode_detailed
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.governance import Phi
from capevo.runtime.policy import Decision, DecisionContext, StepEnd
from capevo.runtime.safety_monitor import SafetyLimits
from capevo.runtime.tasks import Perturbations, TaskEnv, make_task, task_spec
from capevo.runtime.traces import MemoryTraceSink, Outcome, TraceMetadata, TraceReader, TraceWriter

pytestmark = pytest.mark.slow

HORIZON = 40
PHI = Phi.default()


@pytest.fixture(scope="module")
def env() -> Iterator[TaskEnv]:
    e = make_task("T1", horizon=HORIZON)  # perturbations on: the benchmark setting
    yield e
    e.close()


@pytest.fixture
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    with LocalRegistry(tmp_path / "registry", actor="tester") as reg:
        yield reg


@pytest.fixture
def policy() -> DecompositionPolicy:
    return DecompositionPolicy(identity=IdentityMemory.default())


def shapes(env: TaskEnv) -> dict[str, tuple[int, ...]]:
    env.reset(seed=0)
    return {k: tuple(v.shape) for k, v in env.obs_dict.items()}


def load(registry: LocalRegistry, env: TaskEnv, **kwargs: object) -> LoadedCapabilitySet:
    return LoadedCapabilitySet(registry, "T1", observation_shapes=shapes(env), **kwargs)  # type: ignore[arg-type]


def test_pick_episode_is_traced_to_mcap_and_read_back(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy, tmp_path: Path
) -> None:
    published = publish_pick(registry)
    path = tmp_path / "run.mcap"
    with load(registry, env) as caps:
        metadata = TraceMetadata.collect(
            run_id="test-run",
            task="pick",
            capability_set=caps.capability_set,
            phi_hash=PHI.hash,
            agent_identity_hash="agent-hash",
            seeds=(0,),
        )
        with TraceWriter(path, metadata) as sink:
            run = run_episode_detailed(
                env, caps, policy, make_governor(env, PHI), sink, seed=0, episode=0, trace_path=str(path)
            )
    out = run.outcome
    assert out.seed == 0 and out.trace_path == str(path)
    assert 0 < out.steps <= HORIZON
    assert out.unsafe_steps == 0
    assert out.ecm_failures == 0
    assert dict(out.capability_set) == {n: r.version for n, r in published.items()}
    # reach ran first and ended by its descriptor's termination predicate
    first = run.activations[0]
    assert (first.ecm, first.end) == ("pick.reach", StepEnd.TERMINATED.value)
    assert first.reason == "termination predicate holds"
    assert [a.ecm for a in run.activations][:2] == ["pick.reach", "pick.grasp"]
    assert run.end_reason in ("success", "horizon")
    assert out.success == (run.end_reason == "success")

    with TraceReader(path) as reader:
        meta = reader.metadata()
        assert meta.phi_hash == PHI.hash
        assert meta.registry_revision == registry.capability_set().revision
        plans = list(reader.plan_steps())
        invocations = list(reader.invocations())
        steps = list(reader.env_steps())
        interventions = list(reader.interventions())
        (summary,) = list(reader.episode_summaries())
    assert [p.ecm for p in plans] == [a.ecm for a in run.activations]
    assert [p.version for p in plans] == [published[p.ecm].version for p in plans]
    assert len(steps) == out.steps
    assert [s.step for s in steps] == list(range(out.steps))
    # one successful call per step: the ECM that produced each executed action
    assert len(invocations) == out.steps
    assert all(i.outcome is Outcome.OK for i in invocations)
    assert [i.ecm for i in invocations] == [s.ecm for s in steps]
    assert len(interventions) == out.interventions
    assert summary.steps == out.steps and summary.success == out.success
    assert summary.interventions == out.interventions and summary.unsafe_steps == 0
    assert math.isclose(summary.total_reward, out.reward, rel_tol=1e-9)
    assert dict(summary.capability_set) == dict(out.capability_set)
    assert steps[-1].is_success == out.success
    assert set(steps[0].key_state) == {"arm0_eef_pos", "arm0_eef_force"}


def test_invocation_inputs_are_the_ecms_inputs_from_the_observation(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    # Each invocation record holds what its ECM read: the values of its declared inputs at that
    # step, in order, as float32 (checked against the step's flat observation).
    published = publish_pick(registry)
    sink = MemoryTraceSink()
    with load(registry, env) as caps:
        run_episode(env, caps, policy, make_governor(env, PHI), sink, seed=3, episode=0)
    positions: dict[str, range] = {}
    at = 0
    for key in env.task_spec.observation_keys:
        size = int(np.size(env.obs_dict[key]))
        positions[key] = range(at, at + size)
        at += size
    obs_at = {s.step: np.asarray(s.obs, dtype=np.float32) for s in sink.env_steps}
    calls = sink.invocations
    for call in calls:
        keys = [spec.name for spec in published[call.ecm].interface.inputs]
        index = [i for key in keys for i in positions[key]]
        assert np.array_equal(np.asarray(call.input_state, dtype=np.float32), obs_at[call.step][index])
    assert len(calls) > 10


def test_adversarial_ecm_cannot_leave_the_box_with_governance(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    publish_pick(registry, reach=OUT_OF_BOX)
    with load(registry, env) as caps:
        on, off = MemoryTraceSink(), MemoryTraceSink()
        governed = run_episode(env, caps, policy, make_governor(env, PHI), on, seed=3)
        counted = run_episode(env, caps, policy, make_governor(env, PHI, enforce=False), off, seed=3)
    # governance on: the box's margin stops the climb before the +z face
    assert governed.steps == HORIZON
    assert governed.unsafe_steps == 0
    assert governed.interventions > 0
    # steps governance touched: one per distinct step of its records, and so never more than them
    assert governed.intervened_steps == len({i.step for i in on.interventions}) <= governed.interventions
    assert EpisodeOutcome.from_dict(governed.to_dict()) == governed
    assert {i.constraint for i in on.interventions} == {"workspace_box"}
    assert max(s.key_state["arm0_eef_pos"][2] for s in on.env_steps) <= 1.3
    assert all(i.result_action is not None and i.result_action[2] == 0.0 for i in on.interventions)
    assert all(i.enforced for i in on.interventions)
    # governance off (counting): the same ECM leaves the box, and R says it would have intervened
    assert counted.unsafe_steps > 0
    assert counted.interventions > 0
    assert all(i.reason.startswith("not enforced: ") for i in off.interventions)
    assert not any(i.enforced for i in off.interventions)
    assert max(s.key_state["arm0_eef_pos"][2] for s in off.env_steps) > 1.3


@pytest.mark.parametrize(
    ("source", "outcome"),
    [(RAISES, Outcome.EXCEPTION), (NAN, Outcome.NAN), (BAD_SHAPE, Outcome.BAD_SHAPE)],
    ids=["raises", "nan", "bad-shape"],
)
def test_failing_ecm_never_crashes_the_episode(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy, source: str, outcome: Outcome
) -> None:
    publish_pick(registry, reach=source)
    sink = MemoryTraceSink()
    with load(registry, env, recovery="retry") as caps:
        run = run_episode_detailed(env, caps, policy, make_governor(env, PHI), sink, seed=1)
    out = run.outcome
    limit = policy.parameters.max_attempts_per_ecm
    # each activation: the call fails, the retry fails, the safe hold runs, the ECM ends failed
    assert [a.end for a in run.activations] == [StepEnd.FAILED.value] * limit
    assert out.steps == limit
    assert out.ecm_failures == 2 * limit
    assert run.end_reason.startswith("policy: pick.reach reached its attempt limit")
    assert [i.outcome for i in sink.invocations] == [outcome] * (2 * limit)
    assert all(i.output is None and i.error for i in sink.invocations)
    # the held action: no motion, gripper at its default
    assert all(s.action == (0.0,) * 7 for s in sink.env_steps)
    assert sink.plan_steps[-1].ecm == END_PLAN_ECM and sink.plan_steps[-1].reason == run.end_reason
    (summary,) = sink.episode_summaries
    assert summary.steps == out.steps


def test_hanging_untrusted_ecm_is_timed_out_in_its_sandbox(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    publish_pick(registry)
    publish(registry, "pick.reach", HANGS, origin=Origin.LLM)  # untrusted: runs in a sandbox worker
    sink = MemoryTraceSink()
    with load(registry, env, recovery="abort") as caps:
        assert not caps.loaded("pick.reach").in_process
        run = run_episode_detailed(env, caps, policy, make_governor(env, PHI), sink, seed=2, timeout_s=0.3)
    assert run.outcome.steps == policy.parameters.max_attempts_per_ecm
    assert [a.end for a in run.activations] == [StepEnd.FAILED.value] * run.outcome.steps
    outcomes = [i.outcome for i in sink.invocations]
    assert outcomes[0] is Outcome.TIMEOUT
    assert set(outcomes) <= {Outcome.TIMEOUT, Outcome.EXCEPTION}  # a worker past max_restarts is dead
    assert run.outcome.ecm_failures == len(outcomes)


def test_fallback_to_the_previous_version_keeps_the_episode_going(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    good = publish_pick(registry)["pick.reach"]
    bad = publish(registry, "pick.reach", RAISES)
    sink = MemoryTraceSink()
    with load(registry, env, recovery="fallback") as caps:
        assert caps.versions["pick.reach"] == bad.version
        fallback = caps.fallback("pick.reach")
        assert fallback is not None and fallback.version == good.version
        run = run_episode_detailed(env, caps, policy, make_governor(env, PHI), sink, seed=0)
    first, second = sink.invocations[:2]
    assert (first.version, first.outcome) == (bad.version, Outcome.EXCEPTION)
    assert (second.version, second.outcome) == (good.version, Outcome.OK)
    # the fallback is sticky for the activation: reach then runs on the good version
    reach_steps = [s for s in sink.env_steps if s.ecm == "pick.reach"]
    assert reach_steps and all(s.version == good.version for s in reach_steps)
    assert run.activations[0].end == StepEnd.TERMINATED.value
    assert run.outcome.ecm_failures == 1


class SwapDuringEpisode:
    """π_A that, on its first decision, asks for a hot swap (as a registry event would)."""

    def __init__(self, inner: DecompositionPolicy, caps: LoadedCapabilitySet, name: str, version: int) -> None:
        self.inner, self.caps, self.name, self.version = inner, caps, name, version
        self.queued = False

    def decide(self, context: DecisionContext) -> Decision:
        if not self.queued:
            self.caps.queue_swap(self.name, self.version)
            self.queued = True
        return self.inner.decide(context)


def test_hot_swap_applies_only_between_episodes(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    old = publish_pick(registry)["pick.reach"]
    with load(registry, env) as caps:
        new = publish(registry, "pick.reach", REACH.replace('"gain": 10.0', '"gain": 8.0'))
        swapping = SwapDuringEpisode(policy, caps, "pick.reach", new.version)
        sink = MemoryTraceSink()
        first = run_episode_detailed(env, caps, swapping, make_governor(env, PHI), sink, seed=0, episode=0)
        # queued mid-episode, not applied: every reach call of episode 0 ran the old version
        assert swapping.queued and caps.pending() == {"pick.reach": new.version}
        assert {i.version for i in sink.invocations if i.ecm == "pick.reach"} == {old.version}
        assert first.outcome.capability_set["pick.reach"] == old.version
        second = run_episode_detailed(env, caps, policy, make_governor(env, PHI), sink, seed=0, episode=1)
    (swap,) = second.swaps
    assert (swap.name, swap.from_version, swap.to_version, swap.applied) == (
        "pick.reach",
        old.version,
        new.version,
        True,
    )
    assert second.outcome.capability_set["pick.reach"] == new.version
    assert {i.version for i in sink.invocations if i.ecm == "pick.reach" and i.episode == 1} == {new.version}
    assert [s.capability_set["pick.reach"] for s in sink.episode_summaries] == [old.version, new.version]


class EndAtOnce:
    def decide(self, context: DecisionContext) -> Decision:
        return Decision(ecm=None, reason="nothing to do today")


def test_policy_ending_the_episode_ends_it_there(env: TaskEnv, registry: LocalRegistry) -> None:
    publish_pick(registry)
    sink = MemoryTraceSink()
    with load(registry, env) as caps:
        run = run_episode_detailed(env, caps, EndAtOnce(), make_governor(env, PHI), sink, seed=0)
    assert run.outcome.steps == 0 and not run.outcome.success
    assert run.end_reason == "policy: nothing to do today"
    (plan,) = sink.plan_steps
    assert (plan.ecm, plan.reason) == (END_PLAN_ECM, run.end_reason)
    assert sink.env_steps == [] and len(sink.episode_summaries) == 1


class AlwaysReach:
    def decide(self, context: DecisionContext) -> Decision:
        return Decision(ecm="pick.reach", reason="again")


def test_policy_that_makes_no_progress_cannot_spin_forever(env: TaskEnv, registry: LocalRegistry) -> None:
    publish_pick(registry, reach=REACH_DONE_AT_ONCE)
    sink = MemoryTraceSink()
    with load(registry, env) as caps:
        run = run_episode_detailed(
            env, caps, AlwaysReach(), make_governor(env, PHI), sink, seed=0, max_decisions_per_step=5
        )
    assert run.outcome.steps == 0
    assert run.end_reason == "no progress: 5 decisions without an env step"
    assert [a.reason for a in run.activations] == ["done() is true"] * 5
    # done() is the ECM's own normal end: traced as terminated, not ok, not a failure
    assert [i.outcome for i in sink.invocations] == [Outcome.TERMINATED] * 5
    assert run.outcome.ecm_failures == 0


class ChoosesUnknown:
    def decide(self, context: DecisionContext) -> Decision:
        return Decision(ecm="pick.teleport")


def test_policy_choosing_an_unloaded_ecm_is_invalid(env: TaskEnv, registry: LocalRegistry) -> None:
    publish_pick(registry)
    with load(registry, env) as caps, pytest.raises(Invalid) as err:
        run_episode(env, caps, ChoosesUnknown(), make_governor(env, PHI), None, seed=0)
    assert err.value.code.value == "invalid"
    assert "the policy chose ECM 'pick.teleport', which is not loaded" in err.value.message


def test_negative_seed_is_refused(env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy) -> None:
    publish_pick(registry)
    with load(registry, env) as caps, pytest.raises(Invalid) as err:
        run_episode(env, caps, policy, make_governor(env, PHI), None, seed=-1)
    assert err.value.message == "seed must be a non-negative integer, got -1"


def test_exhausted_step_budget_hands_back_to_the_policy(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    publish_pick(registry)
    with load(registry, env) as caps:
        run = run_episode_detailed(env, caps, policy, make_governor(env, PHI), None, seed=0, step_budget_per_ecm=3)
    limit = policy.parameters.max_attempts_per_ecm
    assert [(a.ecm, a.steps, a.end) for a in run.activations] == [
        ("pick.reach", 3, StepEnd.BUDGET_EXHAUSTED.value)
    ] * limit
    assert run.outcome.steps == 3 * limit
    assert run.end_reason.startswith("policy: pick.reach reached its attempt limit")


def test_the_env_senses_proximity_only_when_its_envelope_reads_it(env: TaskEnv) -> None:
    env.reset(seed=0)
    make_governor(env, Phi.for_task(task_spec("T1")))
    assert env.sense_proximity and Phi.for_task(task_spec("T1")).reads_proximity
    for _ in range(12):  # down towards the bin floor, into the sensor's reach of the scene
        env.step([0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0])
    assert any(arm.near for arm in env.robot_state().arms)  # type: ignore[attr-defined]
    make_governor(env, PHI)
    assert not env.sense_proximity and not PHI.reads_proximity
    assert all(arm.near == () for arm in env.robot_state().arms)  # type: ignore[attr-defined]


def test_records_carry_the_envs_observations_read_only(
    env: TaskEnv, registry: LocalRegistry, policy: DecompositionPolicy
) -> None:
    # Traces keep the env's own float32 observation arrays, with no tuple round trip: each step's
    # obs is the previous step's next_obs object, and neither can change after it is written.
    publish_pick(registry)
    sink = MemoryTraceSink()
    with load(registry, env) as caps:
        run = run_episode_detailed(env, caps, policy, make_governor(env, PHI), sink, seed=4)
        reach_inputs = caps.records["pick.reach"].interface.inputs
    steps, calls = sink.env_steps, sink.invocations
    assert len(steps) == run.outcome.steps > 1 and calls
    for before, after in itertools.pairwise(steps):
        assert after.obs is before.next_obs
    vectors = [v for s in steps for v in (s.obs, s.next_obs)] + [c.input_state for c in calls]
    for v in vectors:
        assert isinstance(v, np.ndarray) and v.dtype == np.float32 and v.ndim == 1 and not v.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        steps[0].next_obs[0] = 1.0
    # an invocation's input is its ECM's interface inputs, flattened
    reach_size = sum(math.prod(spec.shape) for spec in reach_inputs)
    assert all(c.input_state.size == reach_size for c in calls if c.ecm == "pick.reach")


@pytest.mark.parametrize("drop_p", [0.0, 1.0], ids=["every-action-runs", "every-action-dropped"])
def test_unsafe_is_the_monitors_verdict_on_the_action_that_really_ran(
    registry: LocalRegistry, policy: DecompositionPolicy, drop_p: float
) -> None:
    # OUT_OF_BOX commands a pose delta of norm 1.0 every step; counting governance lets it through
    # and Φ's cap (1.5) has nothing against it. Graded against a 0.5 cap, every step that ran it is
    # unsafe on ``cap``; a step whose action the task dropped ran zeros, and is not.
    env = make_task("T1", horizon=HORIZON, perturbations=Perturbations(actuation_failure_p=drop_p))
    publish_pick(registry, reach=OUT_OF_BOX)
    sink = MemoryTraceSink()
    try:
        with load(registry, env) as caps:
            run = run_episode_detailed(
                env,
                caps,
                policy,
                make_governor(env, PHI, enforce=False),
                sink,
                seed=3,
                safety_limits=SafetyLimits(action_cap=0.5),
            )
    finally:
        env.close()
    out = run.outcome
    assert out.steps == HORIZON
    (summary,) = sink.episode_summaries
    assert summary.unsafe_steps == out.unsafe_steps == len(sink.unsafe_steps)
    # Each unsafe step is on /safety/unsafe, at its env step, with the monitor's axes and reasons.
    # (the hand climbs out of the box too: those steps break "box" as well)
    assert all("cap" in u.broken and len(u.reasons) == len(u.broken) for u in sink.unsafe_steps)
    assert {u.step for u in sink.unsafe_steps} <= {s.step for s in sink.env_steps}
    if drop_p == 0.0:
        assert run.unsafe_by_constraint.get("cap") == out.steps == out.unsafe_steps
        assert run.unsafe_reasons[0].startswith("step 0: arm 0: cap: pose-delta norm 1 is above 0.5")
    else:
        # The hand never moved: nothing left the box, nothing above the cap ran.
        assert out.unsafe_steps == 0 and run.unsafe_by_constraint == {} and run.unsafe_reasons == ()
    assert all(s.action[:6] == (0.0, 0.0, 1.0, 0.0, 0.0, 0.0) for s in sink.env_steps)  # traced as commanded
