"""The built-in parametric code skills that seed every task's ECMs at version 0.

One module per task family (:mod:`.pick_place` for T1/T2/T5, :mod:`.stack` for T3,
:mod:`.nut_assembly` for T4, :mod:`.peg_in_hole` for T6), sharing :mod:`.grasping` (reach,
grasp, lift). Each skill follows the code ECM contract (:mod:`capevo.runtime.ecm.code`): a
``PARAMS`` literal, ``act(obs, params)`` and ``done(obs, params)``, pure functions of their
arguments. Its interface declares the step's raw observation keys as inputs and one
``action`` output bounded to [-1, 1]; its descriptor is the task's :class:`EcmStep` (so the
termination predicates are the task's decomposition signals).

What version 0 is: *manual creation*. The structure (phases, tolerances, noise handling) is
written by hand; the parameters are plausible guesses made without running the simulator,
deliberately left untuned (wrong grasp height, low gains, wrong carry heights). With
perturbations on, v0 fails most episodes: it is the starting point the learners improve.

Invariants:
1. ``seed_specs(task)`` returns one entry per ECM of the task's decomposition, in order, with
   the step's descriptor, origin ``manual`` and no parent.
2. Every source passes the sandbox validator and follows the contract (``act``, ``done``,
   literal ``PARAMS``).
3. An unknown task raises :class:`Invalid` listing the task names that have skills.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from capevo.errors import Invalid
from capevo.learner.skills import nut_assembly, peg_in_hole, pick_place, stack
from capevo.learner.skills._lib import OBS_SHAPES, PRELUDE, SkillTemplate, publish_spec, render
from capevo.records import EcmVersion, PublishSpec
from capevo.registry.api import Registry
from capevo.runtime.tasks import task_spec
from capevo.runtime.tasks.spec import TaskSpec

Family = Callable[[TaskSpec], dict[str, tuple[SkillTemplate, dict[str, str]]]]
"""Task spec -> ``{ecm: (template, placeholder values)}`` for every ECM of its decomposition."""

_FAMILIES: dict[str, Family] = {}


def register_family(*task_names: str) -> Callable[[Family], Family]:
    """Decorator: ``fn`` provides the skills of the tasks named ``task_names``."""

    def deco(fn: Family) -> Family:
        for name in task_names:
            _FAMILIES[name] = fn
        return fn

    return deco


@register_family("pick", "place", "pick_place_multi")
def _bins(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    return pick_place.templates(spec)


@register_family("stack")
def _stack(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    return stack.templates(spec)


@register_family("nut_assembly")
def _nut(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    return nut_assembly.templates(spec)


@register_family("peg_in_hole")
def _peg(spec: TaskSpec) -> dict[str, tuple[SkillTemplate, dict[str, str]]]:
    return peg_in_hole.templates(spec)


def skill_tasks() -> tuple[str, ...]:
    """Task names that have built-in skills."""
    return tuple(sorted(_FAMILIES))


def make_family(task: str) -> Family:
    """The skill family of ``task`` (``"T1"`` or ``"pick"``).

    Raises:
        Invalid: unknown task or one without built-in skills; the message lists those that have.
    """
    spec = task_spec(task)
    try:
        return _FAMILIES[spec.name]
    except KeyError:
        raise Invalid(
            f"no built-in skills for task {task!r}; valid: {', '.join(skill_tasks())}", details={"field": "task"}
        ) from None


def _templates(task: str) -> tuple[TaskSpec, dict[str, tuple[SkillTemplate, dict[str, str]]]]:
    spec = task_spec(task)
    return spec, make_family(task)(spec)


def seed_source(task: str, ecm: str) -> str:
    """The v0 source of one ECM of ``task``.

    Raises:
        Invalid: unknown task, or ``ecm`` is not in its decomposition (lists the valid names).
    """
    spec, table = _templates(task)
    try:
        template, keys = table[ecm]
    except KeyError:
        raise Invalid(
            f"task {spec.name!r} has no ECM {ecm!r}; valid: {', '.join(spec.ecm_names)}", details={"field": "ecm"}
        ) from None
    return render(template, **keys)


def siblings(task: str, ecm: str) -> tuple[str, ...]:
    """The other ECMs of ``task`` whose v0 comes from the same skill template as ``ecm``'s, in plan
    order: T5's same step for its other two objects; empty for every other task's ECMs.

    Siblings share the hand-written structure and parameter names; their placeholders (which
    object, its grasp height) differ. ``capevo evolve --tie-siblings`` searches one parameter set for them.

    Raises:
        Invalid: as :func:`seed_source`.
    """
    spec, table = _templates(task)
    if ecm not in table:
        seed_source(task, ecm)  # raises the listing error
    template = table[ecm][0]
    return tuple(e for e in spec.ecm_names if e != ecm and table[e][0] is template)


def seed_params(task: str, ecm: str) -> dict[str, float]:
    """The v0 ``PARAMS`` of one ECM of ``task`` (a copy).

    Raises:
        Invalid: as :func:`seed_source`.
    """
    _, table = _templates(task)
    if ecm not in table:
        seed_source(task, ecm)  # raises the listing error
    return {k: float(v) for k, v in table[ecm][0].params.items()}


def seed_specs(task: str) -> list[tuple[str, str, PublishSpec]]:
    """Version 0 of every ECM of ``task``: ``(ecm name, source text, publish spec)`` in plan order.

    Raises:
        Invalid: unknown task or one without built-in skills.
    """
    spec, table = _templates(task)
    out = []
    for step in spec.decomposition:
        template, keys = table[step.ecm]
        out.append((step.ecm, render(template, **keys), publish_spec(step, spec)))
    return out


def seed_registry(
    registry: Registry, task: str, *, promote: bool = True, reason: str = "built-in v0 skill"
) -> list[EcmVersion]:
    """Publish (and by default promote) v0 of every ECM of ``task`` that has no version yet.

    ECMs that already have versions are left alone, so seeding twice is harmless.

    Args:
        registry: Where to publish.
        task: Task id or name.
        promote: Make each new version active.
        reason: Audit reason of the promotion.

    Returns:
        The records of the versions published now (after promotion when ``promote``).
    """
    existing = {s.name for s in registry.list_ecms()}
    out = []
    for name, source, spec in seed_specs(task):
        if name in existing:
            continue
        record = registry.publish(name, source.encode(), spec)
        if promote:
            record = registry.promote(name, record.version, reason=reason)
        out.append(record)
    return out


def seed_all(registry: Registry, tasks: Sequence[str] | None = None) -> list[EcmVersion]:
    """:func:`seed_registry` for every task with built-in skills (or ``tasks``)."""
    out: list[EcmVersion] = []
    for task in tasks or skill_tasks():
        out.extend(seed_registry(registry, task))
    return out


__all__ = [
    "OBS_SHAPES",
    "PRELUDE",
    "SkillTemplate",
    "make_family",
    "publish_spec",
    "register_family",
    "render",
    "seed_all",
    "seed_params",
    "seed_registry",
    "seed_source",
    "seed_specs",
    "skill_tasks",
]
