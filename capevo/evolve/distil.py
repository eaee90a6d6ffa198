"""The hybrid path as one change: a task's code set cloned into neural ECMs and gated together.

Issue 19 asks the framework to carry a skill from hand-written to learned: "a code ECM's
successful traces become BC data for a neural version of the same ECM; the gate decides between
them on the same seeds". :func:`distil_set` does that for every ECM of a task at once:

1. every ECM of the task's decomposition gets one behaviour-cloned neural candidate from the
   successful episodes of ``traces`` (the ``il`` learner, :class:`~capevo.learner.worker.LearnerWorker`
   with ``once``; on a task with a scripted reference its rollouts are added, and DAgger's rounds
   as the preset sets them). An ECM with too few demonstration rows (its step never ran to a
   hand-over in a successful episode) is skipped and keeps its active version;
2. the gate judges the active set against the set with every candidate, **one decision for all**
   (:meth:`capevo.runtime.gate.Gate.run` with ``with_candidates``, as capevo evolve gates a
   chain), on one batch of the seed plan's gate seeds.

Why one decision: on T6 the clones gated one at a time were each rejected, though together they
won 82 to 65 of 90 held-out episodes (``results/evolution/T6-distil``); gated as one change, the
same kind of set was promoted and reached 55/60 (``results/evolution/T6-hybrid``). A skill's
clone may only pay off beside its neighbours' clones, whose hand-overs it was trained on.

What is hand-written: nothing here beyond the learners' and the gate's own settings (the preset);
the demonstrations are the set's own successful steps.

Invariants:
1. Every candidate is decided by the same gate decision: after :func:`distil_set` returns a
   decision, either all of them are active or none is.
2. An ECM without enough demonstration rows is skipped, never an error, unless every ECM is
   (then :class:`~capevo.errors.Invalid`, before any episode of the gate).
3. Nothing is resumed: a process stopped before the decision leaves the clones it published as
   candidates (the gate never saw them), and running again clones anew. A decision cut short
   while promoting keeps its evidence on the members; :meth:`~capevo.runtime.gate.Gate.settle`
   finishes it (capevo evolve calls it when it resumes a chain; this function does not).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.errors import Invalid
from capevo.learner.worker import LearnerConfig, LearnerWorker
from capevo.records import EcmVersion
from capevo.registry.api import Registry
from capevo.runtime.gate import Gate, GateConfig, GateDecision, SeedPlan
from capevo.runtime.tasks import Perturbations, task_spec

Emit = Callable[[dict[str, Any]], None]


@dataclass(frozen=True, slots=True)
class Skipped:
    """An ECM that got no candidate, and why (the learner's own words)."""

    ecm: str
    reason: str


@dataclass(frozen=True, slots=True)
class DistilResult:
    """The candidates cloned, the ECMs skipped, and the one gate decision on all candidates."""

    task: str
    candidates: tuple[EcmVersion, ...]
    skipped: tuple[Skipped, ...]
    decision: GateDecision

    def to_dict(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "candidates": {c.name: c.version for c in self.candidates},
            "skipped": {s.ecm: s.reason for s in self.skipped},
            "promoted": self.decision.promoted,
            "decision": self.decision.to_dict(),
        }


def _demos_missing(exc: Invalid) -> bool:
    """Whether ``exc`` is the ``il`` learner saying it found too few demonstration rows."""
    return (exc.details or {}).get("field") == "demos"


def clone_candidates(
    registry: Registry,
    *,
    task: str,
    traces: Sequence[str | Path],
    preset: str = "cpu-small",
    phi: str = "task",
    seed: int = 0,
    seed_plan: int = 0,
    perturbations: Perturbations | None = None,
    torch_threads: int | None = 1,
    emit: Emit | None = None,
) -> tuple[tuple[EcmVersion, ...], tuple[Skipped, ...]]:
    """Publish one ``il`` candidate per ECM of ``task`` that has demonstration rows in ``traces``.

    Returns:
        The published candidates (in decomposition order) and the ECMs skipped.

    Raises:
        CapevoError: a learner failed for another reason than too few demonstrations.
    """
    spec = task_spec(task)
    published: list[EcmVersion] = []
    skipped: list[Skipped] = []
    never = threading.Event()
    for ecm in spec.ecm_names:
        config = LearnerConfig(
            ecm=ecm,
            modality="il",
            task=spec.name,
            preset=preset,
            traces=tuple(Path(t) for t in traces),
            once=True,
            phi=phi,
            seed=seed,
            seed_plan=seed_plan,
            perturbations=perturbations if perturbations is not None else Perturbations(),
            torch_threads=torch_threads,
        )
        worker = LearnerWorker(config, lambda: registry, emit=emit)
        try:
            record = worker.update(registry, never, reason="distil")
        except Invalid as exc:
            if not _demos_missing(exc):
                raise
            skipped.append(Skipped(ecm=ecm, reason=exc.message))
            if emit is not None:
                emit({"event": "skipped", "ecm": ecm, "reason": exc.message})
            continue
        if record is not None:
            published.append(record)
    return tuple(published), tuple(skipped)


def distil_set(
    registry: Registry,
    evaluator: Any,
    *,
    task: str,
    traces: Sequence[str | Path],
    gate_config: GateConfig,
    gate_episodes: int,
    round_: int,
    preset: str = "cpu-small",
    phi: str = "task",
    seed: int = 0,
    seed_plan: int = 0,
    actor: str = "distil",
    torch_threads: int | None = 1,
    emit: Emit | None = None,
) -> DistilResult:
    """Clone every ECM of ``task`` from ``traces`` and gate the clones as one change.

    Args:
        registry: Where the candidates are published and the decision recorded.
        evaluator: Runs the gate's episodes (in this process or on runtime workers).
        task: Task id or name.
        traces: Trace files or directories of the current set's episodes (its successful ones
            are the demonstrations).
        gate_config: The gate's thresholds and second look.
        gate_episodes: Paired seeds of the gate's first look.
        round_: Which batch of ``seed_plan``'s gate seeds to use; pick one no earlier decision of
            the run used (capevo evolve uses batch ``i`` in iteration ``i``).
        preset: The learners' budget.
        phi: The envelope the learners train under (the gate's episodes run under the
            evaluator's).
        seed: Seeds the learners.
        seed_plan: The run's seed plan (``capevo evolve --seed``).
        actor: Recorded as the gate's actor in the registry.
        torch_threads: CPU threads for torch while cloning.
        emit: Receives the learners' events and ``skipped`` events.

    Raises:
        Invalid: no ECM had demonstration rows (nothing to gate), or bad gate seeds.
        CapevoError: a learner or the gate failed (candidates already published stay candidates).
    """
    spec = task_spec(task)
    candidates, skipped = clone_candidates(
        registry,
        task=spec.name,
        traces=traces,
        preset=preset,
        phi=phi,
        seed=seed,
        seed_plan=seed_plan,
        torch_threads=torch_threads,
        emit=emit,
    )
    if not candidates:
        raise Invalid(
            f"nothing to distil: no ECM of {spec.name} has demonstration rows in the traces given "
            "(they need successful episodes of the set)",
            details={"field": "traces"},
        )
    plan = SeedPlan(base_seed=seed_plan)
    seeds = plan.gate(gate_episodes, round=round_)
    more = plan.gate_extension(gate_config.extend_n, round=round_) if gate_config.extend_n else []
    first, *others = candidates
    gate = Gate(registry, evaluator, gate_config, actor=actor, seed_plan=plan)
    decision = gate.run(
        first.name,
        first.version,
        task=spec.name,
        seeds=seeds,
        extension_seeds=more,
        with_candidates={c.name: c.version for c in others},
    )
    return DistilResult(task=spec.name, candidates=candidates, skipped=skipped, decision=decision)
