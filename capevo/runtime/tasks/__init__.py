"""The six robosuite tasks as gymnasium environments.

``make_task("T1")`` or ``make_task("pick")`` builds one; ``task_spec(...)`` reads a task's
spec (decomposition, signals, action layout) without building a simulator.
"""

from __future__ import annotations

from capevo.runtime.tasks._common import SUCCESS_SIGNAL
from capevo.runtime.tasks.base import RESERVED_ENV_KWARGS, TaskEnv
from capevo.runtime.tasks.perturbations import Perturbations
from capevo.runtime.tasks.registry import (
    all_task_specs,
    make_task,
    register_task,
    task_class,
    task_ids,
    task_names,
    task_of,
    task_spec,
)
from capevo.runtime.tasks.spec import EcmStep, SignalSpec, TaskSpec

__all__ = [
    "RESERVED_ENV_KWARGS",
    "SUCCESS_SIGNAL",
    "EcmStep",
    "Perturbations",
    "SignalSpec",
    "TaskEnv",
    "TaskSpec",
    "all_task_specs",
    "make_task",
    "register_task",
    "task_class",
    "task_ids",
    "task_names",
    "task_of",
    "task_spec",
]
