"""One forced refresh of robosuite's observables in dependency order.

robosuite computes some observables from others through its observation cache
(``Can_to_robot0_eef_pos`` reads ``Can_pos`` and the gripper pose; peg_in_hole's ``t`` reads
what ``angle`` wrote), and its dict order does not always put the producer first: one
forced pass in dict order leaves such observables computed from the previous values, which
is why :meth:`TaskEnv._raw_observations` runs two. :func:`plan_observables` learns who reads
what by running each sensor once against a recording copy of the cache, then orders the
enabled observables so that every reader comes after its producers; one forced pass in that
order gives exactly the two-pass values.

Invariants:
1. In ``plan.order`` every enabled observable comes after each enabled observable that
   produces (is named, or writes as a side effect) a cache key its sensor reads; ties keep
   robosuite's order.
2. ``plan.active`` lists the enabled and active observables in robosuite's order: the keys,
   in order, of robosuite's ``_get_observations()`` without the ``*-state`` concatenations.
3. A dependency cycle (none in robosuite's tasks) yields no plan: the caller keeps the
   two-pass refresh.
4. Planning leaves the environment's cache and every observable's state as they were.
"""

from __future__ import annotations

import heapq
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True, slots=True, kw_only=True)
class ObservablePlan:
    """The order of one forced pass over a robosuite environment's observables.

    Attributes:
        source: The environment's observable dict the plan was made from (a rebuilt dict,
            e.g. after a hard reset, means the plan is stale).
        order: Enabled observables, producers before readers.
        active: ``(name, observable)`` of the enabled and active ones, in robosuite's order.
    """

    source: Mapping[str, Any]
    order: tuple[Any, ...]
    active: tuple[tuple[str, Any], ...]


class _RecordingCache(dict[str, Any]):
    """A copy of the observation cache that notes every key read or written."""

    def __init__(self, base: Mapping[str, Any]) -> None:
        super().__init__(base)
        self.reads: set[str] = set()
        self.writes: set[str] = set()

    def __getitem__(self, key: str) -> Any:
        self.reads.add(key)
        return super().__getitem__(key)

    def __contains__(self, key: object) -> bool:
        if isinstance(key, str):
            self.reads.add(key)
        return super().__contains__(key)

    def get(self, key: str, default: Any = None) -> Any:
        self.reads.add(key)
        return super().get(key, default)

    def __setitem__(self, key: str, value: Any) -> None:
        self.writes.add(key)
        super().__setitem__(key, value)


def plan_observables(env: Any) -> ObservablePlan | None:
    """Order ``env``'s enabled observables for a single forced refresh.

    Call it when the cache is full (after a forced refresh): a sensor that finds a key
    missing may skip reading the others, hiding a dependency.

    Args:
        env: A robosuite environment (``_observables``, ``_obs_cache``).

    Returns:
        The plan, or None when the dependencies form a cycle.
    """
    source = env._observables
    enabled = [(name, o) for name, o in source.items() if o.is_enabled()]
    reads: list[set[str]] = []
    producer: dict[str, int] = {}
    for i, (name, observable) in enumerate(enabled):
        probe = _RecordingCache(env._obs_cache)
        observable._sensor(probe)
        reads.append(probe.reads)
        for key in (name, *sorted(probe.writes)):
            producer.setdefault(key, i)
    n = len(enabled)
    after: list[list[int]] = [[] for _ in range(n)]
    waiting = [0] * n
    for i, keys in enumerate(reads):
        for p in {producer[k] for k in keys if k in producer} - {i}:
            after[p].append(i)
            waiting[i] += 1
    ready = [i for i in range(n) if waiting[i] == 0]
    heapq.heapify(ready)
    order: list[int] = []
    while ready:
        i = heapq.heappop(ready)
        order.append(i)
        for j in after[i]:
            waiting[j] -= 1
            if waiting[j] == 0:
                heapq.heappush(ready, j)
    if len(order) != n:
        return None
    return ObservablePlan(
        source=source,
        order=tuple(enabled[i][1] for i in order),
        active=tuple((name, o) for name, o in enabled if o.is_active()),
    )
