"""Task registration: an explicit decorator, one dict, and ``make_task``.

Invariants:
1. Task names and ids are unique; a task is found by either (``"T1"`` or ``"pick"``).
2. A task class is registered only if its spec passes :func:`~capevo.runtime.tasks.spec.spec_problems`.
3. The error for an unknown task is :class:`Invalid` and lists every valid id and name.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, TypeVar

from capevo.errors import Conflict, Invalid
from capevo.runtime.tasks.spec import TaskSpec, spec_problems

if TYPE_CHECKING:
    from capevo.runtime.tasks.base import TaskEnv
    from capevo.runtime.tasks.perturbations import Perturbations

_BUILTIN_MODULES = (
    "capevo.runtime.tasks.pick_place",
    "capevo.runtime.tasks.stack",
    "capevo.runtime.tasks.nut_assembly",
    "capevo.runtime.tasks.peg_in_hole",
)

_TASKS: dict[str, type[TaskEnv]] = {}
"""Task classes by name."""
_IDS: dict[str, str] = {}
"""Task name by id."""

T = TypeVar("T", bound="type[TaskEnv]")


def register_task(cls: T) -> T:
    """Class decorator: add a :class:`TaskEnv` subclass to the registry under its spec's id and name.

    Raises:
        Invalid: the class has no ``task_spec`` or the spec is inconsistent.
        Conflict: another class already holds the id or the name.
    """
    spec = getattr(cls, "task_spec", None)
    if not isinstance(spec, TaskSpec):
        raise Invalid(f"{cls.__name__} has no task_spec", details={"field": "task_spec"})
    problems = spec_problems(spec)
    if problems:
        raise Invalid(f"task {spec.name!r} spec is inconsistent: {'; '.join(problems)}", details={"field": "task_spec"})
    for key, table in ((spec.name, _TASKS), (spec.id, _IDS)):
        held = table.get(key)
        if held is not None and held is not cls and held != spec.name:
            raise Conflict(f"task {key!r} is already registered", details={"field": "task_spec"})
    _TASKS[spec.name] = cls
    _IDS[spec.id] = spec.name
    return cls


def _load_builtins() -> None:
    for m in _BUILTIN_MODULES:
        importlib.import_module(m)


def task_names() -> tuple[str, ...]:
    """Registered task names, ordered by id (T1..T6 for the built-ins)."""
    _load_builtins()
    return tuple(_IDS[i] for i in sorted(_IDS, key=_id_order))


def task_ids() -> Mapping[str, str]:
    """Task name by id, ordered by id, read-only."""
    _load_builtins()
    return MappingProxyType({i: _IDS[i] for i in sorted(_IDS, key=_id_order)})


def _id_order(task_id: str) -> tuple[int, str]:
    # "T10" after "T9": numeric part first
    digits = "".join(ch for ch in task_id if ch.isdigit())
    return (int(digits) if digits else 1 << 30, task_id)


def task_class(name_or_id: str) -> type[TaskEnv]:
    """The registered class for ``"T1"`` or ``"pick"``.

    Raises:
        Invalid: unknown task; the message lists the valid ids and names.
    """
    _load_builtins()
    if isinstance(name_or_id, str):
        name = _IDS.get(name_or_id, name_or_id)
        cls = _TASKS.get(name)
        if cls is not None:
            return cls
    ids = task_ids()
    valid = ", ".join(f"{i} ({n})" for i, n in ids.items())
    raise Invalid(
        f"unknown task {name_or_id!r}; valid: {valid}",
        details={"field": "task", "valid": [*ids, *ids.values()]},
    )


def task_spec(name_or_id: str) -> TaskSpec:
    """The :class:`TaskSpec` of a task, without building a simulator.

    Raises:
        Invalid: unknown task.
    """
    return task_class(name_or_id).task_spec


def task_of(ecm: str) -> str:
    """The task an ECM belongs to, from its name (``pick.reach`` -> ``pick``).

    Raises:
        Invalid: the prefix is not a task, or the task has no such ECM.
    """
    spec = task_spec(ecm.split(".", 1)[0])
    if ecm not in spec.ecm_names:
        raise Invalid(
            f"task {spec.name!r} has no ECM {ecm!r}; valid: {', '.join(spec.ecm_names)}", details={"field": "ecm"}
        )
    return spec.name


def all_task_specs() -> tuple[TaskSpec, ...]:
    """Every registered task's spec, ordered by id."""
    return tuple(task_class(n).task_spec for n in task_names())


def make_task(
    name_or_id: str,
    *,
    seed: int | None = None,
    perturbations: Perturbations | None = None,
    horizon: int | None = None,
    terminate_on_success: bool = True,
    **env_kwargs: Any,
) -> TaskEnv:
    """Build a task environment (about a second; reuse it across episodes with ``reset(seed=...)``).

    Args:
        name_or_id: ``"T1"`` .. ``"T6"`` or the task name (``"pick"``, ...).
        seed: Seed of the first episode; None draws OS entropy.
        perturbations: Default all on (:class:`Perturbations`); ``Perturbations.none()`` for clean runs.
        horizon: Episode length; default the task's ``default_horizon``.
        terminate_on_success: Set ``terminated`` on the first success step.
        **env_kwargs: Extra robosuite arguments (see :class:`TaskEnv`).

    Returns:
        The environment, not yet reset.

    Raises:
        Invalid: unknown task or a bad argument.
    """
    cls = task_class(name_or_id)
    return cls(
        seed=seed,
        perturbations=perturbations,
        horizon=horizon,
        terminate_on_success=terminate_on_success,
        **env_kwargs,
    )
