"""The runtime layer R: tasks, governance, ECM execution, traces, gating and the worker.

Heavy parts (robosuite, torch) load only when a name that needs them is first used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from capevo._lazy import lazy_getattr

if TYPE_CHECKING:
    from capevo.runtime.evaluation import EpisodeOutcome, Evaluator
    from capevo.runtime.policy import Decision, DecisionContext, DecisionPolicy, StepEnd
    from capevo.runtime.safety_monitor import SafetyLimits, SafetyMonitor, SafetyVerdict
    from capevo.runtime.state import ActionLayout, ArmActionLayout, ArmState, RobotState

_HOMES = {
    "EpisodeOutcome": "capevo.runtime.evaluation",
    "Evaluator": "capevo.runtime.evaluation",
    "Decision": "capevo.runtime.policy",
    "DecisionContext": "capevo.runtime.policy",
    "DecisionPolicy": "capevo.runtime.policy",
    "StepEnd": "capevo.runtime.policy",
    "ActionLayout": "capevo.runtime.state",
    "ArmActionLayout": "capevo.runtime.state",
    "ArmState": "capevo.runtime.state",
    "RobotState": "capevo.runtime.state",
    "SafetyLimits": "capevo.runtime.safety_monitor",
    "SafetyMonitor": "capevo.runtime.safety_monitor",
    "SafetyVerdict": "capevo.runtime.safety_monitor",
}
__all__ = [
    "ActionLayout",
    "ArmActionLayout",
    "ArmState",
    "Decision",
    "DecisionContext",
    "DecisionPolicy",
    "EpisodeOutcome",
    "Evaluator",
    "RobotState",
    "SafetyLimits",
    "SafetyMonitor",
    "SafetyVerdict",
    "StepEnd",
]
__getattr__ = lazy_getattr(__name__, _HOMES)
