"""Which code ECMs may run in the host process, and which go to the sandbox.

Invariants:
1. Only ``code`` ECMs whose origin is in ``in_process_origins`` run in-process; every other
   code ECM (``llm``, ``hybrid``, ``clone``, ``rl``, ``il`` by default) runs in a sandbox
   worker. Neural ECMs run in-process whatever their origin: their loader never unpickles
   (see :mod:`capevo.runtime.ecm.neural`), so the artifact cannot run code.
2. Code is validated against the sandbox rules wherever it runs.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from capevo.errors import Invalid
from capevo.records import Kind, Origin


@dataclass(frozen=True, slots=True, kw_only=True)
class TrustPolicy:
    """Where code ECMs run, by origin.

    Args:
        in_process_origins: Origins whose code runs in the host for speed. The default,
            ``{manual}``, is for the built-in skills shipped with capevo and reviewed by
            people; anything a model or a learner wrote goes to the sandbox.
    """

    in_process_origins: frozenset[Origin] = field(default_factory=lambda: frozenset({Origin.MANUAL}))

    def runs_in_process(self, kind: Kind, origin: Origin) -> bool:
        """Whether an ECM of this kind and origin runs in the host process."""
        if kind is Kind.CODE:
            return origin in self.in_process_origins
        return True

    def to_dict(self) -> dict[str, Any]:
        return {"in_process_origins": sorted(o.value for o in self.in_process_origins)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrustPolicy:
        return cls(in_process_origins=parse_origins(d.get("in_process_origins", ["manual"])))


SANDBOX_EVERYTHING = TrustPolicy(in_process_origins=frozenset())
"""Run every code ECM in the sandbox, even manual ones."""


def parse_origins(values: Iterable[str]) -> frozenset[Origin]:
    """Origin names from a config file.

    Raises:
        Invalid: an unknown origin, listing the valid ones.
    """
    out: set[Origin] = set()
    for v in values:
        try:
            out.add(Origin(v))
        except ValueError:
            valid = ", ".join(o.value for o in Origin)
            raise Invalid(f"in_process_origins: unknown origin {v!r}; valid: {valid}") from None
    return frozenset(out)
