"""One evaluation call's seeds split across runtime workers, and the outcomes merged back.

:class:`~capevo.runtime.remote_evaluator.RemoteEvaluator` runs a call's episodes on every live runtime
worker of the task at once (issue 19, "Rollouts across runtime workers"). This module holds
the bookkeeping of that, without any Zenoh: :func:`split` decides which worker runs which
seeds, and a :class:`SeedLedger` tracks, for each position of the call's seed list, whether
its outcome is in, in flight on some worker, or back in the pool because its worker died or
refused. The transport (queries, liveliness, cancellation) lives in the worker module.

A *part* is the unit of work and of retry: the seeds one worker runs in one query. A worker
replies once per part, with all of its outcomes, so a part that dies takes all of its seeds
back to the pool, even episodes the dead worker had finished (they were never reported, so
nothing of them is counted).

Why it matters: version gating is a statistical evaluation on held-out tasks (paper §3.1,
"ECM Lifecycle"), and the paper's protocol spends 30 evaluation episodes per iteration (§4.1,
"Experimental Setup"). Those episodes are independent given their seeds, so they can run on
several machines at once without changing any result.

Why a deterministic split: capevo's gate pairs the active and the candidate set on the same
seeds (:mod:`capevo.runtime.gate`); a seed fixes the episode's instance whichever worker runs
it (:mod:`capevo.runtime.evaluator`, invariant 3), so the merged outcomes do not depend on the
split. Keeping the split a pure function of the worker set still makes a run reproducible down
to which worker's trace file holds which episode.

Invariants:
1. :func:`split` is a pure function of the indices and the *set* of worker ids (order and
   repeats ignored): ids sorted, contiguous runs of indices in order, sizes differing by at
   most one (the first workers get the larger runs); every index lands in exactly one part and
   no part is empty.
2. The ledger holds at most one outcome per index, the first one accepted; an outcome for an
   index already done is dropped and counted in :attr:`SeedLedger.dropped` (a worker thought
   dead that answers after all never makes a seed count twice).
3. An outcome is accepted for index i only if its ``seed`` is ``seeds[i]``, and a reply only if
   it has one outcome per seed of its part.
4. :meth:`SeedLedger.merged` returns exactly ``len(seeds)`` outcomes, the i-th for
   ``seeds[i]``, and only once every index is done.
5. A failed part sends its unfinished indices back to the pool; an index may be dispatched at
   most ``max_attempts`` times, after which :meth:`SeedLedger.dispatch` raises
   :class:`~capevo.errors.Unavailable` naming the seeds.
6. An index is never in flight on two parts at once.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from capevo.errors import CapevoError, Invalid, Unavailable
from capevo.runtime.evaluation import EpisodeOutcome

DEFAULT_MAX_ATTEMPTS = 3
"""Dispatches of one seed before a call gives up: the first, and two re-runs elsewhere."""


def split(indices: Sequence[int], workers: Iterable[str]) -> list[tuple[str, tuple[int, ...]]]:
    """Which worker runs which indices (invariant 1).

    Args:
        indices: Positions in the call's seed list, in the order they should run.
        workers: Worker ids; order and repeats do not matter.

    Returns:
        ``(worker_id, indices)`` pairs, by sorted worker id; with fewer indices than workers
        only the first ``len(indices)`` workers get a part.

    Raises:
        Invalid: no worker.
    """
    ids = sorted(set(workers))
    if not ids:
        raise Invalid("split: no worker to run the seeds on", details={"field": "workers"})
    items = tuple(indices)
    k = min(len(ids), len(items))
    if k == 0:
        return []
    size, extra = divmod(len(items), k)
    out = []
    start = 0
    for i, worker in enumerate(ids[:k]):
        n = size + (1 if i < extra else 0)
        out.append((worker, items[start : start + n]))
        start += n
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class Part:
    """Seeds one worker runs in one query."""

    part_id: int
    worker_id: str
    indices: tuple[int, ...]
    """Positions in the call's seed list."""
    seeds: tuple[int, ...]
    """``seeds[i]`` for each of :attr:`indices`: what the query asks for."""


class SeedLedger:
    """Where each seed of one call stands: done, in flight on a part, or waiting in the pool.

    Args:
        seeds: The call's seeds, in order (repeats allowed: positions are what is tracked).
        max_attempts: Dispatches of one position before the call gives up.

    Raises:
        Invalid: ``max_attempts`` below 1.
    """

    def __init__(self, seeds: Sequence[int], *, max_attempts: int = DEFAULT_MAX_ATTEMPTS) -> None:
        if isinstance(max_attempts, bool) or not isinstance(max_attempts, int) or max_attempts < 1:
            raise Invalid(
                f"max_attempts must be an integer >= 1, got {max_attempts!r}", details={"field": "max_attempts"}
            )
        self.seeds: tuple[int, ...] = tuple(seeds)
        self.max_attempts = max_attempts
        self._outcomes: list[EpisodeOutcome | None] = [None] * len(self.seeds)
        self._attempts = [0] * len(self.seeds)
        self._pool: list[int] = list(range(len(self.seeds)))
        self._parts: dict[int, Part] = {}
        self._all: dict[int, Part] = {}
        self._ids = itertools.count()
        self.dropped = 0
        """Outcomes received for positions already done, and dropped (invariant 2)."""
        self.failed_parts = 0
        """Parts that failed and sent their seeds back to the pool."""

    # --- state ------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return all(o is not None for o in self._outcomes)

    @property
    def pool(self) -> tuple[int, ...]:
        """Positions waiting to be dispatched, in order."""
        return tuple(sorted(self._pool))

    def in_flight(self, worker_id: str | None = None) -> list[Part]:
        """The parts still running (on ``worker_id`` only, when given), by part id."""
        return [p for _, p in sorted(self._parts.items()) if worker_id is None or p.worker_id == worker_id]

    def attempts(self, index: int) -> int:
        """How often position ``index`` has been dispatched."""
        return self._attempts[index]

    # --- transitions ------------------------------------------------------------------

    def dispatch(self, workers: Iterable[str]) -> list[Part]:
        """Split the pool across ``workers`` (see :func:`split`) and mark the parts in flight.

        Raises:
            Invalid: no worker (while the pool is not empty).
            Unavailable: a position in the pool has used up its attempts (invariant 5).
        """
        pool = sorted(self._pool)
        if not pool:
            return []
        spent = [i for i in pool if self._attempts[i] >= self.max_attempts]
        if spent:
            lost = [self.seeds[i] for i in spent]
            raise Unavailable(
                f"seeds {lost} were dispatched {self.max_attempts} times and every worker running them died or "
                "refused; giving up",
                details={"seeds": lost, "attempts": self.max_attempts},
            )
        parts = []
        for worker, indices in split(pool, workers):
            part = Part(
                part_id=next(self._ids),
                worker_id=worker,
                indices=indices,
                seeds=tuple(self.seeds[i] for i in indices),
            )
            for i in indices:
                self._attempts[i] += 1
            self._parts[part.part_id] = self._all[part.part_id] = part
            parts.append(part)
        self._pool = []
        return parts

    def complete(self, part_id: int, outcomes: Sequence[EpisodeOutcome]) -> int:
        """Record a part's reply; return how many positions it finished.

        A part no longer in flight (failed earlier, e.g. its worker was taken for dead) still
        fills positions nobody finished since, and drops the rest (invariant 2).

        Raises:
            CapevoError: the reply has the wrong number of outcomes or a wrong seed
                (invariant 3); the part is then failed, as if its worker had died.
            Invalid: an unknown part id.
        """
        part = self._all.get(part_id)
        if part is None:
            raise Invalid(f"unknown part {part_id}", details={"part_id": part_id})
        if len(outcomes) != len(part.indices) or any(o.seed != s for o, s in zip(outcomes, part.seeds, strict=False)):
            got = [o.seed for o in outcomes]
            self.fail(part_id)
            raise CapevoError(
                f"runtime worker {part.worker_id} returned outcomes for seeds {got}, asked for {list(part.seeds)}",
                details={"worker_id": part.worker_id},
            )
        self._parts.pop(part_id, None)
        new = 0
        for i, outcome in zip(part.indices, outcomes, strict=True):
            if self._outcomes[i] is None:
                self._outcomes[i] = outcome
                new += 1
                if i in self._pool:  # it had gone back to the pool: it is done now
                    self._pool.remove(i)
            else:
                self.dropped += 1
        return new

    def fail(self, part_id: int) -> tuple[int, ...]:
        """A part's worker died or refused: its unfinished positions go back to the pool.

        Returns:
            The positions returned to the pool (none when the part had already ended).
        """
        part = self._parts.pop(part_id, None)
        if part is None:
            return ()
        self.failed_parts += 1
        back = tuple(i for i in part.indices if self._outcomes[i] is None)
        self._pool.extend(back)
        return back

    def merged(self) -> list[EpisodeOutcome]:
        """Every outcome in seed order (invariant 4).

        Raises:
            Invalid: some positions are not done yet.
        """
        missing = [self.seeds[i] for i, o in enumerate(self._outcomes) if o is None]
        if missing:
            raise Invalid(f"merge: seeds {missing} have no outcome yet", details={"seeds": missing})
        return [o for o in self._outcomes if o is not None]
