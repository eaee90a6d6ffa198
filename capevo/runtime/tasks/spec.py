"""What a task declares about itself: identity, action layout, observations, signals and its
default decomposition into ECM steps.

A :class:`TaskSpec` is a plain frozen value with no robosuite import behind it, so planners,
the registry and the CLI can read every task's decomposition without building a simulator.
Predicates are evaluated with :func:`capevo.registry.predicates.predicate_holds`.

Invariants:
1. Every :class:`Condition` in a task's decomposition names a signal the task declares.
2. Every ECM name in a decomposition is a valid registry slug
   (:func:`capevo.records.names.validate_name`) and starts with ``<task name>.``.
3. Every observation key an :class:`EcmStep` needs is one of the task's observation keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from capevo.errors import Invalid, check_choice
from capevo.records import COMPARISON_OPS, Condition, Descriptor, Predicate
from capevo.runtime.state import ActionLayout


@dataclass(frozen=True, slots=True, kw_only=True)
class SignalSpec:
    """One named scalar a task exposes through ``TaskEnv.signals()``."""

    name: str
    description: str
    units: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class EcmStep:
    """One step of a task's default decomposition: which ECM runs and when it is done."""

    ecm: str
    """ECM name (registry slug), e.g. ``pick.reach``."""
    description: str
    observation_keys: tuple[str, ...]
    """Raw observation keys the ECM needs (a subset of the task's observation keys)."""
    termination: Predicate
    """When the step is done, over the task's signals."""
    applicability: Predicate = field(default_factory=Predicate)
    """When the step may start; empty means always."""

    def descriptor(self) -> Descriptor:
        """The registry descriptor φ for this step's ECM.

        Returns:
            A :class:`Descriptor` carrying this step's description, applicability and termination.
        """
        return Descriptor(description=self.description, applicability=self.applicability, termination=self.termination)


@dataclass(frozen=True, slots=True, kw_only=True)
class TaskSpec:
    """Everything fixed about one task."""

    id: str
    """Short id, ``T1`` .. ``T6``."""
    name: str
    """Slug, e.g. ``pick``; also the prefix of every ECM name in :attr:`decomposition`."""
    env_name: str
    """The robosuite environment class the task is built on."""
    n_arms: int
    action_layout: ActionLayout
    observation_keys: tuple[str, ...]
    """Raw observation keys, in the order they are concatenated into the flat observation."""
    position_keys: tuple[str, ...]
    """The Cartesian position keys (metres) that receive observation noise."""
    signals: tuple[SignalSpec, ...]
    decomposition: tuple[EcmStep, ...]
    success_text: str
    reward_text: str
    default_horizon: int
    perturbation_text: str = ""
    """How this task interprets :class:`~capevo.runtime.tasks.perturbations.Perturbations`."""

    @property
    def signal_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.signals)

    @property
    def ecm_names(self) -> tuple[str, ...]:
        return tuple(s.ecm for s in self.decomposition)

    @property
    def handoff_signals(self) -> tuple[str, ...]:
        """The signals the decomposition's termination and applicability predicates read, in
        spec order. Signals are exact simulator state (``TaskEnv.signals``), not the noisy
        observations the skills see: the hand-offs between ECMs use this oracle, and a report
        comparing methods must name it (issue 19)."""
        used = {c.signal for step in self.decomposition for p in (step.termination, step.applicability) for c in p.all}
        return tuple(name for name in self.signal_names if name in used)

    @property
    def handoff_text(self) -> str:
        """One sentence naming the hand-off oracle, for reports."""
        names = ", ".join(self.handoff_signals) or "none"
        return (
            f"hand-offs between ECMs read exact simulator state, not the noisy observations the skills "
            f"see (signals: {names})"
        )


def cond(signal: str, op: str, value: float) -> Condition:
    """Shorthand for a :class:`Condition`; refuses unknown operators.

    Raises:
        Invalid: ``op`` is not one of :data:`capevo.records.COMPARISON_OPS`.
    """
    check_choice(op, COMPARISON_OPS, what="comparison", field="op")
    return Condition(signal=signal, op=op, value=float(value))


def pred(text: str, *conditions: Condition) -> Predicate:
    """Shorthand for a :class:`Predicate` over ``conditions``."""
    return Predicate(text=text, all=tuple(conditions))


def spec_problems(spec: TaskSpec) -> list[str]:
    """Violations of invariants 1-3 in ``spec``; empty when the spec is consistent.

    Returns:
        One human-readable line per problem.
    """
    from capevo.records.names import validate_name

    problems: list[str] = []
    known = set(spec.signal_names)
    keys = set(spec.observation_keys)
    for step in spec.decomposition:
        try:
            validate_name(step.ecm)
        except Invalid as e:
            problems.append(f"{step.ecm}: {e.message}")
        if not step.ecm.startswith(spec.name + "."):
            problems.append(f"{step.ecm}: does not start with {spec.name + '.'!r}")
        for p in (step.termination, step.applicability):
            problems.extend(f"{step.ecm}: unknown signal {c.signal!r}" for c in p.all if c.signal not in known)
        problems.extend(f"{step.ecm}: unknown observation key {k!r}" for k in step.observation_keys if k not in keys)
    problems.extend(f"position key {k!r} is not an observation key" for k in spec.position_keys if k not in keys)
    return problems
