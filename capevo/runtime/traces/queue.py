"""The trace writer's queue: records and rows kept in write order until the writer encodes them.

The episode loop calls the writer between two robosuite steps, with every CPU cache cold, where
each Python statement costs several times what it costs warm; so an append is one call of the
C queue (``csrc/queue.c``) where it is built: it stamps the wall-clock time, keeps the entry
and calls the writer back when the batch is full or a timed flush is due.
:class:`PythonQueue` is its specification and its stand-in where the C part is not built.

Invariants:
1. ``take()`` returns every entry kept since the last ``take()``, oldest first, each as
   ``(channel id, encode function or None for a row, record or row, wall-clock ns)``.
2. An append and a ``take()`` from another thread never lose or duplicate an entry.
3. After an append that makes the queue hold ``batch`` entries, or that finds the monotonic
   clock at or past ``deadline_ns`` (when not 0), the queue calls ``on_full()`` and passes on
   what it raises.
4. While ``closed`` is set, an append keeps nothing and calls ``refuse(method)``, which raises.
5. A row that is not a tuple of its length is passed to ``check_row(row, length, method)``,
   which raises, and is not kept.
6. ``wait_due(interval_ns, grace_ns)`` returns True once entries are kept or ``dirty`` is set and
   the monotonic clock is at or past ``flushed_ns + interval_ns + grace_ns``, False once ``stop()``
   was called; the C queue waits without the GIL (the writer's flush thread: in a busy loop its
   wakes find the writer flushed and never take the GIL).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from capevo.runtime.traces.native import NATIVE
from capevo.runtime.traces.rows import ENV_STEP_ROW_LEN, INVOCATION_ROW_LEN

Entry = tuple[int, Callable[[Any], bytes] | None, Any, int]


class Queue(Protocol):
    closed: bool
    deadline_ns: int
    flushed_ns: int
    dirty: bool

    def step(self, row: Any) -> None: ...

    def call(self, row: Any) -> None: ...

    def record(self, channel: int, encode: Callable[[Any], bytes], record: Any, method: str) -> None: ...

    def take(self) -> list[Entry]: ...

    def wait_due(self, interval_ns: int, grace_ns: int) -> bool: ...

    def stop(self) -> None: ...

    def __len__(self) -> int: ...


class PythonQueue:
    """The queue in Python (see the module docstring); a lock makes appends atomic."""

    def __init__(
        self,
        *,
        step_channel: int,
        call_channel: int,
        batch: int,
        on_full: Callable[[], None],
        refuse: Callable[[str], None],
        check_row: Callable[[Any, int, str], None],
    ) -> None:
        self._entries: list[Entry] = []
        self._lock = threading.Lock()
        self._step_channel, self._call_channel = step_channel, call_channel
        self._batch = batch
        self._on_full, self._refuse, self._check_row = on_full, refuse, check_row
        self.closed = False
        self.deadline_ns = 0
        self.flushed_ns = 0
        self.dirty = False
        self._stopping = False
        self._wake = threading.Condition(threading.Lock())

    def _keep(self, channel: int, encode: Callable[[Any], bytes] | None, item: Any, method: str) -> None:
        if self.closed:
            self._refuse(method)
            raise RuntimeError(f"{method}: the trace writer is closed")
        with self._lock:
            self._entries.append((channel, encode, item, time.time_ns()))
            kept = len(self._entries)
        if kept >= self._batch or (self.deadline_ns and time.monotonic_ns() >= self.deadline_ns):
            self._on_full()

    def _keep_row(self, row: Any, length: int, channel: int, method: str) -> None:
        if type(row) is not tuple or len(row) != length:
            self._check_row(row, length, method)
            raise TypeError(f"{method} takes a tuple of {length} fields")
        self._keep(channel, None, row, method)

    def step(self, row: Any) -> None:
        self._keep_row(row, ENV_STEP_ROW_LEN, self._step_channel, "write_env_step_row")

    def call(self, row: Any) -> None:
        self._keep_row(row, INVOCATION_ROW_LEN, self._call_channel, "write_invocation_row")

    def record(self, channel: int, encode: Callable[[Any], bytes], record: Any, method: str) -> None:
        self._keep(channel, encode, record, method)

    def take(self) -> list[Entry]:
        with self._lock:
            taken, self._entries = self._entries, []
        return taken

    def wait_due(self, interval_ns: int, grace_ns: int) -> bool:
        if interval_ns <= 0 or grace_ns < 0:
            raise ValueError("interval_ns must be positive and grace_ns not negative")
        with self._wake:
            while not self._stopping:
                now = time.monotonic_ns()
                if self._entries or self.dirty:
                    at = self.flushed_ns + interval_ns + grace_ns
                    if now >= at:
                        return True
                else:
                    at = now + interval_ns  # nothing waits: look again an interval on
                self._wake.wait((at - now) / 1e9)
            return False

    def stop(self) -> None:
        with self._wake:
            self._stopping = True
            self._wake.notify_all()

    def __len__(self) -> int:
        return len(self._entries)


NativeQueue = None if NATIVE is None else NATIVE.Queue


def make_queue(*, native: bool = True, **kwargs: Any) -> Queue:
    """The C queue where it is built and ``native`` is true, else a :class:`PythonQueue`."""
    if native and NativeQueue is not None:
        return NativeQueue(**kwargs)  # type: ignore[no-any-return]
    return PythonQueue(**kwargs)
