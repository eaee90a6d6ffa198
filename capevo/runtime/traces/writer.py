"""TraceWriter: the MCAP file of one run, crash-safe to about the last second.

Layout (see :mod:`capevo.runtime.traces.mcapfile`): the MCAP magic and header, the
metadata records (``capevo.run``, ``capevo.packages``), the five JSON-schema schemas and
channels, then compressed chunks of messages; ``close()`` writes the summary (schemas,
channels, statistics, chunk and metadata indexes) and the footer, so Foxglove and the
``mcap`` tools open the file directly. Everything before the first chunk reaches the OS in
the constructor, so even a worker killed at once leaves a file naming its run.

Batching: with ``batch > 1`` records are kept as they are written and encoded and framed
``batch`` at a time, back to back. Inside an episode loop every robosuite step between two
writes evicts the encoder from the CPU caches, so encoding a record where it is written costs
several times what it costs warm (benchmarks/bench_traces_loop.py). A kept record is as safe as
one in the open chunk: both reach the OS at the next flush. The runtime's writers use
:data:`RUNTIME_BATCH`; the default, 1, encodes each record at once.

The hot path is C where it is built (``csrc/``, :mod:`capevo.runtime.traces.queue`): the episode
loop's ``write_env_step_row``/``write_invocation_row`` are the queue's own append (the wall-clock
stamp, the entry, the batch and deadline checks, one call), and a batch is encoded and framed
into the open chunk in one C call (``csrc/frame.c``: rows spliced as
:meth:`~capevo.runtime.traces.codec.RecordEncoder.rows` splices them, other records through
their encode functions, no Python object per message). ``native=False``, or a source tree
nobody built, runs their Python versions: the same file.

Crash safety: a chunk is finished and handed to the OS when it reaches ``chunk_size`` bytes
and at least every ``flush_interval_s`` seconds while it holds data, checked on every write
and by a background thread (so an idle worker's last records reach the file too). Data the
OS has survives the writer being killed with SIGKILL; ``fsync_on_flush=True`` also survives
power loss at the cost of a disk sync per flush. :func:`capevo.runtime.traces.recover`
turns the unfinished file of a killed worker into a finished one.

Invariants:
1. Header, metadata, schemas and channels are in the OS before the constructor returns.
2. A record written at time t is in the OS by t + ``flush_interval_s`` (+ one background
   tick, a quarter of the interval) or at the next ``flush()``, whichever is first, as
   long as the process lives; after ``flush()`` returns, every record written before it is.
3. ``close()`` is idempotent, leaves a finished MCAP (summary, footer, closing magic) and
   stops the background thread; writes after it raise :class:`Conflict`.
4. Each ``write_*`` method accepts only its record type, or for ``write_*_row`` a tuple of
   its row's length (:class:`Invalid` otherwise, at once), and writes it to its own topic;
   messages get the wall-clock time of the write call as log and publish time and a
   per-channel sequence number starting at 0, in write order. A row's message is its
   record's (:meth:`~capevo.runtime.traces.codec.RecordEncoder.rows`). A record or row whose
   fields do not encode is dropped with :class:`Invalid`: with ``batch=1`` raised by its own
   write call; otherwise by the call that encodes its batch (a later write, ``flush()`` or
   ``close()``, the next of them if the background thread did), after every other record of
   the batch is written.
5. An existing file is never overwritten unless ``overwrite=True`` (:class:`Conflict`).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import LIBRARY_IDENTIFIER

from capevo.errors import CapevoError, Conflict, Invalid, Unavailable
from capevo.runtime.traces import codec
from capevo.runtime.traces.mcapfile import McapFileWriter
from capevo.runtime.traces.native import NATIVE
from capevo.runtime.traces.queue import Entry, make_queue
from capevo.runtime.traces.records import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    Intervention,
    PlanStep,
    TraceMetadata,
    record_type,
    topics,
)
from capevo.runtime.traces.rows import (
    EnvStepRow,
    InvocationRow,
    check_row,
)
from capevo.runtime.traces.sink import check_record

COMPRESSIONS: Mapping[str, str] = {"lz4": "lz4", "zstd": "zstd", "none": ""}
"""Chunk compression by name -> MCAP compression string. lz4 is the default: zstd costs
several µs more per env step, amortised (see benchmarks/bench_traces.py); ``none`` saves lz4's
share of the per-step cost (a fifth to a quarter of it for T6) for files about three times larger
(benchmarks/bench_traces_loop.py ``--compressions lz4 none``)."""
DEFAULT_COMPRESSION = "lz4"


def check_compression(name: object) -> str:
    """``name`` if it is one of :data:`COMPRESSIONS`.

    Raises:
        Invalid: anything else (field ``compression``).
    """
    if not isinstance(name, str) or name not in COMPRESSIONS:
        raise Invalid(
            f"unknown trace compression {name!r}; valid: {', '.join(COMPRESSIONS)}",
            details={"field": "compression"},
        )
    return name


DEFAULT_CHUNK_SIZE = 256 * 1024
DEFAULT_FLUSH_INTERVAL_S = 1.0
RUNTIME_BATCH = 1024
"""Records the runtime's writers (worker, evaluator) keep before encoding them: more than one flush
interval brings at the speeds the runtime reaches (about 400 a second at 200 env steps/s, an
invocation per step), so they encode once per flush, at its deadline (and at each episode's
end). Each batch pays the cold caches once, so fewer batches cost less: T1 64 -> 1024, 30.0 ->
24.2 µs per step in one alternating run (benchmarks/bench_traces_loop.py); the bound caps the
memory a long flush interval could keep (about a MiB)."""

_SEQUENCE_MOD = 2**32


def _library() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("capevo")
    except PackageNotFoundError:  # pragma: no cover - source checkout without install
        ours = "0"
    return f"capevo/{ours}; {LIBRARY_IDENTIFIER}"


class TraceWriter:
    """Write one run's trace to an MCAP file; a :class:`~capevo.runtime.traces.sink.TraceSink`.

    Use as a context manager; leaving the block (normally or by an exception) finishes the
    file.

    Args:
        path: File to create; parent directories are created.
        metadata: Run metadata, written as MCAP metadata records at the start.
        chunk_size: Finish a chunk once it holds this many bytes (uncompressed).
        flush_interval_s: Finish a chunk at least this often while it holds data.
        compression: ``"lz4"`` (default), ``"zstd"`` or ``"none"``.
        fsync_on_flush: Also fsync at every flush (power-loss safety; slower).
        background_flush: Run the thread that flushes while no writes arrive.
        overwrite: Replace an existing file instead of raising :class:`Conflict`.
        batch: Encode records this many at a time (see the module docstring); 1: each at once.
        native: Keep records in the C queue and encode and frame batches in C where they are
            built (False: their Python versions, to compare).

    Raises:
        Invalid: bad chunk size, interval, compression name or batch.
        Conflict: ``path`` exists and ``overwrite`` is false.
        Unavailable: the file cannot be created (OS error, with the reason).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        metadata: TraceMetadata,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        compression: str = DEFAULT_COMPRESSION,
        fsync_on_flush: bool = False,
        background_flush: bool = True,
        overwrite: bool = False,
        batch: int = 1,
        native: bool = True,
    ) -> None:
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
            raise Invalid(f"chunk_size must be a positive integer, got {chunk_size!r}", details={"field": "chunk_size"})
        if not isinstance(flush_interval_s, int | float) or not flush_interval_s > 0:
            raise Invalid(
                f"flush_interval_s must be a positive number, got {flush_interval_s!r}",
                details={"field": "flush_interval_s"},
            )
        if isinstance(batch, bool) or not isinstance(batch, int) or batch <= 0:
            raise Invalid(f"batch must be a positive integer, got {batch!r}", details={"field": "batch"})
        check_compression(compression)
        if not isinstance(metadata, TraceMetadata):
            raise Invalid("metadata must be a TraceMetadata", details={"field": "metadata"})
        self.path = Path(path)
        self.metadata = metadata
        self.flush_interval_s = float(flush_interval_s)
        self.fsync_on_flush = fsync_on_flush
        self._lock = threading.Lock()
        self._closed = False
        self._error: CapevoError | None = None
        self._messages = 0
        self._flushes = 0
        self._encoder = codec.RecordEncoder(kernel=native)
        self._frame_batch = NATIVE.frame_batch if native and NATIVE is not None else None
        self.batch = batch
        # A kept record that failed to encode in the background thread, for the owner's next call.
        self._undelivered: Invalid | None = None
        self._file = self._open(self.path, overwrite)
        try:
            self._mcap = McapFileWriter(self._file, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
            self._mcap.start(profile="", library=_library())
            for name, data in metadata.to_mcap().items():
                self._mcap.add_metadata(name, data)
            self._channels: dict[str, int] = {}
            for topic in topics():
                cls = record_type(topic)
                schema_id = self._mcap.register_schema(
                    name=cls.SCHEMA_NAME, encoding=SCHEMA_ENCODING, data=json.dumps(cls.SCHEMA).encode()
                )
                self._channels[topic] = self._mcap.register_channel(
                    topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=schema_id
                )
            # Channel ids are 1..n in registration order; a list index beats a dict lookup per write.
            self._sequences = [0] * (len(self._channels) + 1)
            self._step_channel = self._channels[EnvStep.TOPIC]
            self._queue = make_queue(
                native=native,
                step_channel=self._step_channel,
                call_channel=self._channels[EcmInvocation.TOPIC],
                batch=batch,
                on_full=self._on_full,
                refuse=self._refuse,
                check_row=check_row,
            )
            # The loop's hot path is the queue's own append, without a Python frame of ours
            # (the methods of the same name below do the same, one frame slower).
            self.write_env_step_row = self._queue.step  # type: ignore[method-assign]
            self.write_invocation_row = self._queue.call  # type: ignore[method-assign]
            self._file.flush()
            if fsync_on_flush:
                os.fsync(self._file.fileno())
        except OSError as exc:
            self._file.close()
            raise Unavailable(f"cannot write trace file {self.path}: {exc.strerror or exc}") from None
        self._flushed_at(time.monotonic())
        self._thread: threading.Thread | None = None
        if background_flush:
            self._thread = threading.Thread(target=self._flush_loop, name=f"trace-flush:{self.path.name}", daemon=True)
            self._thread.start()

    @staticmethod
    def _open(path: Path, overwrite: bool) -> BinaryIO:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            return path.open("wb" if overwrite else "xb")
        except FileExistsError:
            raise Conflict(
                f"trace file already exists: {path} (pass overwrite=True to replace it)", details={"path": str(path)}
            ) from None
        except OSError as exc:
            raise Unavailable(f"cannot create trace file {path}: {exc.strerror or exc}") from None

    # -- writing ---------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed or self._error is not None:
            raise self._error or Conflict(f"trace writer for {self.path} is closed")

    def _refuse(self, method: str) -> None:
        """The queue's callback for an append to a closed or failed writer: raise why."""
        self._check_open()
        raise Conflict(f"trace writer for {self.path} refuses {method}")  # pragma: no cover - closed implies raised

    def _fail(self, error: CapevoError) -> CapevoError:
        """Record the error that ends this writer; every later write raises it."""
        self._error = error
        self._queue.closed = True
        return error

    def _flushed_at(self, monotonic: float) -> None:
        self._last_flush = monotonic
        self._queue.flushed_ns = int(monotonic * 1e9)
        self._arm_deadline()

    def _arm_deadline(self) -> None:
        # The queue calls back at the next timed flush, or at the next write when a record the
        # background thread encoded failed: that write raises it.
        due = 1 if self._undelivered is not None else int((self._last_flush + self.flush_interval_s) * 1e9)
        self._queue.deadline_ns = due

    def _on_full(self) -> None:
        """The queue's callback when a batch is full or a timed flush is due."""
        with self._lock:
            if self._closed or self._error is not None:
                return  # close() encodes what is left; a failed writer refuses the next write
            try:
                due = time.monotonic() - self._last_flush >= self.flush_interval_s
                try:
                    self._encode_pending_locked()
                finally:
                    if due:
                        self._flush_locked(self.fsync_on_flush)
            except OSError as exc:
                raise self._fail(Unavailable(f"writing trace file {self.path} failed: {exc.strerror or exc}")) from None
            self._raise_undelivered()

    def _encode_pending_locked(self) -> None:
        if len(self._queue) == 0:
            return
        native = self._frame_batch is not None
        failed = self._frame_natively() if native else self._frame_in_python(self._queue.take())
        self._queue.dirty = True
        if failed is not None:
            raise failed

    def _frame_natively(self, pending: list[Entry] | None = None) -> Invalid | None:
        """Frame ``pending`` (entries as ``take()`` gives them), or the queue's own entries, which
        the C framer takes itself (``take()`` would build a tuple per entry)."""
        source = self._queue if pending is None else pending

        def frame(chunk: bytearray, index: dict[int, bytearray]) -> tuple[Any, ...]:
            args = (source, self._step_channel, self._sequences, self._encoder.name_json, self._payload)
            return self._frame_batch(chunk, index, *args)  # type: ignore[no-any-return, misc]

        count, _, _, failed = self._mcap.add_framed(frame)
        self._messages += count
        return failed  # type: ignore[no-any-return]

    def _payload(self, entry: Entry) -> bytes | Invalid:
        """An entry's payload where the C framer does not splice it: a record's, or a row's
        through its record (frame.c's fallback); the :class:`Invalid` that drops it."""
        channel_id, encode, item, _ = entry
        if encode is None:
            return self._encoder.record_path(channel_id == self._step_channel, item)
        try:
            return encode(item)
        except Invalid as exc:
            return exc

    def _frame_in_python(self, pending: list[Entry]) -> Invalid | None:
        """What the C framer (csrc/frame.c) does, in Python: its specification."""
        sequences = self._sequences
        failed: Invalid | None = None
        step_channel = self._step_channel
        rows = [(channel_id == step_channel, item) for channel_id, encode, item, _ in pending if encode is None]
        row_payloads = iter(self._encoder.rows(rows) if rows else ())
        messages: list[tuple[int, int, int, bytes]] = []
        for channel_id, encode, record, now in pending:
            try:
                payload = next(row_payloads) if encode is None else encode(record)
            except Invalid as exc:
                failed = failed or exc
                continue
            if type(payload) is not bytes:  # a row's Invalid, in its place
                failed = failed or payload
                continue
            sequence = sequences[channel_id]
            sequences[channel_id] = (sequence + 1) % _SEQUENCE_MOD
            messages.append((channel_id, now, sequence, payload))
        self._mcap.add_messages(messages)
        self._messages += len(messages)
        return failed

    def _raise_undelivered(self) -> None:
        failed, self._undelivered = self._undelivered, None
        if failed is not None:
            self._arm_deadline()
            raise failed

    def write_plan_step(self, record: PlanStep) -> None:
        """Append a plan step to ``/plan``."""
        check_record(record, PlanStep, "write_plan_step")
        self._queue.record(self._channels[PlanStep.TOPIC], self._encoder.encode, record, "write_plan_step")

    def write_invocation(self, record: EcmInvocation) -> None:
        """Append an ECM invocation to ``/ecm/invocation``."""
        if type(record) is not EcmInvocation:
            check_record(record, EcmInvocation, "write_invocation")
        self._queue.record(self._channels[EcmInvocation.TOPIC], self._encoder.invocation, record, "write_invocation")

    def write_intervention(self, record: Intervention) -> None:
        """Append a governance intervention to ``/governance/intervention``."""
        check_record(record, Intervention, "write_intervention")
        self._queue.record(self._channels[Intervention.TOPIC], self._encoder.encode, record, "write_intervention")

    def write_env_step(self, record: EnvStep) -> None:
        """Append an env step to ``/env/step`` (the hot path: one call per control step)."""
        if type(record) is not EnvStep:
            check_record(record, EnvStep, "write_env_step")
        self._queue.record(self._step_channel, self._encoder.env_step, record, "write_env_step")

    def write_env_step_row(self, row: EnvStepRow) -> None:
        """Append an env step given as a row (:mod:`~capevo.runtime.traces.rows`) to ``/env/step``:
        the episode loop's hot path. The same message as ``write_env_step(env_step_of(row))``."""
        self._queue.step(row)

    def write_invocation_row(self, row: InvocationRow) -> None:
        """Append an ECM invocation given as a row to ``/ecm/invocation``; the same message as
        ``write_invocation(invocation_of(row))``."""
        self._queue.call(row)

    def write_episode_summary(self, record: EpisodeSummary) -> None:
        """Append an episode summary to ``/episode/summary`` and flush: episodes are the unit
        learners consume, so a finished episode should not wait for the timer."""
        check_record(record, EpisodeSummary, "write_episode_summary")
        self._queue.record(self._channels[EpisodeSummary.TOPIC], self._encoder.encode, record, "write_episode_summary")
        self.flush()

    # -- flushing --------------------------------------------------------------------------

    def _flush_locked(self, fsync: bool) -> None:
        # Callers encode the kept records first; a chunk is finished whatever they raised.
        self._mcap.flush()
        if fsync:
            os.fsync(self._file.fileno())
        self._flushed_at(time.monotonic())
        self._queue.dirty = False
        self._flushes += 1

    def flush(self, *, fsync: bool | None = None) -> None:
        """Finish the open chunk and hand everything written so far to the OS.

        Args:
            fsync: Also sync to disk; None uses the writer's ``fsync_on_flush``.

        Raises:
            Conflict: the writer is closed.
            Unavailable: the OS refused the write.
        """
        with self._lock:
            self._check_open()
            try:
                try:
                    self._encode_pending_locked()
                finally:
                    self._flush_locked(self.fsync_on_flush if fsync is None else fsync)
            except OSError as exc:
                failure = Unavailable(f"flushing trace file {self.path} failed: {exc.strerror or exc}")
                raise self._fail(failure) from None
            self._raise_undelivered()

    def _flush_loop(self) -> None:
        # The queue's wait_due sleeps, without the GIL, until a grace (a quarter of the interval)
        # after the flush is due while records wait: a busy writer, whose own writes flush at the
        # deadline, is never disturbed; an idle one's last records are flushed here.
        interval_ns = int(self.flush_interval_s * 1e9)
        while self._queue.wait_due(interval_ns, interval_ns // 4):
            with self._lock:
                if self._closed or self._error is not None:
                    return
                kept = self._queue.dirty or len(self._queue) > 0
                if kept and time.monotonic() - self._last_flush >= self.flush_interval_s:
                    try:
                        try:
                            self._encode_pending_locked()
                        except Invalid as exc:
                            self._undelivered = self._undelivered or exc
                        self._flush_locked(self.fsync_on_flush)
                    except OSError as exc:
                        # Surfaces on the next write/flush/close of the owning thread.
                        self._fail(Unavailable(f"flushing trace file {self.path} failed: {exc.strerror or exc}"))
                        return

    # -- closing ---------------------------------------------------------------------------

    def close(self) -> None:
        """Finish the file (summary, footer) and close it. Idempotent.

        Raises:
            Unavailable: a write failed earlier or finishing failed; the file is closed anyway
                and may need :func:`~capevo.runtime.traces.recover`.
            Invalid: a kept record did not encode; it is left out and the file is finished.
        """
        self._queue.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.closed = True
            error: CapevoError | None = self._error
            try:
                if error is None:
                    try:
                        self._encode_pending_locked()
                    except Invalid as exc:
                        error = exc
                    self._mcap.finish()
                    self._file.flush()
                    if self.fsync_on_flush:
                        os.fsync(self._file.fileno())
            except OSError as exc:
                error = Unavailable(f"finishing trace file {self.path} failed: {exc.strerror or exc}")
            finally:
                try:
                    self._file.close()
                except OSError as exc:  # the buffered tail the OS refused: the error is already ours
                    error = error or Unavailable(f"closing trace file {self.path} failed: {exc.strerror or exc}")
        if error is None:
            error, self._undelivered = self._undelivered, None
        if error is not None:
            raise error

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- introspection ---------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def messages_written(self) -> int:
        return self._messages

    @property
    def flushes(self) -> int:
        """Timed and explicit flushes so far (chunks finished for reaching ``chunk_size`` not counted)."""
        return self._flushes

    def stats(self) -> dict[str, Any]:
        return {"path": str(self.path), "messages": self._messages, "flushes": self._flushes, "closed": self._closed}
