"""When a learner should produce a new version: pure, record-based update triggers.

Input: the outcomes of the episodes the ECM's current version ran, oldest first (success
flags), and how many of them had been seen at the last update. Two rules, each optional:

* **count**: at least ``min_new_episodes`` episodes arrived since the last update;
* **degradation**: the success rate over the latest ``window`` episodes is at least
  ``degradation_margin`` below the rate over the ``window`` episodes before them. It needs two
  full windows of history and a full window of *new* episodes (so one bad stretch triggers one
  update, not one per episode).

:func:`decide` is the rule as a pure function; :class:`UpdateTrigger` keeps the state (a
bounded history) for a long-running worker.

Invariants:
1. :func:`decide` never fires with no new episode.
2. With only the count rule, it fires exactly when ``new_episodes >= min_new_episodes``.
3. The degradation rule fires only when ``reference_rate - recent_rate >= margin`` (up to
   1e-12), both over full windows, and ``new_episodes >= window``.
4. :class:`UpdateTrigger` decides exactly as :func:`decide` over the whole history it was fed
   since its last reset, while keeping at most ``2 * window`` outcomes.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from capevo.errors import Invalid

_EPS = 1e-12


@dataclass(frozen=True, slots=True, kw_only=True)
class TriggerConfig:
    """Which rules fire an update.

    Args:
        min_new_episodes: Count rule threshold; None turns the rule off.
        window: Episodes per success-rate window of the degradation rule.
        degradation_margin: Drop in success rate (0-1] that fires; None turns the rule off.

    Raises:
        Invalid: both rules off, or a value out of range.
    """

    min_new_episodes: int | None = 20
    window: int = 20
    degradation_margin: float | None = 0.2

    def __post_init__(self) -> None:
        n = self.min_new_episodes
        if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
            raise Invalid(
                f"min_new_episodes must be a positive integer or None, got {n!r}", details={"field": "min_new_episodes"}
            )
        w = self.window
        if isinstance(w, bool) or not isinstance(w, int) or w < 1:
            raise Invalid(f"window must be a positive integer, got {w!r}", details={"field": "window"})
        m = self.degradation_margin
        if m is not None and (
            isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or not 0 < m <= 1
        ):
            raise Invalid(
                f"degradation_margin must be in (0, 1] or None, got {m!r}", details={"field": "degradation_margin"}
            )
        if n is None and m is None:
            raise Invalid(
                "turn on at least one rule: min_new_episodes or degradation_margin",
                details={"field": "min_new_episodes"},
            )

    def to_dict(self) -> dict[str, Any]:
        return {
            "min_new_episodes": self.min_new_episodes,
            "window": self.window,
            "degradation_margin": self.degradation_margin,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class TriggerDecision:
    """Whether to update now, and the evidence."""

    fire: bool
    reason: str
    """``count``, ``degradation`` or ``""``."""
    new_episodes: int
    recent_rate: float | None = None
    reference_rate: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "fire": self.fire,
            "reason": self.reason,
            "new_episodes": self.new_episodes,
            "recent_rate": self.recent_rate,
            "reference_rate": self.reference_rate,
        }


def _rate(flags: Sequence[bool]) -> float:
    return sum(1 for f in flags if f) / len(flags)


def decide(successes: Sequence[bool], since: int, config: TriggerConfig) -> TriggerDecision:
    """Apply ``config``'s rules to a history of episode outcomes.

    Args:
        successes: Outcomes of the current version's episodes, oldest first (at least the last
            ``2 * window`` of them; older ones are not read).
        since: How many episodes had arrived at the last update (0: none yet); ``len(successes)``
            minus ``since`` are new. ``since`` counts from the same origin as ``successes``.
        config: The rules.

    Returns:
        The decision; ``fire`` False with reason ``""`` when no rule fires.

    Raises:
        Invalid: ``since`` negative or beyond the history.
    """
    total = len(successes)
    if isinstance(since, bool) or not isinstance(since, int) or not 0 <= since <= total:
        raise Invalid(f"since must be in [0, {total}], got {since!r}", details={"field": "since"})
    return _decide(list(successes[-2 * config.window :]), total - since, config)


def _decide(tail: Sequence[bool], new: int, config: TriggerConfig) -> TriggerDecision:
    w = config.window
    recent = _rate(tail[-w:]) if len(tail) >= w else None
    reference = _rate(tail[-2 * w : -w]) if len(tail) >= 2 * w else None
    if new <= 0:
        return TriggerDecision(fire=False, reason="", new_episodes=0, recent_rate=recent, reference_rate=reference)
    if config.min_new_episodes is not None and new >= config.min_new_episodes:
        return TriggerDecision(
            fire=True, reason="count", new_episodes=new, recent_rate=recent, reference_rate=reference
        )
    margin = config.degradation_margin
    if (
        margin is not None
        and recent is not None
        and reference is not None
        and new >= w
        and reference - recent >= margin - _EPS
    ):
        return TriggerDecision(
            fire=True, reason="degradation", new_episodes=new, recent_rate=recent, reference_rate=reference
        )
    return TriggerDecision(fire=False, reason="", new_episodes=new, recent_rate=recent, reference_rate=reference)


class UpdateTrigger:
    """The rules of :func:`decide` with their state, for a long-running learner.

    Feed it each episode's outcome (:meth:`observe`), ask :meth:`check`, call
    :meth:`mark_updated` after publishing a candidate and :meth:`reset` when the ECM's active
    version changes (the history belonged to the old version).
    """

    def __init__(self, config: TriggerConfig | None = None) -> None:
        self.config = config or TriggerConfig()
        self._tail: deque[bool] = deque(maxlen=2 * self.config.window)
        self._total = 0
        self._since = 0

    @property
    def total(self) -> int:
        """Episodes observed since the last reset."""
        return self._total

    @property
    def new_episodes(self) -> int:
        """Episodes observed since the last update (or reset)."""
        return self._total - self._since

    def observe(self, success: bool) -> None:
        """Record one episode's outcome."""
        self._tail.append(bool(success))
        self._total += 1

    def extend(self, successes: Iterable[bool]) -> None:
        for s in successes:
            self.observe(s)

    def check(self) -> TriggerDecision:
        """What :func:`decide` says about the history so far."""
        return _decide(list(self._tail), self._total - self._since, self.config)

    def mark_updated(self) -> None:
        """An update was made now: only later episodes count as new."""
        self._since = self._total

    def reset(self) -> None:
        """Forget everything (a new version became active)."""
        self._tail.clear()
        self._total = 0
        self._since = 0
