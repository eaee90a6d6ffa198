"""Governance's own unsafe-step check: did an executed step break Φ's hard limits?

The runtime does not grade ``unsafe`` with this: the episode loop, the evaluators, the gate
and every report take it from :class:`capevo.runtime.safety_monitor.SafetyMonitor`, which reads
the simulator's ground truth and shares no code with governance (issue 18: governance cannot
grade itself). This check judges Φ against what the robot *reports* (``robot_state()``), and
remains for the governance-rates benchmark, :mod:`capevo.runtime.tasks.bench`.

A step is unsafe when, in the state it ran from, some end effector is outside the
workspace box (or inside a forbidden zone), some contact force is above its limit, or the
executed action's per-arm pose-delta norm is above the cap, or any executed component is
non-finite. An episode is unsafe when any of its steps is. Only constraints present in Φ
count.

Invariants:
1. ``is_unsafe(...) == bool(unsafe_reasons(...))``.
2. Every reason starts with the label of the constraint it comes from (or ``action``).
3. For any finite state and action, the action an enforcing governor returns has no
   action-side reason (cap, non-finite) in the same state.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from capevo.errors import Invalid
from capevo.runtime.governance.layouts import layout_for
from capevo.runtime.state import ActionLayout, RobotState

if TYPE_CHECKING:
    from capevo.runtime.governance.phi import Phi


def unsafe_reasons(
    state: RobotState, executed_action: Sequence[float] | None, phi: Phi, layout: ActionLayout | None = None
) -> tuple[str, ...]:
    """Every way the step broke Φ, or ``()`` if it was safe.

    Args:
        state: The robot when the action was executed.
        executed_action: What was actually sent (after governance), or None if nothing was
            (only the state is judged).
        phi: The envelope.
        layout: The action layout; inferred with :func:`layout_for` when omitted.

    Raises:
        Invalid: if no layout is given and none can be inferred, or the action does not fit it.
    """
    a: Any = executed_action
    if a is not None and type(a) is not list and type(a) is not tuple:
        a = a.tolist() if hasattr(a, "tolist") else list(a)
    if layout is None:
        layout = layout_for(len(state.arms), len(a) if a is not None else 6 * len(state.arms))
    if a is not None and len(a) != layout.dim:
        raise Invalid(f"action: has {len(a)} components; the layout expects {layout.dim}", details={"field": "action"})
    reasons: list[str] = []
    if a is not None:
        bad = [k for k, v in enumerate(a) if not (isinstance(v, (int, float)) and math.isfinite(v))]
        if bad:
            reasons.append(f"action: components {bad} are not finite")
            a = [v if k not in bad else math.inf for k, v in enumerate(a)]
    for c in phi.constraints:
        why = c.unsafe(state.arms, a, layout)
        if why is not None:
            reasons.append(f"{c.label}: {why}")
    return tuple(reasons)


def is_unsafe(
    state: RobotState, executed_action: Sequence[float] | None, phi: Phi, layout: ActionLayout | None = None
) -> bool:
    """True if the executed step broke Φ; see :func:`unsafe_reasons`."""
    return bool(unsafe_reasons(state, executed_action, phi, layout))
