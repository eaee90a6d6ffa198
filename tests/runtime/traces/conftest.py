"""Fixtures of the trace tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from capevo.runtime.traces import codec, writer
from capevo.runtime.traces import queue as trace_queue


@pytest.fixture(params=["c", "python"])
def writer_parts(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """Run the test with the writer's C parts (queue, row splicer, framing), then with their Python
    versions in their place, as in a source tree nobody built."""
    if request.param == "python":
        monkeypatch.setattr(trace_queue, "NativeQueue", None)
        monkeypatch.setattr(codec, "_native", None)
        monkeypatch.setattr(writer, "NATIVE", None)
    else:
        assert trace_queue.NativeQueue is not None and codec.rows_kernel_available(), "C parts not built"
    yield request.param
