"""The trace writer's queue (capevo.runtime.traces.queue invariants 1-5), C and Python alike."""

from __future__ import annotations

import threading
import time
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
CALL = (0, 1, "reach", 1, (), None, 0.0, "ok", None)


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
    with pytest.raises(Invalid, match="write_env_step_row takes a tuple of 12 fields, got a tuple of 9"):
        q.step(CALL)
    with pytest.raises(Invalid, match="write_invocation_row takes a tuple of 9 fields, got a list"):
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


def test_the_c_queue_needs_its_init() -> None:
    assert trace_queue.NativeQueue is not None
    bare = trace_queue.NativeQueue.__new__(trace_queue.NativeQueue)
    with pytest.raises(RuntimeError, match="__init__ was not called"):
        bare.take()
    with pytest.raises(ValueError, match="batch must be positive"):
        trace_queue.NativeQueue(step_channel=1, call_channel=2, batch=0, on_full=print, refuse=print, check_row=print)
