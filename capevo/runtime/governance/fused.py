"""The fused kernel: a whole Φ checked in one C call, with the Python checks as its specification.

Each Python check costs about a microsecond of interpreter overhead whatever it computes, and a
per-task Φ runs ten of them per action; the issue's budget is 5 µs for all of R(a, Φ). So a
:class:`~capevo.runtime.governance.governor.Governor` whose Φ has a C port of every constraint
(``csrc/<kind>.c``, built as ``capevo.runtime.governance._fused`` when the package installs)
runs the checks there: one call reads the action and the arm states, rotates the arms'
translations into the world frame, applies every check in Φ order and returns the verdict.
The governor still builds the interventions and counts them, so records, counters and the
returned action are what the Python checks give, bit for bit.

Invariants:
1. :func:`fused_program` returns a program only when the kernel is built, not switched off
   (``CAPEVO_GOVERNANCE_KERNEL=0``), and every constraint of Φ has a ``kernel_spec`` whose kind
   the kernel knows; otherwise None, and the governor runs the Python checks.
2. For every input, ``program(arms, action, enforce)`` returns ``True`` (allow), ``None`` (the
   Python checks must decide: inputs that are not exact floats, non-finite values, rare paths
   with formatted reasons) or ``(governed, records, indices)``: the governed action (None for
   ⊥), the intervention records and the index in Φ of each record's constraint. A governor that
   follows it gives the same output as one that does not
   (tested over random and recorded states, ``tests/runtime/governance/test_gov_fused.py``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from capevo.runtime.governance.cap import SHRINK
from capevo.runtime.governance.records import Intervention
from capevo.runtime.state import ActionLayout

if TYPE_CHECKING:
    from capevo.runtime.governance.phi import Phi

try:
    from capevo.runtime.governance import _fused
except ImportError:  # a source tree nobody installed: the Python checks still govern
    _fused = None
else:
    _fused.set_shrink(SHRINK)
    _fused.set_record_type(Intervention)

ENV_SWITCH = "CAPEVO_GOVERNANCE_KERNEL"
"""Set to 0 to govern with the Python checks only (to compare, or to debug a check)."""


def kernel_available() -> bool:
    """Whether the C kernel is built and not switched off."""
    return _fused is not None and os.environ.get(ENV_SWITCH, "1") != "0"


def kernel_kinds() -> tuple[str, ...]:
    """Constraint kinds the built kernel has a check for (empty when it is not built)."""
    return tuple(_fused.kinds()) if _fused is not None else ()


def fused_program(phi: Phi, layout: ActionLayout, rot: Sequence[tuple[int, tuple[float, ...]]] | None) -> Any | None:
    """Φ compiled into one kernel call for ``layout``, or None where the Python checks must run.

    Args:
        phi: The envelope.
        layout: The action layout the governor was built for.
        rot: The governor's rotated arms, as ``(offset, 9 floats)`` pairs; None for none.
    """
    if not kernel_available():
        return None
    known = set(kernel_kinds())
    specs = []
    for c in phi.constraints:
        make_spec = getattr(c, "kernel_spec", None)
        spec = make_spec(layout) if make_spec is not None else None
        if spec is None or spec.kind not in known:
            return None
        specs.append(spec)
    labels = tuple(c.label for c in phi.constraints)
    return _fused.Program(tuple(specs), layout.dim, len(layout.arms), tuple(rot or ()), labels)
