"""Which Φ runs: the scene-aware per-task envelope by default, the paper's on request.

Every part that runs episodes (the runtime worker, the evaluator, the gate's and the learner's
episodes, ``capevo evolve``, ``scripts/demo``) takes a :data:`PhiChoice` and resolves it here,
so they agree on one default:

* ``"task"`` (the default): :meth:`Phi.for_task`, the paper's workspace box, 20 N contact-force
  limit and velocity cap (paper §4.1, "Experimental Setup"), plus what is known about the task's scene
  (braking near surfaces, obstacles and sensed objects, a force ramp, the arm's reach; see
  :mod:`capevo.runtime.governance.task_phi`). It prevents collisions instead of reacting to them.
* ``"paper"``: :meth:`Phi.default`, the paper's three constraints alone, to reproduce its table.
* a path to a Φ YAML file, or a :class:`Phi` object: that envelope, for every task.

Φ is fixed for a run (paper §3.2: Φ "remains fixed during evolution"); nothing here loosens it per skill.

Invariants:
1. ``resolve_phi(None, t) == resolve_phi("task", t) == Phi.for_task(t)`` and
   ``resolve_phi("paper", t) == Phi.default()`` for every task ``t``.
2. ``phi_name(resolve_phi(c, t), t)`` is ``c`` for ``c`` in :data:`PHI_NAMES`, and
   ``"custom"`` for an envelope equal to neither.
3. A bad choice raises :class:`Invalid` naming the valid ones; a bad file raises what
   :func:`load_phi` raises.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Union

from capevo.errors import Invalid
from capevo.runtime.governance import Phi, load_phi

PHI_TASK = "task"
PHI_PAPER = "paper"
PHI_NAMES: tuple[str, ...] = (PHI_TASK, PHI_PAPER)
"""The named envelopes; anything else is a Φ YAML file."""
DEFAULT_PHI = PHI_TASK
"""The runtime's default: the scene-aware per-task envelope."""

PhiChoice = Union[Phi, str, "os.PathLike[str]", None]
"""A Φ, a name in :data:`PHI_NAMES`, a YAML path, or None (:data:`DEFAULT_PHI`)."""


def resolve_phi(choice: PhiChoice, task: Any) -> Phi:
    """The envelope ``choice`` names for ``task`` (a ``TaskSpec``, a ``TaskEnv`` or a task name).

    Raises:
        Invalid: ``choice`` is neither a Φ, a known name, nor a readable Φ file.
    """
    if isinstance(choice, Phi):
        return choice
    if choice is None or choice == PHI_TASK:
        return Phi.for_task(task)
    if choice == PHI_PAPER:
        return Phi.default()
    if isinstance(choice, (str, os.PathLike)):
        path = Path(choice)
        if not path.is_file():
            raise Invalid(
                f"phi: {str(choice)!r} is neither one of {', '.join(PHI_NAMES)} nor a Φ YAML file",
                details={"field": "phi", "valid": list(PHI_NAMES)},
            )
        return load_phi(path)
    raise Invalid(
        f"phi: expected one of {', '.join(PHI_NAMES)}, a Φ YAML path or a Phi, got {type(choice).__name__}",
        details={"field": "phi", "valid": list(PHI_NAMES)},
    )


def phi_name(phi: Phi, task: Any) -> str:
    """``"task"`` or ``"paper"`` when ``phi`` is that envelope for ``task``, else ``"custom"``."""
    if phi.hash == Phi.for_task(task).hash:
        return PHI_TASK
    if phi.hash == Phi.default().hash:
        return PHI_PAPER
    return "custom"


def check_phi_choice(choice: object) -> str:
    """``choice`` as a config value: a name in :data:`PHI_NAMES` or an existing file's path.

    Raises:
        Invalid: anything else, naming the valid names.
    """
    if isinstance(choice, str) and (choice in PHI_NAMES or Path(choice).is_file()):
        return choice
    raise Invalid(
        f"phi: expected one of {', '.join(PHI_NAMES)} or a Φ YAML file, got {choice!r}",
        details={"field": "phi", "valid": list(PHI_NAMES)},
    )


__all__ = [
    "DEFAULT_PHI",
    "PHI_NAMES",
    "PHI_PAPER",
    "PHI_TASK",
    "PhiChoice",
    "check_phi_choice",
    "phi_name",
    "resolve_phi",
]
