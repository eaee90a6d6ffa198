"""M_ep, episodic memory: one JSON line per episode, appended and fsynced, never rewritten.

Each line is the canonical JSON (sorted keys, no spaces) of an :class:`EpisodeRecord`
followed by ``\\n``, written with one ``write`` and made durable with ``fsync`` before
:meth:`EpisodicMemory.append` returns. The file grows without bound; reading streams it.

A crash (power loss, a full disk) can leave a torn last line: bytes with no final newline.
Such a line was never acknowledged, so readers ignore it and report it
(:attr:`EpisodicLog.torn_tail_bytes`), and the next writer cuts it off before appending so
it cannot glue onto the next record.

Invariants:
1. Every record whose ``append`` returned is read back equal, in append order, even if the
   writer process is SIGKILLed right after.
2. A torn last line is never returned and never raises; it is reported in bytes.
3. A malformed line that is not the torn tail raises :class:`Corrupt` naming its line number.
4. Iterations never decrease along the file (``append`` refuses with :class:`Invalid`).
5. One writer at a time: a second :class:`EpisodicMemory` on the same file raises
   :class:`Conflict` while the first is open (an advisory ``flock``, released by the kernel
   when the holder dies).
6. ``EpisodeRecord.from_dict(r.to_dict()) == r``; a record with a bad field raises :class:`Invalid`.
"""

from __future__ import annotations

import fcntl
import json
import logging
import math
import os
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from capevo.errors import CapevoError, Conflict, Corrupt, Invalid, NotFound
from capevo.records.audit import canonical_json
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.storage.blobs import append_synced, fsync_dir

log = logging.getLogger(__name__)

_TAIL_CHUNK = 64 * 1024


def _bad(field_name: str, message: str) -> Invalid:
    return Invalid(f"{field_name}: {message}", details={"field": field_name})


def _int(value: Any, field_name: str, *, minimum: int | None = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _bad(field_name, f"must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        raise _bad(field_name, f"must be at least {minimum}, got {value}")
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeRecord:
    """One episode as the agent remembers it.

    Args:
        iteration: Closed-loop iteration the episode belongs to (several episodes may share one).
        task: Task name.
        seed: Episode seed.
        success: Whether the task's success criterion held.
        reward: Episode return.
        steps: Environment steps taken.
        capability_set: ECM name -> version the episode ran with.
        trace: Where the episode's trace is (an MCAP path or URI), if one was written.

    Raises:
        Invalid: a field of the wrong type or range.
    """

    iteration: int
    task: str
    seed: int
    success: bool
    reward: float
    steps: int
    capability_set: Mapping[str, int] = field(default_factory=dict)
    trace: str | None = None

    def __post_init__(self) -> None:
        _int(self.iteration, "iteration")
        _int(self.seed, "seed", minimum=None)
        _int(self.steps, "steps")
        if not isinstance(self.task, str) or not 0 < len(self.task) <= 256:
            raise _bad("task", f"must be a non-empty string of at most 256 characters, got {self.task!r}")
        if not isinstance(self.success, bool):
            raise _bad("success", f"must be true or false, got {self.success!r}")
        if isinstance(self.reward, bool) or not isinstance(self.reward, (int, float)) or not math.isfinite(self.reward):
            raise _bad("reward", f"must be a finite number, got {self.reward!r}")
        object.__setattr__(self, "reward", float(self.reward))
        if not isinstance(self.capability_set, Mapping):
            raise _bad("capability_set", f"must be a mapping of ECM name to version, got {self.capability_set!r}")
        caps: dict[str, int] = {}
        for name, version in sorted(self.capability_set.items(), key=lambda kv: str(kv[0])):
            if not isinstance(name, str) or not name:
                raise _bad("capability_set", f"ECM names must be non-empty strings, got {name!r}")
            caps[name] = _int(version, f"capability_set.{name}")
        object.__setattr__(self, "capability_set", MappingProxyType(caps))
        if self.trace is not None and not isinstance(self.trace, str):
            raise _bad("trace", f"must be a string or null, got {self.trace!r}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration,
            "task": self.task,
            "seed": self.seed,
            "success": self.success,
            "reward": self.reward,
            "steps": self.steps,
            "capability_set": dict(self.capability_set),
            "trace": self.trace,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EpisodeRecord:
        """Inverse of :meth:`to_dict`.

        Raises:
            Invalid: a missing, unknown or bad field.
        """
        if not isinstance(d, Mapping):
            raise _bad("<record>", "must be a JSON object")
        known = {"iteration", "task", "seed", "success", "reward", "steps", "capability_set", "trace"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise _bad(str(unknown[0]), "unknown field")
        missing = sorted(known - {"trace"} - set(d))
        if missing:
            raise _bad(missing[0], "missing")
        return cls(
            iteration=d["iteration"],
            task=d["task"],
            seed=d["seed"],
            success=d["success"],
            reward=d["reward"],
            steps=d["steps"],
            capability_set=d["capability_set"],
            trace=d.get("trace"),
        )

    @classmethod
    def from_outcome(cls, *, iteration: int, task: str, outcome: EpisodeOutcome) -> EpisodeRecord:
        """The record of an evaluated episode."""
        return cls(
            iteration=iteration,
            task=task,
            seed=outcome.seed,
            success=outcome.success,
            reward=outcome.reward,
            steps=outcome.steps,
            capability_set=outcome.capability_set,
            trace=outcome.trace_path,
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodicLog:
    """What a read of M_ep found."""

    path: str
    records: tuple[EpisodeRecord, ...]
    torn_tail_bytes: int = 0
    """Length of an unterminated last line that was ignored (0: the file ended cleanly)."""

    @property
    def torn(self) -> bool:
        return self.torn_tail_bytes > 0


def _parse_line(raw: bytes, path: Path, lineno: int) -> EpisodeRecord:
    try:
        return EpisodeRecord.from_dict(json.loads(raw))
    except (ValueError, RecursionError) as exc:
        raise Corrupt(
            f"{path}:{lineno}: not a JSON episode record: {exc}", details={"path": str(path), "line": lineno}
        ) from None
    except Invalid as exc:
        raise Corrupt(
            f"{path}:{lineno}: bad episode record: {exc.message}",
            details={"path": str(path), "line": lineno, **exc.details},
        ) from None


def _numbered_lines(path: Path) -> Iterator[tuple[int, bytes]]:
    """``(line number, raw line)`` of ``path`` from 1; only the last one may lack its newline.

    Raises:
        NotFound: no file at ``path``.
    """
    try:
        f = path.open("rb")
    except FileNotFoundError:
        raise NotFound(f"no episodic memory at {path}", details={"path": str(path)}) from None
    with f:
        yield from enumerate(f, start=1)


def iter_episodes(path: str | os.PathLike[str]) -> Iterator[EpisodeRecord]:
    """Stream the complete records of ``path`` in order, skipping a torn last line silently.

    Raises:
        NotFound: no file at ``path``.
        Corrupt: a malformed complete line.
    """
    p = Path(path)
    for lineno, raw in _numbered_lines(p):
        if not raw.endswith(b"\n"):
            return
        yield _parse_line(raw, p, lineno)


def read_episodes(path: str | os.PathLike[str]) -> EpisodicLog:
    """Read every complete record of ``path``; a torn last line is ignored and reported.

    Returns:
        The records in append order and the size of any torn tail.

    Raises:
        NotFound: no file at ``path``.
        Corrupt: a malformed line that is not the torn tail (the message names the line).
    """
    p = Path(path)
    records: list[EpisodeRecord] = []
    torn = 0
    for lineno, raw in _numbered_lines(p):
        if not raw.endswith(b"\n"):
            torn = len(raw)
            log.warning("%s:%d: ignoring a torn last line of %d bytes (a write that never completed)", p, lineno, torn)
            break
        records.append(_parse_line(raw, p, lineno))
    return EpisodicLog(path=str(p), records=tuple(records), torn_tail_bytes=torn)


class EpisodicMemory:
    """The append-only episode log of one agent, open for writing.

    Args:
        path: The JSON Lines file; created (with its parent directories) if absent.

    Raises:
        Conflict: another open :class:`EpisodicMemory` holds the file.
        Corrupt: the last complete line is not a valid record.
        Invalid: the file cannot be opened.
    """

    __slots__ = ("_fd", "_last_iteration", "_lock", "_path", "repaired_bytes")

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._path = Path(path)
        self._lock = threading.Lock()
        try:
            self._path.parent.mkdir(parents=True, exist_ok=True)
            existed = self._path.exists()
            fd = os.open(self._path, os.O_RDWR | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as exc:
            raise Invalid(
                f"cannot open episodic memory {self._path}: {exc.strerror}", details={"path": str(path)}
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise Conflict(
                f"episodic memory {self._path} is already open for writing by another writer",
                details={"path": str(self._path)},
            ) from None
        self._fd: int | None = fd
        try:
            if not existed:
                # The new file's directory entry must be durable too, or the whole log can vanish.
                fsync_dir(self._path.parent)
            self.repaired_bytes, self._last_iteration = self._recover_tail()
        except BaseException:
            self.close()
            raise

    @property
    def path(self) -> Path:
        return self._path

    def _recover_tail(self) -> tuple[int, int | None]:
        """Cut a torn last line off; return its length and the last record's iteration."""
        fd = self._require_open()
        size = os.fstat(fd).st_size
        start = size
        buf = b""
        while start > 0:
            step = min(_TAIL_CHUNK, start)
            start -= step
            buf = os.pread(fd, step, start) + buf
            # The last complete line ends at the last newline; we need the one before it too.
            if buf.count(b"\n") >= 2 or start == 0:
                break
        cut = buf.rfind(b"\n") + 1  # 0 when there is no newline at all
        torn = len(buf) - cut
        if torn:
            log.warning("%s: cutting off a torn last line of %d bytes before appending", self._path, torn)
            os.ftruncate(fd, size - torn)
            os.fsync(fd)
        complete = buf[:cut]
        if not complete:
            return torn, None
        last_line = complete[complete.rfind(b"\n", 0, len(complete) - 1) + 1 :]
        try:
            last = EpisodeRecord.from_dict(json.loads(last_line))
        except (ValueError, RecursionError, Invalid) as exc:
            raise Corrupt(
                f"{self._path}: the last complete record is not valid ({exc}); refusing to append to it",
                details={"path": str(self._path)},
            ) from None
        return torn, last.iteration

    def _require_open(self) -> int:
        if self._fd is None:
            raise Invalid(f"episodic memory {self._path} is closed", details={"path": str(self._path)})
        return self._fd

    @property
    def last_iteration(self) -> int | None:
        """Iteration of the last record in the file (None while empty)."""
        return self._last_iteration

    def append(self, record: EpisodeRecord) -> None:
        """Write ``record`` as one line and fsync it; durable once this returns.

        Raises:
            Invalid: not an :class:`EpisodeRecord`, an iteration lower than the last one, or the memory is closed.
            CapevoError: the write or fsync failed (the partial line is cut off again).
        """
        if not isinstance(record, EpisodeRecord):
            raise Invalid(f"expected an EpisodeRecord, got {type(record).__name__}", details={"field": "record"})
        line = canonical_json(record.to_dict()).encode() + b"\n"
        with self._lock:
            fd = self._require_open()
            if self._last_iteration is not None and record.iteration < self._last_iteration:
                raise _bad(
                    "iteration", f"{record.iteration} is before the last recorded iteration {self._last_iteration}"
                )
            try:
                append_synced(fd, line)
            except OSError as exc:
                raise CapevoError(
                    f"cannot append to {self._path}: {exc.strerror}", details={"path": str(self._path)}
                ) from None
            self._last_iteration = record.iteration

    def read(self) -> EpisodicLog:
        """Everything appended so far (see :func:`read_episodes`)."""
        return read_episodes(self._path)

    def close(self) -> None:
        """Release the file; idempotent."""
        with self._lock:
            if self._fd is not None:
                fd, self._fd = self._fd, None
                os.close(fd)  # also drops the flock

    def __enter__(self) -> EpisodicMemory:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
