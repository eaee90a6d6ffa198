"""π_A, the default decision policy: walk the task's decomposition, choose ECMs by their descriptors.

The decomposition (from M_id) fixes the order of the steps; the ECMs' descriptors, read from
the capability set the runtime loaded, say when each step applies and when it is done. The
policy is called only when an ECM ends (state-triggered, never on a clock) and is a pure
function of its parameters, M_id and the :class:`~capevo.runtime.policy.DecisionContext`.

A decision:

1. Status: for every step, ``done`` = its termination predicate holds over the signals and
   ``applicable`` = its applicability predicate holds (empty predicates hold).
2. Origin of the walk:
   - episode start: the first step;
   - the previous step TERMINATED: the step after it (a step's termination need not stay
     true once later steps run: ``reach`` ends with the gripper open, ``grasp`` closes it);
   - the previous step FAILED or ran out of budget: re-plan from the start of the
     decomposition, skipping only the prefix up to the last step *before the failed one*
     whose termination still holds (a lift that stalls with the object still grasped
     retries the lift; one whose object slipped goes back to grasp or reach; in a
     multi-object task the objects already placed stay placed).
3. Choice: the first step from the origin that is not done and is applicable. The walk may
   pass over a step that is not done only to a step whose applicability predicate holds
   (the world is already past the skipped step); it never passes over one to a step with no
   applicability predicate, because such a step starts a new stage of the plan (T5's
   ``bread.reach`` after the milk's steps) and would abandon the skipped one. If there is
   none but some step from the origin is not done, walk again from the re-plan origin (as
   after a failure of the origin step); if still none, end the episode, naming the first
   step that is not done and the applicability it waits for.
4. End: every step from the origin done -> ``Decision(ecm=None, reason="all steps done")``.
5. Attempt limit: the chosen ECM already started ``max_attempts_per_ecm`` times in this
   episode -> end the episode, naming the ECM and the limit.

Invariants:
1. ``decide`` names only ECMs of the task's decomposition, and only one whose termination
   predicate does not hold and whose applicability predicate holds.
2. An ECM of the decomposition missing from ``context.capabilities`` raises :class:`Invalid`
   naming every missing ECM, whatever the signals; so does a predicate over a signal the
   context lacks (naming the ECM and the predicate).
3. ``decide`` never returns an ECM whose attempts reached ``max_attempts_per_ecm``.
4. ``decide`` is deterministic and keeps no state between calls.
5. ``parameters_vector()`` is a fixed function of :class:`PolicyParameters`.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

from capevo.agent.identity import IdentityMemory
from capevo.errors import Invalid
from capevo.records import Descriptor, EcmVersion, Predicate
from capevo.registry.predicates import missing_signals, predicate_holds
from capevo.runtime.policy import Decision, DecisionContext, StepEnd

ALL_DONE = "all steps done"
MAX_ATTEMPTS_LIMIT = 1000


@dataclass(frozen=True, slots=True, kw_only=True)
class PolicyParameters:
    """θ of :class:`DecompositionPolicy`.

    Args:
        max_attempts_per_ecm: How many times one ECM may be started in one episode.

    Raises:
        Invalid: a parameter out of range.
    """

    max_attempts_per_ecm: int = 3

    def __post_init__(self) -> None:
        v = self.max_attempts_per_ecm
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_ATTEMPTS_LIMIT:
            raise Invalid(
                f"max_attempts_per_ecm: must be an integer from 1 to {MAX_ATTEMPTS_LIMIT}, got {v!r}",
                details={"field": "max_attempts_per_ecm"},
            )

    def to_dict(self) -> dict[str, Any]:
        return {"max_attempts_per_ecm": self.max_attempts_per_ecm}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PolicyParameters:
        return cls(max_attempts_per_ecm=d.get("max_attempts_per_ecm", 3))

    def vector(self) -> tuple[float, ...]:
        """The parameters as numbers, in field order."""
        return (float(self.max_attempts_per_ecm),)


@dataclass(frozen=True, slots=True, kw_only=True)
class PlanStep:
    """One step of a task's plan: the ECM, the version the runtime loaded, and its descriptor."""

    index: int
    ecm: str
    version: int
    descriptor: Descriptor


@dataclass(frozen=True, slots=True, kw_only=True)
class StepStatus:
    """One step evaluated against the current signals."""

    index: int
    ecm: str
    done: bool
    """Its termination predicate holds."""
    applicable: bool
    """Its applicability predicate holds."""
    unconditional: bool
    """Its applicability predicate is empty: it can always start."""
    attempts: int
    """How many times it was started in this episode."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DecompositionPolicy:
    """π_A: plans each task with its decomposition from M_id and picks ECMs by their descriptors.

    Args:
        identity: M_id, whose decompositions give each task's steps.
        parameters: θ, the policy's own parameters.
    """

    identity: IdentityMemory
    parameters: PolicyParameters = field(default_factory=PolicyParameters)

    def parameters_vector(self) -> tuple[float, ...]:
        """θ as a vector, for the drift metric Δπ."""
        return self.parameters.vector()

    def plan(
        self,
        task: str,
        capabilities: Mapping[str, EcmVersion],
        *,
        signals: Collection[str] | None = None,
    ) -> tuple[PlanStep, ...]:
        """The task's steps with the loaded version and descriptor of each ECM.

        Args:
            task: Task name (or built-in id such as ``"T1"``).
            capabilities: The active version of every loaded ECM, by name.
            signals: If given, the signal names the task exposes; every predicate must use only these.

        Returns:
            The steps in decomposition order.

        Raises:
            Invalid: unknown task, ECMs missing from ``capabilities``, or predicates over unknown signals.
        """
        names = self.identity.decomposition(task)
        missing = [n for n in names if n not in capabilities]
        if missing:
            raise Invalid(
                f"task {task!r} needs ECM(s) {', '.join(missing)}, which the runtime has not loaded "
                f"(loaded: {', '.join(sorted(capabilities)) or 'none'})",
                details={"field": "capabilities", "task": task, "missing": missing},
            )
        steps = tuple(
            PlanStep(index=i, ecm=n, version=capabilities[n].version, descriptor=capabilities[n].descriptor)
            for i, n in enumerate(names)
        )
        if signals is not None:
            available = frozenset(signals)
            for step in steps:
                for which in ("applicability", "termination"):
                    lacking = missing_signals(getattr(step.descriptor, which), available)
                    if lacking:
                        raise Invalid(
                            f"{step.ecm} v{step.version} {which} predicate uses signal(s) {', '.join(lacking)}, "
                            f"which task {task!r} does not expose",
                            details={"field": f"{step.ecm}.{which}", "ecm": step.ecm, "missing": lacking},
                        )
        return steps

    def assess(self, context: DecisionContext) -> tuple[StepStatus, ...]:
        """Every step of ``context.task`` evaluated against ``context.signals``.

        Raises:
            Invalid: as :meth:`plan`, or a predicate names a signal absent from ``context.signals``.
        """
        steps = self.plan(context.task, context.capabilities)
        return tuple(
            StepStatus(
                index=s.index,
                ecm=s.ecm,
                done=_holds(s, "termination", s.descriptor.termination, context.signals),
                applicable=_holds(s, "applicability", s.descriptor.applicability, context.signals),
                unconditional=not s.descriptor.applicability.all,
                attempts=int(context.attempts.get(s.ecm, 0)),
            )
            for s in steps
        )

    def candidates(self, context: DecisionContext) -> tuple[str, ...]:
        """Every step the walk could run now: not done, applicable, under the attempt limit.

        In decomposition order from the walk's origin (see the module docstring); the
        decomposition policy itself runs the first of them unless an earlier step is over
        its attempt limit.

        Raises:
            Invalid: as :meth:`assess`.
        """
        _, ready, _ = _walk(context, self.assess(context))
        limit = self.parameters.max_attempts_per_ecm
        return tuple(s.ecm for s in ready if s.attempts < limit)

    def decide(self, context: DecisionContext) -> Decision:
        """The next ECM of the task's decomposition, or the end of the episode.

        Returns:
            ``Decision(ecm=name, reason=...)`` to run ``name`` next; ``Decision(ecm=None,
            reason=...)`` when all steps are done (reason ``"all steps done"``), no step is
            applicable, or the chosen ECM reached its attempt limit.

        Raises:
            Invalid: as :meth:`assess`.
        """
        status = self.assess(context)
        origin, ready, how = _walk(context, status)
        if all(s.done for s in status[origin:]):
            return Decision(ecm=None, reason=ALL_DONE)
        if not ready:
            waiting = next(s for s in status[origin:] if not s.done)
            step = self.plan(context.task, context.capabilities)[waiting.index]
            needs = _describe(step.descriptor.applicability)
            return Decision(ecm=None, reason=f"no applicable step: {waiting.ecm} is not done and needs {needs}")
        chosen = ready[0]
        limit = self.parameters.max_attempts_per_ecm
        if chosen.attempts >= limit:
            return Decision(
                ecm=None, reason=f"{chosen.ecm} reached its attempt limit ({chosen.attempts} of {limit} starts)"
            )
        return Decision(ecm=chosen.ecm, reason=f"{how}: {chosen.ecm}")


def _walk(context: DecisionContext, status: tuple[StepStatus, ...]) -> tuple[int, list[StepStatus], str]:
    """(origin, steps ready to run in order, reason prefix); nothing is ready when all are done."""
    origin, how = _walk_origin(context, status)
    if all(s.done for s in status[origin:]):
        return origin, [], how
    ready = _ready(status, origin)
    if not ready:
        fallback = _replan_origin(status, origin)
        if fallback < origin:
            ready = _ready(status, fallback)
            how = f"nothing applicable from {status[origin].ecm}; re-planned from {status[fallback].ecm}"
    return origin, ready, how


def _holds(step: PlanStep, which: str, predicate: Predicate, signals: Mapping[str, float]) -> bool:
    try:
        return predicate_holds(predicate, signals)
    except Invalid as exc:
        raise Invalid(
            f"{step.ecm} v{step.version} {which} predicate: {exc.message}",
            details={**exc.details, "ecm": step.ecm, "predicate": which},
        ) from None


def _ready(status: tuple[StepStatus, ...], origin: int) -> list[StepStatus]:
    """Steps from ``origin`` that are not done and applicable, stopping at the first
    unconditional step that would pass over an inapplicable step not done (rule 3)."""
    ready: list[StepStatus] = []
    passed_over = False
    for s in status[origin:]:
        if s.done:
            continue
        if passed_over and s.unconditional:
            break
        if s.applicable:
            ready.append(s)
        else:
            passed_over = True
    return ready


def _replan_origin(status: tuple[StepStatus, ...], limit: int) -> int:
    """One past the last step before ``limit`` whose termination holds (0 if none)."""
    for s in reversed(status[:limit]):
        if s.done:
            return s.index + 1
    return 0


def _walk_origin(context: DecisionContext, status: tuple[StepStatus, ...]) -> tuple[int, str]:
    """Where the walk starts, and why (the prefix of the decision's reason)."""
    index = {s.ecm: s.index for s in status}
    prev = context.previous_ecm
    end = StepEnd(context.previous_end)
    if end is StepEnd.STARTED or prev is None:
        return 0, "start"
    if prev not in index:
        # An ECM outside the plan ran (a recovery or a planner's pick): judge from scratch.
        return 0, f"{prev} ({end.value}) is not in the plan; from the start"
    if end is StepEnd.TERMINATED:
        return index[prev] + 1, f"{prev} done; next"
    origin = _replan_origin(status, index[prev])
    return origin, f"{prev} {end.value}; re-planned"


def _describe(predicate: Predicate) -> str:
    conditions = " and ".join(f"{c.signal} {c.op} {c.value:g}" for c in predicate.all)
    if predicate.text and conditions:
        return f"{predicate.text!r} ({conditions})"
    return repr(predicate.text) if predicate.text else conditions or "nothing"
