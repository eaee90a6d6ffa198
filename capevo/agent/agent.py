"""The persistent agent A = (π_A, M_id, M_ep): fixed for the robot's life, remembering every episode.

The closed loop improves ECMs, never the agent. :class:`PersistentAgent` makes that
checkable: it hashes π_A (class and parameters) with M_id at start-up, re-hashes at the
start of every iteration, and tracks the policy's parameter drift Δπ, which must stay 0.0.

Invariants:
1. ``identity_hash`` is computed once, at construction, and never changes.
2. ``check_identity`` raises :class:`IdentityViolation` whenever π_A's class or parameters,
   M_id, or the identity memory π_A plans with differ from start-up; the message says which
   of these changed and names the changed fields.
3. ``begin_iteration`` checks identity before recording Δπ, so a drift is never recorded
   for a changed agent.
4. The agent itself is a :class:`~capevo.runtime.policy.DecisionPolicy`: ``decide`` is π_A's.
"""

from __future__ import annotations

from capevo.agent.base import AgentPolicy
from capevo.agent.drift import DEFAULT_EPS, PolicyDriftTracker
from capevo.agent.episodic import EpisodeRecord, EpisodicMemory
from capevo.agent.fingerprint import Fingerprint, changed_paths, fingerprint
from capevo.agent.identity import IdentityMemory
from capevo.errors import IdentityViolation, Invalid
from capevo.runtime.policy import Decision, DecisionContext

_MAX_PATHS = 8


class PersistentAgent:
    """A = (π_A, M_id, M_ep).

    Args:
        policy: π_A; must plan with an identity memory equal to ``identity``.
        identity: M_id.
        episodic_memory: M_ep, open for appending.
        drift_eps: Denominator floor of Δπ.

    Raises:
        Invalid: ``policy`` lacks the :class:`~capevo.agent.base.AgentPolicy` surface, its
            parameters cannot be hashed, or it plans with a different identity memory.
    """

    __slots__ = ("_drift", "_identity", "_memory", "_policy", "_start")

    def __init__(
        self,
        policy: AgentPolicy,
        identity: IdentityMemory,
        episodic_memory: EpisodicMemory,
        *,
        drift_eps: float = DEFAULT_EPS,
    ) -> None:
        if not isinstance(policy, AgentPolicy):
            raise Invalid(
                f"policy: {type(policy).__name__} lacks identity, parameters, parameters_vector() or decide()",
                details={"field": "policy"},
            )
        if not isinstance(identity, IdentityMemory):
            raise Invalid(
                f"identity: expected an IdentityMemory, got {type(identity).__name__}", details={"field": "identity"}
            )
        if not isinstance(episodic_memory, EpisodicMemory):
            raise Invalid(
                f"episodic_memory: expected an EpisodicMemory, got {type(episodic_memory).__name__}",
                details={"field": "episodic_memory"},
            )
        try:
            start = fingerprint(policy, identity)
        except (TypeError, ValueError) as exc:
            raise Invalid(f"policy: parameters cannot be hashed: {exc}", details={"field": "policy"}) from None
        planned = policy.identity.to_dict()
        if planned != start.identity:
            paths = changed_paths(start.identity, planned)
            raise Invalid(
                f"policy: plans with an identity memory that differs from the agent's at {_list(paths)}",
                details={"field": "policy", "paths": paths},
            )
        self._policy = policy
        self._identity = identity
        self._memory = episodic_memory
        self._start: Fingerprint = start
        self._drift = PolicyDriftTracker(eps=drift_eps)

    @property
    def policy(self) -> AgentPolicy:
        return self._policy

    @property
    def identity(self) -> IdentityMemory:
        return self._identity

    @property
    def episodic_memory(self) -> EpisodicMemory:
        return self._memory

    @property
    def identity_hash(self) -> str:
        """sha256 hex digest of π_A and M_id at start-up."""
        return self._start.hash

    def check_identity(self) -> str:
        """Recompute the identity hash and compare it with start-up.

        Returns:
            The hash (equal to :attr:`identity_hash`).

        Raises:
            IdentityViolation: naming what changed (policy parameters, identity memory, or the
                identity memory the policy plans with) and the changed fields.
        """
        try:
            now = fingerprint(self._policy, self._identity)
        except (TypeError, ValueError) as exc:
            raise IdentityViolation(
                f"policy parameters changed since start-up and can no longer be hashed: {exc}",
                details={"changed": ["policy parameters"], "expected_hash": self._start.hash},
            ) from None
        problems: list[str] = []
        changed: list[str] = []
        paths: dict[str, list[str]] = {}
        policy_paths = changed_paths(self._start.policy, now.policy)
        if policy_paths:
            changed.append("policy parameters")
            paths["policy"] = policy_paths
            problems.append(
                f"policy parameters changed ({self._describe(self._start.policy, now.policy, policy_paths)})"
            )
        identity_paths = changed_paths(self._start.identity, now.identity)
        if identity_paths:
            changed.append("identity memory")
            paths["identity"] = identity_paths
            problems.append(f"identity memory changed at {_list(identity_paths)}")
        planned = self._policy.identity.to_dict()
        planned_paths = changed_paths(self._start.identity, planned)
        if planned_paths:
            changed.append("policy identity memory")
            paths["policy_identity"] = planned_paths
            problems.append(f"the identity memory the policy plans with changed at {_list(planned_paths)}")
        if problems:
            raise IdentityViolation(
                f"agent identity changed since start-up: {'; '.join(problems)}",
                details={
                    "changed": changed,
                    "paths": paths,
                    "expected_hash": self._start.hash,
                    "actual_hash": now.hash,
                },
            )
        return now.hash

    @staticmethod
    def _describe(before: dict[str, object], after: dict[str, object], paths: list[str]) -> str:
        parts = []
        for path in paths[:_MAX_PATHS]:
            parts.append(f"{path}: {_lookup(before, path)!r} -> {_lookup(after, path)!r}")
        more = f", and {len(paths) - _MAX_PATHS} more" if len(paths) > _MAX_PATHS else ""
        return ", ".join(parts) + more

    def begin_iteration(self, iteration: int) -> float:
        """Start closed-loop iteration ``iteration``: check identity, then record θ for Δπ.

        Returns:
            Δπ between the first iteration and this one (0.0 for this agent).

        Raises:
            IdentityViolation: as :meth:`check_identity`.
            Invalid: ``iteration`` lower than the previous one.
        """
        self.check_identity()
        return self._drift.observe(iteration, self._policy.parameters_vector())

    def policy_drift(self) -> float:
        """Δπ between the first and the last iteration begun (0.0 before any)."""
        return self._drift.drift()

    def decide(self, context: DecisionContext) -> Decision:
        """π_A's decision (see :class:`~capevo.runtime.policy.DecisionPolicy`)."""
        return self._policy.decide(context)

    def remember(self, record: EpisodeRecord) -> None:
        """Append one episode to M_ep (durable when this returns)."""
        self._memory.append(record)


def _list(paths: list[str]) -> str:
    shown = ", ".join(paths[:_MAX_PATHS])
    return shown + (f" and {len(paths) - _MAX_PATHS} more" if len(paths) > _MAX_PATHS else "")


def _lookup(doc: object, path: str) -> object:
    """The value at a dotted path of :func:`changed_paths` (``<absent>`` if it is not there)."""
    cur = doc
    for part in path.replace("[", ".[").split("."):
        if not part:
            continue
        try:
            cur = cur[int(part[1:-1])] if part.startswith("[") else cur[part]  # type: ignore[index]
        except (KeyError, IndexError, TypeError, ValueError):
            return "<absent>"
    return cur
