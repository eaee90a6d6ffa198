"""Loading and invoking ECMs of every kind, safely.

* :mod:`.loader` — registry version + artifact bytes -> :class:`LoadedEcm` (by kind).
* :mod:`.code` — the code-skill contract, :class:`CodeSkill` (in-process), θ tools.
* :mod:`.neural` — SB3 model zips loaded without unpickling, deterministic on CPU.
* :mod:`.prompt` — prompt text.
* :mod:`.trust` — which origins run in-process; the rest go to :mod:`capevo.runtime.sandbox`.
* :mod:`.invoker` — step-by-step execution with timeouts, budgets, outcome records, recovery.
* :mod:`.recovery` — retry / fallback / safe-abort strategies.
* :mod:`.compose` — plan type checks (O(c_i) against I(c_j)).
* :mod:`.marshal` — observation dict -> ECM inputs per the interface spec.
"""

from __future__ import annotations

from capevo.runtime.ecm.base import LoadedEcm, Runner
from capevo.runtime.ecm.code import CodeSkill, read_params, with_params
from capevo.runtime.ecm.compose import check_composition, check_pair
from capevo.runtime.ecm.invoker import EcmInvoker
from capevo.runtime.ecm.loader import LoadOptions, load_code, load_ecm, load_neural, make_loader, register_loader
from capevo.runtime.ecm.marshal import clip_to_bounds, flatten_inputs, marshal_inputs, output_size
from capevo.runtime.ecm.neural import NeuralPolicy, load_sb3_policy
from capevo.runtime.ecm.outcome import FAILURES, Outcome, Status, StepResult
from capevo.runtime.ecm.prompt import load_prompt
from capevo.runtime.ecm.recovery import (
    RECOVERIES,
    Fallback,
    RecoveryStrategy,
    Resolution,
    Retry,
    SafeAbort,
    make_recovery,
    register_recovery,
)
from capevo.runtime.ecm.trust import SANDBOX_EVERYTHING, TrustPolicy

__all__ = [
    "FAILURES",
    "RECOVERIES",
    "SANDBOX_EVERYTHING",
    "CodeSkill",
    "EcmInvoker",
    "Fallback",
    "LoadOptions",
    "LoadedEcm",
    "NeuralPolicy",
    "Outcome",
    "RecoveryStrategy",
    "Resolution",
    "Retry",
    "Runner",
    "SafeAbort",
    "Status",
    "StepResult",
    "TrustPolicy",
    "check_composition",
    "check_pair",
    "clip_to_bounds",
    "flatten_inputs",
    "load_code",
    "load_ecm",
    "load_neural",
    "load_prompt",
    "load_sb3_policy",
    "make_loader",
    "make_recovery",
    "marshal_inputs",
    "output_size",
    "read_params",
    "register_loader",
    "register_recovery",
    "with_params",
]
