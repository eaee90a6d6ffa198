"""The methods capevo is compared against (issue 20, paper §4.1 "Baselines"), one module per method, and the
record types every method of the experiment harness shares (:mod:`capevo.baselines.base`).

The methods and the governed whole-task env load robosuite (and torch when they run) only when
one of their names is first used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from capevo._lazy import lazy_getattr
from capevo.baselines.base import Budget, CellSpec, Emit, EpisodeResult, IterationRecord, Method

if TYPE_CHECKING:
    from capevo.baselines.am import AgentModification, AgentModificationBC
    from capevo.baselines.governed_env import GovernedTaskEnv, evaluate_policy
    from capevo.baselines.skimo import Skimo
    from capevo.baselines.spirl import Spirl

_HOMES = {
    "AgentModification": "capevo.baselines.am",
    "AgentModificationBC": "capevo.baselines.am",
    "GovernedTaskEnv": "capevo.baselines.governed_env",
    "evaluate_policy": "capevo.baselines.governed_env",
    "Skimo": "capevo.baselines.skimo",
    "Spirl": "capevo.baselines.spirl",
}
__all__ = [
    "AgentModification",
    "AgentModificationBC",
    "Budget",
    "CellSpec",
    "Emit",
    "EpisodeResult",
    "GovernedTaskEnv",
    "IterationRecord",
    "Method",
    "Skimo",
    "Spirl",
    "evaluate_policy",
]
__getattr__ = lazy_getattr(__name__, _HOMES)
