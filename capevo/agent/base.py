"""What the persistent agent needs of its decision policy π_A, beyond deciding.

The runtime only calls :meth:`~capevo.runtime.policy.DecisionPolicy.decide`. The agent also
hashes the policy (identity invariance) and measures its parameter drift (Δπ), so a policy it
holds exposes its parameters as a record and as a vector, and the identity memory it plans with.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from capevo.runtime.policy import Decision, DecisionContext

if TYPE_CHECKING:
    from capevo.agent.identity import IdentityMemory


class ParameterRecord(Protocol):
    """A frozen record of a policy's parameters."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form; what the identity hash covers."""
        ...


@runtime_checkable
class AgentPolicy(Protocol):
    """π_A as the persistent agent holds it: a decision policy with inspectable parameters."""

    @property
    def identity(self) -> IdentityMemory:
        """The identity memory whose decompositions the policy plans with."""
        ...

    @property
    def parameters(self) -> ParameterRecord:
        """The policy's own parameters (never ECM parameters)."""
        ...

    def parameters_vector(self) -> tuple[float, ...]:
        """The numeric parameters, in a fixed order, for the drift metric Δπ."""
        ...

    def decide(self, context: DecisionContext) -> Decision:
        """The next ECM to run, or ``Decision(ecm=None)`` to end the episode."""
        ...
