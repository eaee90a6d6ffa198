"""The least change to an action that bounds its closing speed along one direction.

Shared by ``contact_approach`` (closing on a sensed pair) and ``reach_limit`` (moving out of an
arm's reach): both bound a speed ``Σ_{k: a_k n_k > 0} a_k · n_k`` and leave the rest of the motion
alone as far as they can.

Invariants (after :func:`brake_along`, with ``sign`` folded into ``n``):
1. ``Σ_{k: a_k n_k > 0} a_k · n_k <= q`` (to rounding).
2. Only components with ``a_k · n_k > 0`` change, towards 0 and never past it; a bound already
   met changes nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

from capevo.runtime.governance.cap import SHRINK


def brake_along(arm: list[float], axes: Sequence[tuple[int, float]], q: float, sign: float = 1.0) -> None:
    """Shrink ``arm``'s components approaching along ``n`` (``sign · a_k · n_k > 0``) so that their
    closing speed is at most ``q``, changing the action as little as possible.

    The least-squares change under that bound removes ``λ · n_k`` from each approaching
    component, with one ``λ`` for all; a component that would cross 0 stops at 0 and the rest
    share what is left. So the closing motion is removed along ``n`` and motion across ``n``
    (tangential) is kept, where scaling every approaching component by one factor would slow a
    hand that mostly moves past a geom as much as one that moves straight at it.
    """
    # The closing speed first: a bound already met (the common case) builds nothing.
    c = 0.0
    for k, n in axes:
        v = sign * arm[k] * n
        if v > 0.0:
            c += v
    if c <= q:
        return
    active = [(k, n) for k, n in axes if sign * arm[k] * n > 0.0]
    excess = c - q * SHRINK
    while active and excess > 0.0:
        nn = 0.0
        for _, n in active:
            nn += n * n
        if not nn > 0.0:
            # Directions so small their squares underflow: scale by one factor instead.
            c = 0.0
            for k, n in active:
                c += sign * arm[k] * n
            f = q / c * SHRINK if c > q else 1.0
            for k, _ in active:
                arm[k] *= f
            return
        lam = excess / nn
        # The component that reaches 0 first (smallest |a_k| / |n_k|) bounds lambda.
        k0, n0 = min(active, key=lambda kn: abs(arm[kn[0]] / kn[1]))
        if lam * abs(n0) < abs(arm[k0]):
            for k, n in active:
                v = arm[k] - sign * lam * n
                # Components that reach 0 together (an action parallel to n) can cross it by
                # rounding; they stop at 0, which closes no faster.
                arm[k] = v if v * arm[k] > 0.0 else 0.0
            return
        excess -= sign * arm[k0] * n0
        arm[k0] = 0.0
        active.remove((k0, n0))
