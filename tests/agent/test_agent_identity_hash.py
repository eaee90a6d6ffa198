"""Identity invariance: the hash of π_A and M_id, PersistentAgent's checks and Δπ.

Fingerprint invariants 1-3, agent invariants 1-4, drift invariants 1-3.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import MappingProxyType

import pytest
from _agent_helpers import PICK_FAR, context, task_capabilities

from capevo.agent import (
    Belief,
    DecompositionPolicy,
    EpisodeRecord,
    EpisodicMemory,
    IdentityMemory,
    LlmPolicy,
    LlmSettings,
    PersistentAgent,
    PolicyDriftTracker,
    PolicyParameters,
    ScriptedChatClient,
    identity_hash,
    parse_identity,
    policy_drift,
    read_episodes,
)
from capevo.agent.fingerprint import changed_paths
from capevo.errors import ErrorCode, IdentityViolation, Invalid
from capevo.records.audit import canonical_json
from capevo.runtime.policy import DecisionPolicy


@pytest.fixture
def memory(tmp_path: Path) -> Iterator[EpisodicMemory]:
    m = EpisodicMemory(tmp_path / "episodes.jsonl")
    yield m
    m.close()


def make_agent(memory: EpisodicMemory, *, max_attempts: int = 3) -> PersistentAgent:
    identity = IdentityMemory.default()
    policy = DecompositionPolicy(identity=identity, parameters=PolicyParameters(max_attempts_per_ecm=max_attempts))
    return PersistentAgent(policy, identity, memory)


def test_hash_is_sha256_of_the_canonical_document() -> None:
    identity = IdentityMemory.default()
    policy = DecompositionPolicy(identity=identity)
    body = {
        "policy": {"type": "DecompositionPolicy", "parameters": {"max_attempts_per_ecm": 3}},
        "identity": identity.to_dict(),
    }
    assert identity_hash(policy, identity) == hashlib.sha256(canonical_json(body).encode()).hexdigest()


def test_hash_ignores_yaml_layout_but_not_values() -> None:
    a = parse_identity("version: 1\nname: a\ndecompositions: {t: [t.a, t.b]}\n")
    b = parse_identity('# comment\ndecompositions:\n  t:\n    - t.a\n    - t.b\nname: "a"\nversion: 1\n')
    c = parse_identity("version: 1\nname: a\ndecompositions: {t: [t.b, t.a]}\n")
    h = [identity_hash(DecompositionPolicy(identity=m), m) for m in (a, b, c)]
    assert h[0] == h[1] != h[2]
    p4 = DecompositionPolicy(identity=a, parameters=PolicyParameters(max_attempts_per_ecm=4))
    assert identity_hash(p4, a) != h[0]


def test_hash_is_the_same_in_another_process() -> None:
    code = (
        "from capevo.agent import DecompositionPolicy, IdentityMemory, identity_hash\n"
        "m = IdentityMemory.default()\n"
        "print(identity_hash(DecompositionPolicy(identity=m), m))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    m = IdentityMemory.default()
    assert out.stdout.strip() == identity_hash(DecompositionPolicy(identity=m), m)


def test_changed_paths_names_every_difference() -> None:
    before = {"a": 1, "b": [1, 2], "c": {"d": "x"}, "e": 1}
    after = {"a": 1, "b": [1, 3], "c": {"d": "y"}, "f": 2, "e": 1.0}
    assert changed_paths(before, after) == ["b[1]", "c.d", "e", "f"]
    assert changed_paths(before, json.loads(json.dumps(before))) == []


def test_agent_hash_is_fixed_at_start_and_rechecked(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    assert len(agent.identity_hash) == 64
    assert agent.check_identity() == agent.identity_hash
    assert agent.identity_hash == identity_hash(agent.policy, agent.identity)
    assert isinstance(agent, DecisionPolicy)
    caps = task_capabilities("pick")
    assert agent.decide(context("pick", PICK_FAR, caps)).ecm == "pick.reach"


def _violation(agent: PersistentAgent) -> IdentityViolation:
    with pytest.raises(IdentityViolation) as info:
        agent.check_identity()
    assert info.value.code is ErrorCode.IDENTITY_VIOLATION
    assert info.value.details["expected_hash"] == agent.identity_hash
    return info.value


def test_mutating_a_policy_parameter_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    start = agent.identity_hash
    object.__setattr__(agent.policy.parameters, "max_attempts_per_ecm", 5)
    err = _violation(agent)
    assert agent.identity_hash == start  # fixed at start-up
    assert err.details["actual_hash"] == identity_hash(agent.policy, agent.identity) != start
    assert err.message == (
        "agent identity changed since start-up: policy parameters changed (parameters.max_attempts_per_ecm: 3 -> 5)"
    )
    assert err.details["changed"] == ["policy parameters"]


def test_swapping_the_parameters_record_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    object.__setattr__(agent.policy, "parameters", PolicyParameters(max_attempts_per_ecm=9))
    assert "parameters.max_attempts_per_ecm: 3 -> 9" in _violation(agent).message


def test_a_broken_parameter_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    object.__setattr__(agent.policy.parameters, "max_attempts_per_ecm", float("nan"))
    err = _violation(agent)
    assert err.message.startswith("policy parameters changed since start-up and can no longer be hashed")


def test_editing_a_decomposition_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    edited = dict(agent.identity.decompositions)
    edited["pick"] = ("pick.reach", "pick.lift")
    object.__setattr__(agent.identity, "decompositions", MappingProxyType(edited))
    err = _violation(agent)
    # The policy plans with the same (edited) object, so both views report the change.
    assert err.message == (
        "agent identity changed since start-up: identity memory changed at decompositions.pick; "
        "the identity memory the policy plans with changed at decompositions.pick"
    )
    assert err.details["changed"] == ["identity memory", "policy identity memory"]


def test_editing_a_goal_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    object.__setattr__(agent.identity.goals[0], "text", "Win at any cost.")
    assert "identity memory changed at goals[0].text" in _violation(agent).message


def test_adding_a_belief_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    object.__setattr__(agent.identity, "beliefs", (*agent.identity.beliefs, Belief(id="new", text="x")))
    assert "identity memory changed at beliefs" in _violation(agent).message


def test_replacing_the_policys_identity_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    other = parse_identity("version: 1\nname: other\ndecompositions: {t: [t.a]}\n")
    object.__setattr__(agent.policy, "identity", other)
    err = _violation(agent)
    assert err.message.startswith(
        "agent identity changed since start-up: the identity memory the policy plans with changed at "
    )
    assert err.details["changed"] == ["policy identity memory"]


def test_replacing_the_policy_class_is_caught(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    llm = LlmPolicy(
        fallback=agent.policy,  # type: ignore[arg-type]
        settings=LlmSettings(base_url="http://127.0.0.1:9/v1", model="m"),
        client=ScriptedChatClient([]),
    )
    object.__setattr__(agent, "_policy", llm)
    err = _violation(agent)
    assert "policy parameters changed (" in err.message and "type: 'DecompositionPolicy' -> 'LlmPolicy'" in err.message


def test_llm_policy_settings_are_part_of_the_identity(memory: EpisodicMemory) -> None:
    identity = IdentityMemory.default()
    llm = LlmPolicy(
        fallback=DecompositionPolicy(identity=identity),
        settings=LlmSettings(base_url="http://127.0.0.1:9/v1", model="m1", api_key="secret-key"),
        client=ScriptedChatClient([]),
    )
    agent = PersistentAgent(llm, identity, memory)
    assert "secret-key" not in canonical_json(llm.parameters.to_dict()) + repr(llm)
    object.__setattr__(llm.settings, "model", "m2")
    assert "parameters.model: 'm1' -> 'm2'" in _violation(agent).message


def test_begin_iteration_checks_before_recording_drift(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    assert agent.begin_iteration(0) == 0.0
    object.__setattr__(agent.policy.parameters, "max_attempts_per_ecm", 6)
    with pytest.raises(IdentityViolation):
        agent.begin_iteration(1)
    assert agent.policy_drift() == 0.0  # the changed θ was never recorded


def test_policy_drift_is_exactly_zero_over_iterations(memory: EpisodicMemory) -> None:
    agent = make_agent(memory)
    caps = task_capabilities("pick")
    for it in range(5):
        assert agent.begin_iteration(it) == 0.0
        agent.decide(context("pick", PICK_FAR, caps))
        agent.remember(EpisodeRecord(iteration=it, task="pick", seed=it, success=False, reward=0.0, steps=1))
    assert agent.policy_drift() == 0.0
    assert [r.iteration for r in read_episodes(memory.path).records] == [0, 1, 2, 3, 4]


def test_the_agent_refuses_a_policy_planning_with_another_identity(memory: EpisodicMemory) -> None:
    other = parse_identity("version: 1\nname: other\ndecompositions: {t: [t.a]}\n")
    with pytest.raises(Invalid) as info:
        PersistentAgent(DecompositionPolicy(identity=other), IdentityMemory.default(), memory)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message.startswith("policy: plans with an identity memory that differs from the agent's at ")


def test_the_agent_refuses_a_policy_without_parameters(memory: EpisodicMemory) -> None:
    class Bare:
        def decide(self, context: object) -> object:
            return None

    with pytest.raises(Invalid) as info:
        PersistentAgent(Bare(), IdentityMemory.default(), memory)  # type: ignore[arg-type]
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "policy: Bare lacks identity, parameters, parameters_vector() or decide()"


def test_policy_drift_formula() -> None:
    assert policy_drift((3.0, 4.0), (3.0, 4.0)) == 0.0
    assert policy_drift((3.0, 4.0), (6.0, 8.0)) == pytest.approx(1.0)
    assert policy_drift((3.0, 4.0), (3.0, 4.5)) == pytest.approx(0.1)
    assert policy_drift((0.0, 0.0), (0.0, 1e-12), eps=1e-12) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("first", "last", "message"),
    [
        ((1.0,), (1.0, 2.0), "last: has 2 parameters but first has 1; the policy's parameter layout changed"),
        ((1.0,), (float("nan"),), "last[0]: must be finite, got nan"),
        ((float("inf"),), (1.0,), "first[0]: must be finite, got inf"),
    ],
)
def test_policy_drift_errors(first: tuple[float, ...], last: tuple[float, ...], message: str) -> None:
    with pytest.raises(Invalid) as info:
        policy_drift(first, last)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == message


def test_drift_tracker_keeps_the_first_vector() -> None:
    t = PolicyDriftTracker()
    assert t.drift() == 0.0
    assert t.observe(0, (3.0, 4.0)) == 0.0
    assert t.observe(1, (3.0, 4.5)) == pytest.approx(0.1)
    assert t.observe(2, (3.0, 4.0)) == 0.0
    assert t.observe(2, (6.0, 8.0)) == pytest.approx(1.0)
    assert (t.first_iteration, t.last_iteration) == (0, 2)
    assert t.drift() == pytest.approx(1.0)
    with pytest.raises(Invalid) as info:
        t.observe(1, (3.0, 4.0))
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "iteration: 1 comes before the last recorded iteration 2"
