"""The persistent agent A = (π_A, M_id, M_ep).

- π_A: :class:`DecompositionPolicy` (default, no network) or :class:`LlmPolicy` (optional,
  asks an OpenAI-compatible chat endpoint, falls back to the decomposition policy).
- M_id: :class:`IdentityMemory`, goals, beliefs and task decompositions from YAML.
- M_ep: :class:`EpisodicMemory`, one fsynced JSON line per episode.
- :class:`PersistentAgent` ties them together, checks the identity hash every iteration and
  tracks the policy drift Δπ (:class:`PolicyDriftTracker`).
"""

from __future__ import annotations

from capevo.agent.agent import PersistentAgent
from capevo.agent.base import AgentPolicy, ParameterRecord
from capevo.agent.drift import PolicyDriftTracker, policy_drift
from capevo.agent.episodic import EpisodeRecord, EpisodicLog, EpisodicMemory, iter_episodes, read_episodes
from capevo.agent.fingerprint import Fingerprint, fingerprint, identity_hash
from capevo.agent.identity import Belief, Goal, IdentityMemory, load_identity, parse_identity
from capevo.agent.llm import (
    ChatClient,
    HttpChatClient,
    LlmParameters,
    LlmPolicy,
    LlmSettings,
    ScriptedChatClient,
    parse_choice,
)
from capevo.agent.policy import ALL_DONE, DecompositionPolicy, PlanStep, PolicyParameters, StepStatus

__all__ = [
    "ALL_DONE",
    "AgentPolicy",
    "Belief",
    "ChatClient",
    "DecompositionPolicy",
    "EpisodeRecord",
    "EpisodicLog",
    "EpisodicMemory",
    "Fingerprint",
    "Goal",
    "HttpChatClient",
    "IdentityMemory",
    "LlmParameters",
    "LlmPolicy",
    "LlmSettings",
    "ParameterRecord",
    "PersistentAgent",
    "PlanStep",
    "PolicyDriftTracker",
    "PolicyParameters",
    "ScriptedChatClient",
    "StepStatus",
    "fingerprint",
    "identity_hash",
    "iter_episodes",
    "load_identity",
    "parse_choice",
    "parse_identity",
    "policy_drift",
    "read_episodes",
]
