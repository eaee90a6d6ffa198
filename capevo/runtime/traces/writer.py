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
several times what it costs warm (benchmarks/bench_traces_loop.py: about 190 µs per T1 step
unbatched, 70 with batches of 64). A kept record is as safe as one in the open chunk: both reach
the OS at the next flush. The runtime's writers use :data:`RUNTIME_BATCH`; the default, 1,
encodes each record at once.

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
4. Each ``write_*`` method accepts only its record type (:class:`Invalid` otherwise, at
   once) and writes it to its own topic; messages get the wall-clock time of the write call
   as log and publish time and a per-channel sequence number starting at 0, in write order.
   A record whose fields do not encode is dropped with :class:`Invalid`: with ``batch=1``
   raised by its own write call; otherwise by the call that encodes its batch (a later
   write, ``flush()`` or ``close()``, the next of them if the background thread did), after
   every other record of the batch is written.
5. An existing file is never overwritten unless ``overwrite=True`` (:class:`Conflict`).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import LIBRARY_IDENTIFIER

from capevo.errors import CapevoError, Conflict, Invalid, Unavailable
from capevo.runtime.traces import codec
from capevo.runtime.traces.mcapfile import McapFileWriter
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
from capevo.runtime.traces.sink import check_record

COMPRESSIONS: Mapping[str, str] = {"lz4": "lz4", "zstd": "zstd", "none": ""}
"""Chunk compression by name -> MCAP compression string. lz4 is the default: zstd costs
several µs more per env step, amortised (see benchmarks/bench_traces.py)."""

DEFAULT_CHUNK_SIZE = 256 * 1024
DEFAULT_FLUSH_INTERVAL_S = 1.0
RUNTIME_BATCH = 64
"""Records the runtime's writers (worker, evaluator) encode at a time: about 30 env steps with
their invocations, half a second of a 60-steps/s episode, under the flush interval."""

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
        compression: str = "lz4",
        fsync_on_flush: bool = False,
        background_flush: bool = True,
        overwrite: bool = False,
        batch: int = 1,
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
        if compression not in COMPRESSIONS:
            raise Invalid(
                f"unknown compression {compression!r}; valid: {', '.join(COMPRESSIONS)}",
                details={"field": "compression"},
            )
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
        self._dirty = False
        self._encoder = codec.RecordEncoder()
        self.batch = batch
        # (channel id, encode function, record, wall-clock ns of the write), in write order.
        self._pending: list[tuple[int, Callable[[Any], bytes], Any, int]] = []
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
            self._file.flush()
            if fsync_on_flush:
                os.fsync(self._file.fileno())
        except OSError as exc:
            self._file.close()
            raise Unavailable(f"cannot write trace file {self.path}: {exc.strerror or exc}") from None
        self._last_flush = time.monotonic()
        self._stop = threading.Event()
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

    def _write(self, topic: str, encode: Callable[[Any], bytes], record: Any) -> None:
        now = time.time_ns()
        with self._lock:
            if self._closed or self._error is not None:  # _check_open, inlined: once per record
                raise self._error or Conflict(f"trace writer for {self.path} is closed")
            pending = self._pending
            pending.append((self._channels[topic], encode, record, now))
            try:
                due = time.monotonic() - self._last_flush >= self.flush_interval_s
                if due or len(pending) >= self.batch:
                    try:
                        self._encode_pending_locked()
                    finally:
                        if due:
                            self._flush_locked(self.fsync_on_flush)
            except OSError as exc:
                self._error = Unavailable(f"writing trace file {self.path} failed: {exc.strerror or exc}")
                raise self._error from None
            if self._undelivered is not None:
                self._raise_undelivered()

    def _encode_pending_locked(self) -> None:
        pending = self._pending
        if not pending:
            return
        self._pending = []
        add, sequences = self._mcap.add_message, self._sequences
        failed: Invalid | None = None
        for channel_id, encode, record, now in pending:
            try:
                payload = encode(record)
            except Invalid as exc:
                failed = failed or exc
                continue
            sequence = sequences[channel_id]
            sequences[channel_id] = (sequence + 1) % _SEQUENCE_MOD
            add(channel_id, now, now, sequence, payload)
            self._messages += 1
            self._dirty = True
        if failed is not None:
            raise failed

    def _raise_undelivered(self) -> None:
        failed, self._undelivered = self._undelivered, None
        if failed is not None:
            raise failed

    def write_plan_step(self, record: PlanStep) -> None:
        """Append a plan step to ``/plan``."""
        check_record(record, PlanStep, "write_plan_step")
        self._write(PlanStep.TOPIC, self._encoder.encode, record)

    def write_invocation(self, record: EcmInvocation) -> None:
        """Append an ECM invocation to ``/ecm/invocation``."""
        if type(record) is not EcmInvocation:
            check_record(record, EcmInvocation, "write_invocation")
        self._write(EcmInvocation.TOPIC, self._encoder.invocation, record)

    def write_intervention(self, record: Intervention) -> None:
        """Append a governance intervention to ``/governance/intervention``."""
        check_record(record, Intervention, "write_intervention")
        self._write(Intervention.TOPIC, self._encoder.encode, record)

    def write_env_step(self, record: EnvStep) -> None:
        """Append an env step to ``/env/step`` (the hot path: one call per control step)."""
        if type(record) is not EnvStep:
            check_record(record, EnvStep, "write_env_step")
        self._write(EnvStep.TOPIC, self._encoder.env_step, record)

    def write_episode_summary(self, record: EpisodeSummary) -> None:
        """Append an episode summary to ``/episode/summary`` and flush: episodes are the unit
        learners consume, so a finished episode should not wait for the timer."""
        check_record(record, EpisodeSummary, "write_episode_summary")
        self._write(EpisodeSummary.TOPIC, self._encoder.encode, record)
        self.flush()

    # -- flushing --------------------------------------------------------------------------

    def _flush_locked(self, fsync: bool) -> None:
        # Callers encode the kept records first; a chunk is finished whatever they raised.
        self._mcap.flush()
        if fsync:
            os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()
        self._dirty = False
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
                self._error = Unavailable(f"flushing trace file {self.path} failed: {exc.strerror or exc}")
                raise self._error from None
            self._raise_undelivered()

    def _flush_loop(self) -> None:
        tick = self.flush_interval_s / 4
        while not self._stop.wait(tick):
            with self._lock:
                if self._closed or self._error is not None:
                    return
                if (self._dirty or self._pending) and time.monotonic() - self._last_flush >= self.flush_interval_s:
                    try:
                        try:
                            self._encode_pending_locked()
                        except Invalid as exc:
                            self._undelivered = self._undelivered or exc
                        self._flush_locked(self.fsync_on_flush)
                    except OSError as exc:
                        # Surfaces on the next write/flush/close of the owning thread.
                        self._error = Unavailable(f"flushing trace file {self.path} failed: {exc.strerror or exc}")
                        return

    # -- closing ---------------------------------------------------------------------------

    def close(self) -> None:
        """Finish the file (summary, footer) and close it. Idempotent.

        Raises:
            Unavailable: a write failed earlier or finishing failed; the file is closed anyway
                and may need :func:`~capevo.runtime.traces.recover`.
            Invalid: a kept record did not encode; it is left out and the file is finished.
        """
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
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
                self._file.close()
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
