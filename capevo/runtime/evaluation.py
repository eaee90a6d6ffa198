"""Evaluation results, and the evaluator protocol gating runs candidates through.

An :class:`Evaluator` runs seeded episodes of a task with a given capability set. The
in-process runtime implements it directly; the runtime worker serves the same call over
Zenoh, so the gate does not care where episodes run. Pairing matters: the gate runs the
active and the candidate set on the same seeds, and the task guarantees that a seed fixes
the instance (initial scene and perturbation draws).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeOutcome:
    """One evaluated episode."""

    seed: int
    success: bool
    reward: float
    steps: int
    duration_s: float
    interventions: int
    unsafe_steps: int
    ecm_failures: int
    capability_set: Mapping[str, int]
    trace_path: str | None = None
    phi_hash: str | None = None
    """Hash of the envelope Φ the episode ran under (None: not recorded)."""
    intervened_steps: int | None = None
    """Steps at which governance changed (or, counting, would have changed) the action; one
    step can hold several of the ``interventions`` records (None: not recorded)."""
    strict_success: bool | None = None
    """The task's stricter check beside ``success`` (``TaskEnv.strict_success``; T6: the peg
    through the plate), latched over the episode; None for tasks without one."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "success": self.success,
            "reward": self.reward,
            "steps": self.steps,
            "duration_s": self.duration_s,
            "interventions": self.interventions,
            "unsafe_steps": self.unsafe_steps,
            "ecm_failures": self.ecm_failures,
            "capability_set": dict(self.capability_set),
            "trace_path": self.trace_path,
            "phi_hash": self.phi_hash,
            "intervened_steps": self.intervened_steps,
            "strict_success": self.strict_success,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EpisodeOutcome:
        return cls(
            seed=int(d["seed"]),
            success=bool(d["success"]),
            reward=float(d["reward"]),
            steps=int(d["steps"]),
            duration_s=float(d["duration_s"]),
            interventions=int(d["interventions"]),
            unsafe_steps=int(d["unsafe_steps"]),
            ecm_failures=int(d["ecm_failures"]),
            capability_set={str(k): int(v) for k, v in d["capability_set"].items()},
            trace_path=d.get("trace_path"),
            phi_hash=d.get("phi_hash"),
            intervened_steps=None if d.get("intervened_steps") is None else int(d["intervened_steps"]),
            strict_success=None if d.get("strict_success") is None else bool(d["strict_success"]),
        )


@runtime_checkable
class Evaluator(Protocol):
    """Runs seeded evaluation episodes of ``task`` with ECM versions ``versions``.

    ``versions`` maps ECM name to version; ECMs the task needs that are not named run at
    their active version.
    """

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]: ...
