"""The trace writer's queue (capevo.runtime.traces.queue invariants 1-6), C and Python alike."""

from __future__ import annotations

import gc
import threading
import time
import weakref
from typing import Any

import pytest

from capevo.errors import Conflict, Invalid
from capevo.runtime.traces import queue as trace_queue
from capevo.runtime.traces.rows import check_row

KINDS = ["c", "python"]


class Calls:
    """The writer's side of a queue: counts callbacks, raises where told to."""

    def __init__(self) -> None:
        self.full = 0
        self.refused: list[str] = []
        self.fail_on_full: Exception | None = None

    def on_full(self) -> None:
        self.full += 1
        if self.fail_on_full is not None:
            raise self.fail_on_full

    def refuse(self, method: str) -> None:
        self.refused.append(method)
        raise Conflict(f"closed; cannot {method}")


def make(kind: str, calls: Calls, batch: int = 100) -> Any:
    cls = trace_queue.NativeQueue if kind == "c" else trace_queue.PythonQueue
    assert cls is not None, "the C queue is not built"
    return cls(
        step_channel=4, call_channel=2, batch=batch, on_full=calls.on_full, refuse=calls.refuse, check_row=check_row
    )


STEP = (0, 1, "reach", 1, (), (), 0.0, (), False, False, False, ())
CALL = (0, 1, "reach", 1, (), None, None, 0.0, "ok", None)


def encode(record: object) -> bytes:
    return b"{}"


@pytest.mark.parametrize("kind", KINDS)
def test_take_returns_every_entry_in_order_with_its_wall_clock_time(kind: str) -> None:
    calls = Calls()
    q = make(kind, calls)
    before = time.time_ns()
    q.step(STEP)
    q.record(1, encode, "plan", "write_plan_step")
    q.call(CALL)
    after = time.time_ns()
    assert len(q) == 3
    taken = q.take()
    assert [(c, e, item) for c, e, item, _ in taken] == [(4, None, STEP), (1, encode, "plan"), (2, None, CALL)]
    times = [t for *_, t in taken]
    assert before <= times[0] <= times[1] <= times[2] <= after
    assert q.take() == [] and len(q) == 0
    assert calls.full == 0


@pytest.mark.parametrize("kind", KINDS)
def test_a_full_batch_or_a_due_deadline_calls_the_writer_back(kind: str) -> None:
    calls = Calls()
    q = make(kind, calls, batch=3)
    q.step(STEP)
    q.step(STEP)
    assert calls.full == 0
    q.step(STEP)
    assert calls.full == 1  # the queue does not take: the writer does, in on_full
    q.take()
    q.deadline_ns = time.monotonic_ns() + 3_600 * 10**9
    q.call(CALL)
    assert calls.full == 1
    q.deadline_ns = 1
    q.call(CALL)
    assert calls.full == 2
    q.deadline_ns = 0  # never
    q.take()
    q.call(CALL)
    assert calls.full == 2


@pytest.mark.parametrize("kind", KINDS)
def test_what_the_callback_raises_reaches_the_writer_and_the_entry_is_kept(kind: str) -> None:
    calls = Calls()
    q = make(kind, calls, batch=1)
    calls.fail_on_full = Invalid("a kept record does not encode")
    with pytest.raises(Invalid, match="does not encode"):
        q.step(STEP)
    assert len(q) == 1


@pytest.mark.parametrize("kind", KINDS)
def test_a_closed_queue_keeps_nothing_and_asks_why(kind: str) -> None:
    calls = Calls()
    q = make(kind, calls)
    q.closed = True
    for append in (lambda: q.step(STEP), lambda: q.call(CALL), lambda: q.record(1, encode, "x", "write_plan_step")):
        with pytest.raises(Conflict):
            append()
    assert calls.refused == ["write_env_step_row", "write_invocation_row", "write_plan_step"]
    assert len(q) == 0 and q.closed


@pytest.mark.parametrize("kind", KINDS)
def test_a_row_of_the_wrong_shape_is_refused_by_check_row(kind: str) -> None:
    q = make(kind, Calls())
    with pytest.raises(Invalid, match="write_env_step_row takes a tuple of 12 fields, got a tuple of 10"):
        q.step(CALL)
    with pytest.raises(Invalid, match="write_invocation_row takes a tuple of 10 fields, got a list"):
        q.call(list(CALL))
    assert len(q) == 0


@pytest.mark.parametrize("kind", KINDS)
def test_appends_and_takes_from_two_threads_lose_and_duplicate_nothing(kind: str) -> None:
    q = make(kind, Calls(), batch=10**9)
    n = 20_000
    taken: list[Any] = []
    done = threading.Event()

    def consume() -> None:
        while not done.is_set():
            taken.extend(q.take())
        taken.extend(q.take())

    consumer = threading.Thread(target=consume)
    consumer.start()
    for i in range(n):
        q.record(1, encode, i, "write_plan_step")
    done.set()
    consumer.join()
    assert [item for _, _, item, _ in taken] == list(range(n))


@pytest.mark.parametrize("kind", KINDS)
def test_entries_past_any_initial_capacity_keep_their_order_and_kinds(kind: str) -> None:
    q = make(kind, Calls(), batch=10**9)
    kinds = [i % 3 for i in range(1000)]
    for i, k in enumerate(kinds):
        if k == 0:
            q.step(STEP)
        elif k == 1:
            q.call(CALL)
        else:
            q.record(1, encode, i, "write_plan_step")
    assert len(q) == 1000
    want = [(4, None, STEP), (2, None, CALL)]
    assert [(c, e, item) for c, e, item, _ in q.take()] == [
        want[k] if k < 2 else (1, encode, i) for i, k in enumerate(kinds)
    ]


class AppendsWhenCollected:
    """A record in a reference cycle that appends to the queue from its finalizer."""

    def __init__(self, q: Any, appended: list[str]) -> None:
        self.q, self.appended, self.me = q, appended, self

    def __del__(self) -> None:
        self.q.record(1, encode, "from a finalizer", "write_plan_step")
        self.appended.append("from a finalizer")


@pytest.mark.parametrize("kind", KINDS)
def test_a_kept_cycle_is_collected_after_take_and_what_its_finalizer_appends_is_kept(kind: str) -> None:
    q = make(kind, Calls(), batch=10**9)
    appended: list[str] = []
    record = AppendsWhenCollected(q, appended)
    alive = weakref.ref(record)
    q.record(1, encode, record, "write_plan_step")
    del record
    gc.collect()
    assert alive() is not None  # the queue holds it (and tells the collector so)
    (entry,) = q.take()
    del entry
    gc.collect()
    assert alive() is None and appended == ["from a finalizer"]
    assert [item for _, _, item, _ in q.take()] == ["from a finalizer"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_cycle_through_kept_entries_is_collected(kind: str) -> None:
    class Holder:
        q: Any = None

    holder = Holder()
    q = make(kind, Calls(), batch=10**9)
    holder.q = q
    q.record(1, encode, holder, "write_plan_step")
    q.step((*STEP[:-1], (holder,)))
    alive = weakref.ref(holder)
    del holder, q
    gc.collect()
    assert alive() is None


def test_the_c_queue_needs_its_init() -> None:
    assert trace_queue.NativeQueue is not None
    bare = trace_queue.NativeQueue.__new__(trace_queue.NativeQueue)
    with pytest.raises(RuntimeError, match="__init__ was not called"):
        bare.take()
    with pytest.raises(ValueError, match="batch must be positive"):
        trace_queue.NativeQueue(step_channel=1, call_channel=2, batch=0, on_full=print, refuse=print, check_row=print)


MS = 1_000_000


def in_thread(fn: Any) -> tuple[threading.Thread, list[Any]]:
    out: list[Any] = []
    thread = threading.Thread(target=lambda: out.append(fn()))
    thread.start()
    return thread, out


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("waiting", ["entry", "dirty chunk"])
def test_wait_due_returns_true_once_what_waits_is_a_grace_past_due(kind: str, waiting: str) -> None:
    q = make(kind, Calls())
    q.flushed_ns = time.monotonic_ns()
    if waiting == "entry":
        q.record(1, encode, "plan", "write_plan_step")
    else:
        q.dirty = True
    assert q.wait_due(60 * MS, 20 * MS) is True
    # Invariant 6: never before the flush is due plus the grace (the monotonic clock cannot lie).
    assert time.monotonic_ns() >= q.flushed_ns + 80 * MS
    # Already due: at once, every time, until the writer flushes.
    assert q.wait_due(60 * MS, 20 * MS) is True


@pytest.mark.parametrize("kind", KINDS)
def test_wait_due_sleeps_while_nothing_waits_and_stop_ends_it(kind: str) -> None:
    q = make(kind, Calls())
    q.flushed_ns = 0  # long ago: anything kept would be due at once
    thread, out = in_thread(lambda: q.wait_due(20 * MS, 5 * MS))
    # It looks again every interval and finds nothing; meanwhile this thread runs (no GIL held).
    spins = 0
    end = time.monotonic() + 0.15
    while time.monotonic() < end:
        spins += 1
    assert thread.is_alive() and spins > 1000
    q.stop()
    thread.join(timeout=10)
    assert out == [False]
    assert q.wait_due(20 * MS, 5 * MS) is False  # stopped for good


@pytest.mark.parametrize("kind", KINDS)
def test_wait_due_notices_what_comes_to_wait_and_a_flush_that_moves_the_due_time(kind: str) -> None:
    q = make(kind, Calls())
    q.flushed_ns = time.monotonic_ns()
    thread, out = in_thread(lambda: q.wait_due(200 * MS, 10 * MS))
    time.sleep(0.03)
    q.record(1, encode, "plan", "write_plan_step")  # something waits now
    time.sleep(0.02)
    moved = q.flushed_ns = time.monotonic_ns()  # the writer flushed: due again only 210 ms on
    thread.join(timeout=10)
    assert out == [True] and time.monotonic_ns() >= moved + 210 * MS


@pytest.mark.parametrize("kind", KINDS)
def test_wait_due_refuses_a_bad_interval(kind: str) -> None:
    q = make(kind, Calls())
    for interval, grace in ((0, 1), (-5, 1), (10, -1)):
        with pytest.raises(ValueError, match="interval_ns must be positive"):
            q.wait_due(interval, grace)
