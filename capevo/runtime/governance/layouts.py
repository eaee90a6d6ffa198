"""Action layouts governance needs beyond :data:`capevo.runtime.state.SINGLE_PANDA`.

Invariants:
1. :func:`check_layout` accepts a layout only if every arm's six pose indices and its
   gripper index lie in ``[0, dim)`` and no index belongs to two places.
2. :func:`layout_for` returns :data:`SINGLE_PANDA` for (1 arm, 7), :data:`TWO_ARM_NO_GRIPPER`
   for (2 arms, 12), and otherwise packs arms back to back (6 per arm, or 6 + gripper).
"""

from __future__ import annotations

from capevo.errors import Invalid
from capevo.runtime.state import SINGLE_PANDA, ActionLayout, ArmActionLayout

TWO_ARM_NO_GRIPPER = ActionLayout(dim=12, arms=(ArmActionLayout(offset=0), ArmActionLayout(offset=6)))
"""Two OSC_POSE arms without grippers, robot 0 first (TwoArmPegInHole: 12-dim)."""


def check_layout(layout: ActionLayout) -> ActionLayout:
    """Return ``layout`` if its indices fit ``dim`` without overlap.

    Raises:
        Invalid: naming the first arm whose indices are out of range or overlap another's.
    """
    used: set[int] = set()
    for i, arm in enumerate(layout.arms):
        idx = [*range(arm.offset, arm.offset + 6), *([] if arm.gripper is None else [arm.gripper])]
        for j in idx:
            if not 0 <= j < layout.dim:
                raise Invalid(
                    f"layout.arms[{i}]: index {j} is outside an action of {layout.dim}",
                    details={"field": f"layout.arms[{i}]"},
                )
            if j in used:
                raise Invalid(f"layout.arms[{i}]: index {j} is used twice", details={"field": f"layout.arms[{i}]"})
            used.add(j)
    return layout


def layout_for(n_arms: int, dim: int) -> ActionLayout:
    """The layout for ``n_arms`` arms in an action of ``dim`` components.

    Raises:
        Invalid: if ``dim`` is neither ``6 * n_arms`` nor ``7 * n_arms`` (or ``n_arms < 1``).
    """
    if n_arms == 1 and dim == 7:
        return SINGLE_PANDA
    if n_arms == 2 and dim == 12:
        return TWO_ARM_NO_GRIPPER
    if n_arms >= 1 and dim == 6 * n_arms:
        return ActionLayout(dim=dim, arms=tuple(ArmActionLayout(offset=6 * i) for i in range(n_arms)))
    if n_arms >= 1 and dim == 7 * n_arms:
        return ActionLayout(
            dim=dim, arms=tuple(ArmActionLayout(offset=7 * i, gripper=7 * i + 6) for i in range(n_arms))
        )
    raise Invalid(
        f"action: cannot infer a layout for {n_arms} arm(s) and {dim} components; pass layout=",
        details={"field": "action"},
    )
