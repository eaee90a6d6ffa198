"""Each package's ``__all__`` is exactly the public API users should import, and every name resolves."""

from __future__ import annotations

import importlib

import pytest

PUBLIC = {
    "capevo.registry": {
        "Action", "ArtifactRef", "AuditEvent", "CapabilitySet", "Client", "Descriptor", "EcmDetail",
        "EcmSummary", "EcmVersion", "IOSpec", "Interface", "Kind", "LocalRegistry", "Origin", "Predicate",
        "Provenance", "PublishSpec", "Registry", "State", "VerifyReport", "dump_publish_spec", "open_registry",
        "parse_publish_spec", "serve",
    },
    "capevo.baselines": {
        "AgentModification", "AgentModificationBC", "Budget", "CellSpec", "Emit", "EpisodeResult", "GovernedTaskEnv",
        "IterationRecord", "Method", "Skimo", "Spirl", "evaluate_policy",
    },
    "capevo.storage": {"AbstractStore", "BlobStore", "SqliteStore"},
    "capevo.runtime": {
        "ActionLayout", "ArmActionLayout", "ArmState", "Decision", "DecisionContext", "DecisionPolicy",
        "EpisodeOutcome", "Evaluator", "RobotState", "SafetyLimits", "SafetyMonitor", "SafetyVerdict", "StepEnd",
    },
    "capevo.records": {
        "Action", "ArtifactRef", "Attribution", "AuditEvent", "Auth", "COMPARISON_OPS", "CapabilitySet", "Condition",
        "DEFAULT_MEDIA_TYPES", "Descriptor", "EcmDetail", "EcmSummary", "EcmVersion", "IOSpec", "Interface", "Kind",
        "Mutation", "Origin", "Predicate", "Provenance", "PublishSpec", "State", "VerifyReport",
    },
    "capevo.agent": {
        "ALL_DONE", "AgentPolicy", "Belief", "ChatClient", "DecompositionPolicy", "EpisodeRecord", "EpisodicLog",
        "EpisodicMemory", "Fingerprint", "Goal", "HttpChatClient", "IdentityMemory", "LlmParameters", "LlmPolicy",
        "LlmSettings", "ParameterRecord", "PersistentAgent", "PlanStep", "PolicyDriftTracker", "PolicyParameters",
        "ScriptedChatClient", "StepStatus", "fingerprint", "identity_hash", "iter_episodes", "load_identity",
        "parse_choice", "parse_identity", "policy_drift", "read_episodes",
    },
}  # fmt: skip


@pytest.mark.parametrize("package", sorted(PUBLIC))
def test_all_matches_the_public_api_and_resolves(package: str) -> None:
    module = importlib.import_module(package)
    assert set(module.__all__) == PUBLIC[package]
    assert len(module.__all__) == len(set(module.__all__))
    for name in module.__all__:
        assert getattr(module, name) is not None


def test_unknown_name_is_an_attribute_error() -> None:
    registry = importlib.import_module("capevo.registry")
    with pytest.raises(AttributeError, match="has no attribute 'Nope'"):
        _ = registry.Nope
