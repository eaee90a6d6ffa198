"""Δπ: how far the decision policy's parameters moved between the first and the last iteration.

``Δπ = ||θ_last − θ_first||₂ / max(||θ_first||₂, ε)``. The persistent agent never learns, so
for it Δπ is exactly 0.0; the metric is there to show it, next to how far the ECMs moved.

Invariants:
1. ``policy_drift(v, v) == 0.0`` exactly, for every finite ``v``.
2. Vectors of different lengths, or with a non-finite entry, raise :class:`Invalid`.
3. The tracker keeps the vector of the first iteration it saw; iterations never go backwards.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from capevo.errors import Invalid

DEFAULT_EPS = 1e-12


def _vector(values: Sequence[float], what: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise Invalid(f"{what}: expected a sequence of numbers", details={"field": what}) from None
    bad = [i for i, v in enumerate(out) if not math.isfinite(v)]
    if bad:
        raise Invalid(f"{what}[{bad[0]}]: must be finite, got {out[bad[0]]}", details={"field": f"{what}[{bad[0]}]"})
    return out


def policy_drift(first: Sequence[float], last: Sequence[float], *, eps: float = DEFAULT_EPS) -> float:
    """Normalised ℓ2 distance ``||last − first|| / max(||first||, eps)``.

    Args:
        first: θ at the first iteration.
        last: θ at the last iteration.
        eps: Floor of the denominator, so an all-zero θ_first does not divide by zero.

    Returns:
        Δπ, a non-negative float.

    Raises:
        Invalid: different lengths, a non-finite entry, or ``eps`` not positive.
    """
    a, b = _vector(first, "first"), _vector(last, "last")
    if len(a) != len(b):
        raise Invalid(
            f"last: has {len(b)} parameters but first has {len(a)}; the policy's parameter layout changed",
            details={"field": "last"},
        )
    if not (isinstance(eps, (int, float)) and math.isfinite(eps) and eps > 0):
        raise Invalid(f"eps: must be a positive finite number, got {eps!r}", details={"field": "eps"})
    distance = math.sqrt(math.fsum((y - x) ** 2 for x, y in zip(a, b, strict=True)))
    norm = math.sqrt(math.fsum(x * x for x in a))
    return distance / max(norm, float(eps))


class PolicyDriftTracker:
    """Remembers θ at the first iteration and reports Δπ at each later one.

    Args:
        eps: Denominator floor of :func:`policy_drift`.
    """

    __slots__ = ("_eps", "_first", "_first_iteration", "_last", "_last_iteration")

    def __init__(self, *, eps: float = DEFAULT_EPS) -> None:
        self._eps = eps
        self._first: tuple[float, ...] | None = None
        self._last: tuple[float, ...] | None = None
        self._first_iteration: int | None = None
        self._last_iteration: int | None = None

    @property
    def first_iteration(self) -> int | None:
        return self._first_iteration

    @property
    def last_iteration(self) -> int | None:
        return self._last_iteration

    def observe(self, iteration: int, vector: Sequence[float]) -> float:
        """Record θ at ``iteration``; the first call fixes θ_first.

        Returns:
            Δπ between the first recorded iteration and this one.

        Raises:
            Invalid: ``iteration`` lower than the last one seen, or a bad vector (see :func:`policy_drift`).
        """
        if isinstance(iteration, bool) or not isinstance(iteration, int):
            raise Invalid(f"iteration: must be an integer, got {iteration!r}", details={"field": "iteration"})
        if self._last_iteration is not None and iteration < self._last_iteration:
            raise Invalid(
                f"iteration: {iteration} comes before the last recorded iteration {self._last_iteration}",
                details={"field": "iteration"},
            )
        v = _vector(vector, "vector")
        first = self._first if self._first is not None else v
        drift = policy_drift(first, v, eps=self._eps)
        if self._first is None:
            self._first, self._first_iteration = v, iteration
        self._last, self._last_iteration = v, iteration
        return drift

    def drift(self) -> float:
        """Δπ between the first and the last recorded iteration (0.0 before any)."""
        if self._first is None or self._last is None:
            return 0.0
        return policy_drift(self._first, self._last, eps=self._eps)
