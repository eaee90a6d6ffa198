"""What learners read from recent experience: how each episode ended, from its MCAP trace.

The episode loop traces every plan decision (``/plan``), every ECM call (``/ecm/invocation``)
and a summary per episode. From those this module derives, per episode, the ECMs started in
order, the one running when the episode ended, why it ended, and the calls that failed; then
which ECM of a task's decomposition to improve next (:func:`pick_ecm_to_update`), how far
episodes got (:func:`progress`), and a plain-text failure summary for an LLM prompt.

Invariants:
1. :func:`read_episode_ends` returns one :class:`EpisodeEnd` per ``/episode/summary`` record,
   in file order; an episode without a summary (crashed writer) is skipped.
2. :func:`pick_ecm_to_update` returns None exactly when no failed episode has a readable
   trace; otherwise the ECM of the decomposition with the largest blame, ties going to the
   earliest step (fix upstream first). Each failed episode spreads a blame of 1 equally over
   its failed activations: those that did not hand over to a later step (re-planned back,
   or still running when the episode ended).
3. :func:`progress` is 1.0 for a successful episode and ``k / n`` otherwise, ``k`` the index
   of the furthest decomposition step the episode started (0 when none).
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from capevo.errors import CapevoError
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.traces import EcmInvocation, EpisodeSummary, PlanStep, TraceReader
from capevo.runtime.traces import Outcome as CallOutcome

MAX_ERRORS_KEPT = 5
"""Error texts kept per episode (the first ones)."""
_TOPICS = (PlanStep.TOPIC, EcmInvocation.TOPIC, EpisodeSummary.TOPIC)


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeEnd:
    """How one traced episode went, as far as learners care."""

    seed: int | None
    success: bool
    plan: tuple[str, ...]
    """ECMs started, in order (re-plans repeat names)."""
    last_ecm: str | None
    """The ECM started last: the one that was running or had just given up when it ended."""
    end_reason: str
    """The policy's reason when it ended the episode; ``success`` or ``horizon`` otherwise."""
    reward: float
    steps: int
    budget_exhausted: tuple[str, ...] = ()
    """ECMs whose step budget ran out, once per activation."""
    errors: tuple[str, ...] = ()
    """``ecm: outcome: error`` of the first failed calls."""
    last_inputs: Mapping[str, tuple[float, ...]] = field(default_factory=dict)
    """Per ECM, the flat input state of its last call (a real observation for smoke runs)."""
    trace_path: str | None = None


def read_episode_ends(path: str | os.PathLike[str]) -> list[EpisodeEnd]:
    """Every finished episode of one trace file.

    Raises:
        NotFound, Invalid, Corrupt: the file is missing, not an MCAP file, or undecodable.
    """
    plans: dict[int, list[str]] = {}
    ends: dict[int, str] = {}
    budget: dict[int, list[str]] = {}
    errors: dict[int, list[str]] = {}
    inputs: dict[int, dict[str, tuple[float, ...]]] = {}
    out: list[EpisodeEnd] = []
    reader = TraceReader(path, allow_incomplete=True)
    for rec in reader.records(_TOPICS):
        ep = rec.episode
        if isinstance(rec, PlanStep):
            if rec.ecm:
                plans.setdefault(ep, []).append(rec.ecm)
            else:
                ends[ep] = rec.reason
        elif isinstance(rec, EcmInvocation):
            inputs.setdefault(ep, {})[rec.ecm] = rec.input_state
            if rec.outcome is CallOutcome.BUDGET_EXHAUSTED:
                budget.setdefault(ep, []).append(rec.ecm)
            elif rec.outcome is not CallOutcome.OK:
                kept = errors.setdefault(ep, [])
                if len(kept) < MAX_ERRORS_KEPT:
                    kept.append(f"{rec.ecm}: {rec.outcome.value}: {rec.error or ''}".strip())
        elif isinstance(rec, EpisodeSummary):
            plan = tuple(plans.get(ep, ()))
            reason = ends.get(ep) or ("success" if rec.success else "horizon")
            out.append(
                EpisodeEnd(
                    seed=rec.seed,
                    success=rec.success,
                    plan=plan,
                    last_ecm=plan[-1] if plan else None,
                    end_reason=reason,
                    reward=rec.total_reward,
                    steps=rec.steps,
                    budget_exhausted=tuple(budget.get(ep, ())),
                    errors=tuple(errors.get(ep, ())),
                    last_inputs=dict(inputs.get(ep, {})),
                    trace_path=str(Path(path)),
                )
            )
    return out


def episode_ends(outcomes: Sequence[EpisodeOutcome]) -> list[EpisodeEnd]:
    """:class:`EpisodeEnd` for each outcome that has a trace, matched by trace file and seed.

    Outcomes without ``trace_path`` (or whose episode the file lacks) are skipped.
    """
    by_path: dict[str, list[EpisodeEnd]] = {}
    out: list[EpisodeEnd] = []
    used: Counter[tuple[str, int | None]] = Counter()
    for o in outcomes:
        if not o.trace_path:
            continue
        if o.trace_path not in by_path:
            try:
                by_path[o.trace_path] = read_episode_ends(o.trace_path)
            except CapevoError:  # a missing or damaged trace only loses that evidence
                by_path[o.trace_path] = []
        # the same seed may appear twice in one file: take them in order
        key = (o.trace_path, o.seed)
        matches = [e for e in by_path[o.trace_path] if e.seed == o.seed]
        if used[key] < len(matches):
            out.append(matches[used[key]])
            used[key] += 1
    return out


def trace_paths(outcomes: Iterable[EpisodeOutcome]) -> tuple[str, ...]:
    """The distinct trace files of ``outcomes``, in first-seen order."""
    return tuple(dict.fromkeys(o.trace_path for o in outcomes if o.trace_path))


def _ends(evidence: Sequence[EpisodeOutcome] | Sequence[EpisodeEnd]) -> list[EpisodeEnd]:
    if all(isinstance(e, EpisodeEnd) for e in evidence):
        return list(evidence)  # type: ignore[arg-type]
    return episode_ends(evidence)  # type: ignore[arg-type]


def failed_activations(end: EpisodeEnd, decomposition: Sequence[str]) -> list[str]:
    """The activations of a failed episode that did not hand over to a later step, in order.

    An activation of a decomposition step failed when the next ECM started is the same step
    or an earlier one (a re-plan: the step ran out of budget, gave up, or undid an earlier
    step's work, e.g. dropped the object), or when it was the last one of a failed episode.
    A jump forward (later steps already done) is a hand-over. ECMs outside the decomposition
    are skipped (not judged, and not a hand-over). A failed episode that started no step
    blames the first step.
    """
    steps = list(decomposition)
    if end.success or not steps:
        return []
    plan = [ecm for ecm in end.plan if ecm in steps]
    out = []
    for i, ecm in enumerate(plan):
        if i + 1 == len(plan) or steps.index(plan[i + 1]) <= steps.index(ecm):
            out.append(ecm)
    return out or [steps[0]]


def failure_weights(
    evidence: Sequence[EpisodeOutcome] | Sequence[EpisodeEnd], decomposition: Sequence[str]
) -> dict[str, float]:
    """Blame per ECM of ``decomposition`` over the failed episodes (see invariant 2).

    Each failed episode carries weight 1, shared equally by its failed activations
    (:func:`failed_activations`), so one episode's retries do not outweigh other episodes.
    """
    weights: dict[str, float] = {}
    for e in _ends(evidence):
        failed = failed_activations(e, decomposition)
        for ecm in failed:
            weights[ecm] = weights.get(ecm, 0.0) + 1.0 / len(failed)
    return {k: round(v, 6) for k, v in weights.items()}


def pick_ecm_to_update(
    evidence: Sequence[EpisodeOutcome] | Sequence[EpisodeEnd], decomposition: Sequence[str]
) -> str | None:
    """The ECM of ``decomposition`` that failed episodes blame most (None: no failures).

    Args:
        evidence: Recent outcomes (their traces are read) or already-read episode ends.
        decomposition: The task's ECM names in plan order.

    Returns:
        The ECM to improve next, ties going to the earliest step; None when no failed episode
        has a readable trace.
    """
    weights = failure_weights(evidence, decomposition)
    if not weights:
        return None
    order = list(decomposition)
    return max(weights, key=lambda name: (weights[name], -order.index(name)))


def progress(end: EpisodeEnd, decomposition: Sequence[str]) -> float:
    """How far one episode got through the decomposition, in [0, 1] (see invariant 3)."""
    if end.success:
        return 1.0
    steps = list(decomposition)
    if not steps:
        return 0.0
    started = [steps.index(p) for p in end.plan if p in steps]
    return (max(started) if started else 0) / len(steps)


def failure_summary(
    evidence: Sequence[EpisodeOutcome] | Sequence[EpisodeEnd], decomposition: Sequence[str], ecm: str
) -> str:
    """A short plain-text account of recent episodes, focused on ``ecm`` (for an LLM prompt)."""
    ends = _ends(evidence)
    if not ends:
        return "No traced episodes are available."
    failed = [e for e in ends if not e.success]
    lines = [f"{len(ends) - len(failed)} of {len(ends)} recent episodes succeeded."]
    weights = failure_weights(ends, decomposition)
    if weights:
        ranked = sorted(weights.items(), key=lambda kv: -kv[1])
        where = ", ".join(f"{name} ({w:.3g})" for name, w in ranked)
        lines.append(f"Steps that failed to hand over (blame, 1 per failed episode): {where}.")
    reasons = Counter(e.end_reason for e in failed)
    if reasons:
        lines.append("Why they ended: " + "; ".join(f"{r} ({n})" for r, n in reasons.most_common(4)) + ".")
    starts = sum(e.plan.count(ecm) for e in ends)
    exhausted = sum(e.budget_exhausted.count(ecm) for e in ends)
    lines.append(f"{ecm} was started {starts} times and ran out of its step budget {exhausted} times.")
    errors = [err for e in ends for err in e.errors if err.startswith(ecm + ":")]
    if errors:
        lines.append("Errors of its calls (first few): " + " | ".join(errors[:MAX_ERRORS_KEPT]))
    return "\n".join(lines)
