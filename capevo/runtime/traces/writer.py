"""TraceWriter: the MCAP file of one run, crash-safe to about the last second.

The file is written by the ``mcap`` library's own :class:`mcap.writer.Writer` (chunking,
compression, CRCs, indexes, summary): the MCAP magic and header, the metadata records
(``capevo.run``, ``capevo.packages``), then chunks of messages, the first of which also holds the
five JSON-schema schemas and channels; ``close()`` writes the summary (schemas, channels,
statistics, chunk and metadata indexes) and the footer, so Foxglove and the ``mcap`` tools open
the file directly.

Records are kept as they are written and encoded (:mod:`~capevo.runtime.traces.codec`) and
handed to the mcap Writer all at once, at each flush or every :data:`KEPT_RECORDS`: in the
episode loop every robosuite step between two writes evicts the CPU caches, so encoding a record
where it is written costs about three times what it costs in a run of them, which took the
writer past 1 % of an episode (benchmarks/bench_traces_loop.py). A kept record is as safe as one
in the open chunk: both reach the OS at the next flush.

Crash safety: :meth:`mcap.writer.Writer.flush` finishes the open chunk and hands everything to
the OS. The writer calls it at least every ``flush_interval_s`` seconds while records wait,
checked on every write and by a background thread (so an idle worker's last records reach the
file too), at every episode summary and at ``flush()``. Data the OS has survives the writer being
killed with SIGKILL; ``fsync_on_flush=True`` also survives power loss at the cost of a disk sync
per flush. :func:`capevo.runtime.traces.recover` turns the unfinished file of a killed worker into
a finished one.

Invariants:
1. Header and metadata are in the OS before the constructor returns.
2. A record written at time t is in the OS by t + ``flush_interval_s`` (+ one background
   tick, a quarter of the interval) or at the next ``flush()``, whichever is first, as
   long as the process lives; after ``flush()`` returns, every record written before it is.
3. ``close()`` is idempotent, leaves a finished MCAP (summary, footer, closing magic) and
   stops the background thread; writes after it raise :class:`Conflict`.
4. Each ``write_*`` method accepts only its record type (:class:`Invalid` otherwise) and writes
   it to its own topic; messages get the wall-clock time of the write call as log and publish
   time and a per-channel sequence number starting at 0, in write order. A record whose fields
   do not encode is left out, after every other kept record is written, with :class:`Invalid`
   raised by the call that encoded it (a write, ``flush()`` or ``close()``), or, when the
   background thread did, by the owner's next one.
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

from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from capevo.errors import CapevoError, Conflict, Invalid, Unavailable, check_choice
from capevo.runtime.traces import codec
from capevo.runtime.traces.records import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    Intervention,
    PlanStep,
    TraceMetadata,
    TraceRecord,
    UnsafeStep,
    record_type,
    topics,
)
from capevo.runtime.traces.sink import check_record

COMPRESSIONS: Mapping[str, str] = {"lz4": "lz4", "zstd": "zstd", "none": ""}
"""Chunk compression by name -> MCAP compression string. lz4 is the default: cheap to write;
``zstd`` makes smaller files for more CPU, ``none`` larger ones (about three times lz4's) for less."""
DEFAULT_COMPRESSION = "lz4"

_COMPRESSION_TYPES: Mapping[str, CompressionType] = {
    "lz4": CompressionType.LZ4,
    "zstd": CompressionType.ZSTD,
    "none": CompressionType.NONE,
}


def check_compression(name: object) -> str:
    """``name`` if it is one of :data:`COMPRESSIONS`.

    Raises:
        Invalid: anything else (field ``compression``).
    """
    return check_choice(name, tuple(COMPRESSIONS), what="trace compression", field="compression")


DEFAULT_CHUNK_SIZE = 256 * 1024
DEFAULT_FLUSH_INTERVAL_S = 1.0
KEPT_RECORDS = 1024
"""Records kept before they are encoded, unless a flush comes first: more than one flush
interval brings at the speeds the runtime reaches (a few hundred records a second); the bound
caps the memory a long interval could keep."""

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
        flush_interval_s: Finish a chunk and hand it to the OS at least this often while records wait.
        compression: ``"lz4"`` (default), ``"zstd"`` or ``"none"``.
        fsync_on_flush: Also fsync at every flush (power-loss safety; slower).
        background_flush: Run the thread that flushes while no writes arrive.
        overwrite: Replace an existing file instead of raising :class:`Conflict`.

    Raises:
        Invalid: bad chunk size, interval or compression name.
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
    ) -> None:
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
            raise Invalid(f"chunk_size must be a positive integer, got {chunk_size!r}", details={"field": "chunk_size"})
        if not isinstance(flush_interval_s, int | float) or not flush_interval_s > 0:
            raise Invalid(
                f"flush_interval_s must be a positive number, got {flush_interval_s!r}",
                details={"field": "flush_interval_s"},
            )
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
        self._waiting = False  # records written since the last flush
        # Records written and not yet encoded, oldest first: (channel, wall-clock ns, record).
        self._kept: list[tuple[int, int, TraceRecord]] = []
        # A kept record that did not encode, for the owner's next call to raise.
        self._undelivered: Invalid | None = None
        self._file = self._open(self.path, overwrite)
        try:
            self._mcap = Writer(self._file, chunk_size=chunk_size, compression=_COMPRESSION_TYPES[compression])
            self._mcap.start(profile="", library=_library())
            for name, data in metadata.to_mcap().items():
                self._mcap.add_metadata(name, data)
            self._channels: dict[str, int] = {}
            for topic in topics():
                cls = record_type(topic)
                schema = json.dumps(cls.SCHEMA).encode()
                schema_id = self._mcap.register_schema(cls.SCHEMA_NAME, SCHEMA_ENCODING, schema)
                self._channels[topic] = self._mcap.register_channel(topic, MESSAGE_ENCODING, schema_id)
            self._sequences = dict.fromkeys(self._channels.values(), 0)
            self._mcap.flush()
            if fsync_on_flush:
                os.fsync(self._file.fileno())
        except OSError as exc:
            self._file.close()
            raise Unavailable(f"cannot write trace file {self.path}: {exc.strerror or exc}") from None
        self._last_flush = time.monotonic()
        self._stopping = threading.Event()
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

    def _fail(self, error: CapevoError) -> CapevoError:
        """Record the error that ends this writer; every later write raises it."""
        self._error = error
        return error

    def _write(self, record: TraceRecord, expected: type[Any], method: str) -> None:
        now = time.time_ns()
        check_record(record, expected, method)
        with self._lock:
            self._check_open()
            self._kept.append((self._channels[expected.TOPIC], now, record))
            self._messages += 1
            self._waiting = True
            try:
                if time.monotonic() - self._last_flush >= self.flush_interval_s:
                    self._flush_locked(self.fsync_on_flush)
                elif len(self._kept) >= KEPT_RECORDS:
                    self._encode_kept_locked()
            except OSError as exc:
                raise self._fail(Unavailable(f"writing trace file {self.path} failed: {exc.strerror or exc}")) from None
            self._deliver_locked()

    def write_plan_step(self, record: PlanStep) -> None:
        """Append a plan step to ``/plan``."""
        self._write(record, PlanStep, "write_plan_step")

    def write_invocation(self, record: EcmInvocation) -> None:
        """Append an ECM invocation to ``/ecm/invocation``."""
        self._write(record, EcmInvocation, "write_invocation")

    def write_intervention(self, record: Intervention) -> None:
        """Append a governance intervention to ``/governance/intervention``."""
        self._write(record, Intervention, "write_intervention")

    def write_env_step(self, record: EnvStep) -> None:
        """Append an env step to ``/env/step``."""
        self._write(record, EnvStep, "write_env_step")

    def write_unsafe_step(self, record: UnsafeStep) -> None:
        """Append a step the safety monitor graded unsafe to ``/safety/unsafe``."""
        self._write(record, UnsafeStep, "write_unsafe_step")

    def write_episode_summary(self, record: EpisodeSummary) -> None:
        """Append an episode summary to ``/episode/summary`` and flush: episodes are the unit
        learners consume, so a finished episode should not wait for the timer."""
        self._write(record, EpisodeSummary, "write_episode_summary")
        self.flush()

    # -- flushing --------------------------------------------------------------------------

    def _encode_kept_locked(self) -> None:
        """Encode the kept records into the mcap Writer, in write order; one that does not encode
        is dropped, its :class:`Invalid` kept for the owner's next call (:meth:`_deliver_locked`)."""
        kept, self._kept = self._kept, []
        for channel, now, record in kept:
            try:
                payload = codec.encode(record)
            except Invalid as exc:
                self._messages -= 1
                self._undelivered = self._undelivered or exc
                continue
            sequence = self._sequences[channel]
            self._sequences[channel] = (sequence + 1) % _SEQUENCE_MOD
            self._mcap.add_message(channel, now, payload, now, sequence)

    def _deliver_locked(self) -> None:
        failed, self._undelivered = self._undelivered, None
        if failed is not None:
            raise failed

    def _flush_locked(self, fsync: bool) -> None:
        self._encode_kept_locked()
        self._mcap.flush()
        if fsync:
            os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()
        self._waiting = False
        self._flushes += 1

    def flush(self, *, fsync: bool | None = None) -> None:
        """Finish the open chunk and hand everything written so far to the OS.

        Args:
            fsync: Also sync to disk; None uses the writer's ``fsync_on_flush``.

        Raises:
            Conflict: the writer is closed.
            Unavailable: the OS refused the write.
            Invalid: a record written since the last such error did not encode (it is left out).
        """
        with self._lock:
            self._check_open()
            try:
                self._flush_locked(self.fsync_on_flush if fsync is None else fsync)
            except OSError as exc:
                failure = Unavailable(f"flushing trace file {self.path} failed: {exc.strerror or exc}")
                raise self._fail(failure) from None
            self._deliver_locked()

    def _flush_loop(self) -> None:
        # Wakes four times an interval; a busy writer's own writes flush at the deadline, so
        # here only an idle writer's last records are flushed.
        while not self._stopping.wait(self.flush_interval_s / 4):
            with self._lock:
                if self._closed or self._error is not None:
                    return
                if self._waiting and time.monotonic() - self._last_flush >= self.flush_interval_s:
                    try:
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
        self._stopping.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            error: CapevoError | None = self._error
            try:
                if error is None:
                    self._encode_kept_locked()
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
