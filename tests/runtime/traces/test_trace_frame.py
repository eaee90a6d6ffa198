"""The writer's C batch framer (csrc/frame.c) against its specification, the writer's Python path
(RecordEncoder.rows_in_python, then McapFileWriter.add_messages): the same chunk bytes, index,
sequences and dropped entries."""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from _trace_helpers import make_metadata, one_of_each
from hypothesis import given
from hypothesis import strategies as st
from test_trace_rows import batches

from capevo.errors import Invalid
from capevo.runtime.traces import EcmInvocation, EnvStep, PlanStep, TraceWriter
from capevo.runtime.traces.native import NATIVE

PLAN = one_of_each(0)[0]


def refuse(record: Any) -> bytes:
    raise Invalid(f"refused {type(record).__name__}")


@contextmanager
def open_writer(native: bool) -> Iterator[TraceWriter]:
    with tempfile.TemporaryDirectory() as folder:
        w = TraceWriter(Path(folder) / "t.mcap", make_metadata(), batch=10_000, background_flush=False, native=native)
        try:
            yield w
        finally:
            w.close()


def pending_for(w: TraceWriter, specs: list[tuple[str, Any, int]]) -> list[tuple[int, Any, Any, int]]:
    """The queue's entries for ``specs``: rows, plan steps (the writer's encoder), refused records."""
    channels = w._channels
    out: list[tuple[int, Any, Any, int]] = []
    for kind, item, now in specs:
        if kind == "step":
            out.append((channels[EnvStep.TOPIC], None, item, now))
        elif kind == "call":
            out.append((channels[EcmInvocation.TOPIC], None, item, now))
        else:
            out.append((channels[PlanStep.TOPIC], w._encoder.encode if kind == "plan" else refuse, item, now))
    return out


def framed(native: bool, specs: list[tuple[str, Any, int]], first_sequence: int) -> tuple[Any, ...]:
    with open_writer(native) as w:
        w._sequences[:] = [first_sequence] * len(w._sequences)
        frame = w._frame_natively if native else w._frame_in_python
        failed = frame(pending_for(w, specs))
        mcap = w._mcap
        state = (
            bytes(mcap._chunk),
            {k: bytes(v) for k, v in mcap._index.items()},
            list(w._sequences),
            mcap.messages,
            (mcap._chunk_start, mcap._chunk_end),
            None if failed is None else (type(failed), failed.message),
        )
        w._mcap._new_chunk()
    return state


def test_the_c_framer_is_built() -> None:
    assert NATIVE is not None and hasattr(NATIVE, "frame_batch"), "the C parts are not built"


@given(
    rows=batches(),
    records=st.lists(st.sampled_from(["plan", "refused"]), max_size=3),
    times=st.lists(st.integers(0, 2**64 - 1), min_size=12, max_size=12),
    first_sequence=st.sampled_from([0, 7, 2**32 - 2]),
    data=st.data(),
)
def test_the_c_framer_frames_what_the_python_path_frames(
    rows: list[tuple[bool, tuple[Any, ...]]],
    records: list[str],
    times: list[int],
    first_sequence: int,
    data: st.DataObject,
) -> None:
    specs: list[tuple[str, Any, int]] = [("step" if s else "call", row, 0) for s, row in rows]
    for kind in records:
        specs.insert(data.draw(st.integers(0, len(specs))), (kind, PLAN, 0))
    specs = [(kind, item, times[i % len(times)]) for i, (kind, item, _) in enumerate(specs)]
    assert framed(True, specs, first_sequence) == framed(False, specs, first_sequence)


def test_a_batch_the_framer_cannot_take_changes_nothing() -> None:
    assert NATIVE is not None, "the C parts are not built"
    good = (1, None, "not a row", 5)
    for bad, error in (
        ([good, (1, 2, 3)], TypeError),
        ([good, (99, None, (), 5)], ValueError),  # a channel without a sequence
        ([good, (1, None, (), -5)], OverflowError),
    ):
        chunk, index, sequences = bytearray(b"head"), {}, [0, 3, 4]
        with pytest.raises(error):
            NATIVE.frame_batch(chunk, index, bad, 1, sequences, str.encode, lambda e: b"{}")
        assert (chunk, index, sequences) == (bytearray(b"head"), {}, [0, 3, 4])


def test_a_fallback_that_raises_changes_nothing() -> None:
    assert NATIVE is not None, "the C parts are not built"

    def fallback(entry: tuple[Any, ...]) -> bytes:
        if entry[2] == "boom":
            raise RuntimeError("boom")
        return b"{}"

    chunk, index, sequences = bytearray(), {}, [0, 0]
    pending = [(1, refuse, "fine", 1), (1, refuse, "boom", 2)]
    with pytest.raises(RuntimeError, match="boom"):
        NATIVE.frame_batch(chunk, index, pending, 1, sequences, str.encode, fallback)
    assert (chunk, index, sequences) == (bytearray(), {}, [0, 0])


def test_dropped_entries_take_no_sequence_and_the_first_invalid_is_returned() -> None:
    assert NATIVE is not None, "the C parts are not built"
    invalids = iter([Invalid("first"), Invalid("second")])
    payloads: dict[str, Callable[[], Any]] = {"a": lambda: b'{"a":1}', "x": lambda: next(invalids)}
    pending = [(1, refuse, key, t) for t, key in enumerate("axaxa", start=10)]
    chunk, index, sequences = bytearray(), {}, [0, 5]
    count, first, last, failure = NATIVE.frame_batch(
        chunk, index, pending, 9, sequences, str.encode, lambda e: payloads[e[2]]()
    )
    assert (count, first, last, failure.message) == (3, 10, 14, "first")
    assert sequences == [0, 8]
    assert len(index[1]) == 3 * 16 and len(chunk) == 3 * (31 + 7)


def test_the_c_framer_takes_the_c_queues_entries_as_take_gives_them() -> None:
    # The writer hands frame_batch its C queue (no tuple per entry): the same chunk, index and
    # sequences as the list take() gives, at the times the queue stamped, and the queue is empty.
    import struct

    import numpy as np

    from capevo.runtime.state import ArmState
    from capevo.runtime.traces import Outcome

    obs = np.arange(46, dtype=np.float32) / 7
    obs.flags.writeable = False
    arm = ArmState(eef_pos=(0.1, 0.2, 0.9), eef_force=(0.0, -1.5, 3.25))
    step = (0, 1, "pick.reach", 0, obs, (0.5, -1.0), 0.1, obs, False, False, False, (arm,))
    call = (0, 1, "pick.reach", 0, obs, tuple(range(21, 30)), (0.5, -1.0), 0.001, Outcome.OK, None)
    with open_writer(True) as queued, open_writer(True) as listed:
        q, channels = queued._queue, queued._channels
        specs: list[tuple[int, Any, Any]] = []
        for i in range(40):
            q.call(call)
            q.step(step)
            specs += [(channels[EcmInvocation.TOPIC], None, call), (channels[EnvStep.TOPIC], None, step)]
            if i % 9 == 0:
                q.record(channels[PlanStep.TOPIC], queued._encoder.encode, PLAN, "write_plan_step")
                specs.append((channels[PlanStep.TOPIC], listed._encoder.encode, PLAN))
        assert queued._frame_natively() is None and len(q) == 0
        chunk = bytes(queued._mcap._chunk)
        times, at = [], 0
        while at < len(chunk):  # each Message record's log time, in order
            length, log_time = struct.unpack_from("<Q", chunk, at + 1)[0], struct.unpack_from("<Q", chunk, at + 15)[0]
            times.append(log_time)
            at += 9 + length
        assert len(times) == len(specs)
        assert listed._frame_natively([(*spec, t) for spec, t in zip(specs, times, strict=True)]) is None
        assert chunk == bytes(listed._mcap._chunk)
        assert {k: bytes(v) for k, v in queued._mcap._index.items()} == {
            k: bytes(v) for k, v in listed._mcap._index.items()
        }
        assert queued._sequences == listed._sequences
        for w in (queued, listed):
            w._mcap._new_chunk()
