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
   or still running when the episode ended; at the horizon, a step that spent more than its
   hog threshold (:func:`hog_threshold`) in one activation instead of the last one).
3. :func:`progress` is 1.0 for a successful episode and ``k / n`` otherwise, ``k`` the index
   of the furthest decomposition step the episode started (0 when none).
5. ``EpisodeEnd.ecm_unsafe`` attributes each step the independent safety monitor graded unsafe
   (``/safety/unsafe``) to the ECM whose call produced that step's action ("" when no call is
   traced for the step). Governance interventions are not unsafe steps: under the default
   envelope most are braking before a contact, which is the envelope working.
4. :func:`handover_rate` counts an episode when it succeeded or its plan started a step after
   the judged one; it is monotone in those episodes and in [0, 1].
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
from capevo.runtime.traces.records import UnsafeStep

MAX_ERRORS_KEPT = 5
"""Error texts kept per episode (the first ones)."""
HOG_SHARE = 0.5
"""An episode that ran out of time blames a step that spent more than this share of it..."""
HOG_FAIR_MULTIPLE = 2.0
"""...or more than this multiple of its even share (the episode's steps over the decomposition's
length), whichever is smaller. Written by hand, not tuned: in a long chain (T5's 15 steps over 900)
no step can spend half of the episode, yet one reach spending 200 steps (3x its share) is where
the time went (issue 19's T5 traces)."""
_TOPICS = (PlanStep.TOPIC, EcmInvocation.TOPIC, EpisodeSummary.TOPIC, UnsafeStep.TOPIC)


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
    ecm_steps: Mapping[str, int] = field(default_factory=dict)
    """Per ECM, how many calls (environment steps) it made in the episode."""
    ecm_unsafe: Mapping[str, int] = field(default_factory=dict)
    """Per ECM, steps it was running that the safety monitor graded unsafe."""


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
    calls: dict[int, Counter[str]] = {}
    step_ecm: dict[tuple[int, int], str] = {}
    stops: dict[int, list[int]] = {}
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
            calls.setdefault(ep, Counter())[rec.ecm] += 1
            step_ecm[(ep, rec.step)] = rec.ecm
            if rec.outcome is CallOutcome.BUDGET_EXHAUSTED:
                budget.setdefault(ep, []).append(rec.ecm)
            elif rec.outcome not in (CallOutcome.OK, CallOutcome.TERMINATED):
                kept = errors.setdefault(ep, [])
                if len(kept) < MAX_ERRORS_KEPT:
                    kept.append(f"{rec.ecm}: {rec.outcome.value}: {rec.error or ''}".strip())
        elif isinstance(rec, UnsafeStep):
            stops.setdefault(ep, []).append(rec.step)
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
                    ecm_steps=dict(calls.get(ep, {})),
                    ecm_unsafe=dict(Counter(step_ecm.get((ep, st), "") for st in stops.get(ep, ()))),
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


def hog_threshold(episode_steps: int, decomposition_length: int) -> float:
    """Steps above which one activation of a step is where a timed-out episode's time went.

    The smaller of :data:`HOG_SHARE` of the episode and :data:`HOG_FAIR_MULTIPLE` times an even
    split of it over the decomposition's steps (a decomposition of 0 or 1 steps: the share alone).
    """
    share = HOG_SHARE * episode_steps
    if decomposition_length <= 1:
        return share
    return min(share, HOG_FAIR_MULTIPLE * episode_steps / decomposition_length)


def failed_activations(end: EpisodeEnd, decomposition: Sequence[str]) -> list[str]:
    """The activations of a failed episode that did not hand over to a later step, in order.

    An activation of a decomposition step failed when the next ECM started is the same step
    or an earlier one (a re-plan: the step ran out of budget, gave up, or undid an earlier
    step's work, e.g. dropped the object), or when it was the last one of a failed episode.
    A jump forward (later steps already done) is a hand-over. ECMs outside the decomposition
    are skipped (not judged, and not a hand-over). A failed episode that started no step
    blames the first step.

    Out of time: when the episode ended at the horizon and the step that spent the most steps,
    started once, spent more than :func:`hog_threshold` of them, that step, not the one the
    clock happened to stop, takes the last activation's blame (a slow reach leaves the lift no
    time).
    """
    steps = list(decomposition)
    if end.success or not steps:
        return []
    plan = [ecm for ecm in end.plan if ecm in steps]
    out = []
    for i, ecm in enumerate(plan):
        if i + 1 == len(plan) or steps.index(plan[i + 1]) <= steps.index(ecm):
            out.append(ecm)
    spent = {k: v for k, v in end.ecm_steps.items() if k in steps}
    if out and end.end_reason == "horizon" and spent and end.steps > 0:
        hog = max(spent, key=lambda k: (spent[k], -steps.index(k)))
        # one activation spent it: a step re-planned back to many times is slow because a
        # later step keeps failing, which the plan rule already blames
        if spent[hog] > hog_threshold(end.steps, len(steps)) and plan.count(hog) == 1:
            out[-1] = hog
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


def handover_rate(
    outcomes: Sequence[EpisodeOutcome],
    decomposition: Sequence[str],
    ecm: str,
    *,
    ends: Sequence[EpisodeEnd] | None = None,
) -> float:
    """Fraction of ``outcomes`` that succeeded or started a step after ``ecm`` (see invariant 4).

    Args:
        outcomes: Episodes (their traces are read unless ``ends`` is given).
        decomposition: The task's ECM names in plan order.
        ecm: The step judged; outside the decomposition only successes count.
        ends: Already-read episode ends of ``outcomes`` (matched by seed, in order).

    Returns:
        A rate in [0, 1]; 0.0 for no outcomes.
    """
    if not outcomes:
        return 0.0
    steps = list(decomposition)
    later = set(steps[steps.index(ecm) + 1 :]) if ecm in steps else set()
    by_seed: dict[int | None, list[EpisodeEnd]] = {}
    for e in ends if ends is not None else episode_ends(outcomes):
        by_seed.setdefault(e.seed, []).append(e)
    n = 0
    for o in outcomes:
        matches = by_seed.get(o.seed)
        end = matches.pop(0) if matches else None
        if o.success or (end is not None and later.intersection(end.plan)):
            n += 1
    return n / len(outcomes)


def unsafe_ecm(evidence: Sequence[EpisodeOutcome] | Sequence[EpisodeEnd], decomposition: Sequence[str]) -> str | None:
    """The ECM of ``decomposition`` with unsafe steps (the monitor's) in the most episodes, ties to the
    earliest step; None when no episode had one (see ``EpisodeEnd.ecm_unsafe``)."""
    counts: Counter[str] = Counter()
    for e in _ends(evidence):
        counts.update(name for name, n in e.ecm_unsafe.items() if n > 0 and name in decomposition)
    if not counts:
        return None
    order = list(decomposition)
    return max(counts, key=lambda name: (counts[name], -order.index(name)))


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
