"""A loaded ECM: its identity and interface, plus the runner that executes it.

Invariants:
1. ``runner`` is None exactly for prompt ECMs, which are not executable; ``text`` is set
   exactly for them.
2. :meth:`LoadedEcm.close` is idempotent and releases the runner (kills a sandbox worker).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from capevo.records import Interface, Kind, Origin
from capevo.runtime.sandbox.client import SkillStep


@runtime_checkable
class Runner(Protocol):
    """Executes one ECM step by step. Implemented by :class:`~capevo.runtime.ecm.code.CodeSkill`,
    :class:`~capevo.runtime.sandbox.client.SandboxedSkill` and
    :class:`~capevo.runtime.ecm.neural.NeuralPolicy`."""

    in_process: bool

    def step(self, inputs: Mapping[str, np.ndarray], *, timeout_s: float) -> SkillStep:
        """``done`` check then action for one marshalled observation.

        Raises whatever the ECM raised; sandboxed runners also raise
        :class:`capevo.errors.Timeout` and :class:`~capevo.runtime.sandbox.client.WorkerDied`.
        """
        ...

    def close(self) -> None: ...


@dataclass(eq=False, slots=True, kw_only=True)
class LoadedEcm:
    """One ECM version ready to run (a live handle, not a record)."""

    name: str
    version: int
    kind: Kind
    origin: Origin
    interface: Interface = field(default_factory=Interface)
    runner: Runner | None = None
    text: str | None = None

    @property
    def label(self) -> str:
        """``name@version`` for messages."""
        return f"{self.name}@{self.version}"

    @property
    def in_process(self) -> bool:
        return self.runner.in_process if self.runner is not None else True

    def close(self) -> None:
        """Release the runner (kills a sandbox worker). Idempotent."""
        if self.runner is not None:
            self.runner.close()

    def __enter__(self) -> LoadedEcm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
