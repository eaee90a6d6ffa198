"""Content-addressed, durable blob storage for ECM artifacts.

A blob whose sha256 is ``abcdef…`` lives at ``root/ab/cdef…``. Every write goes through a
:class:`BlobWriter`: it streams into a temporary file in ``root/incoming`` (the same file
system), hashing as it goes, fsyncs it, ``os.replace``-s it into place and fsyncs the
directory, so a reader (or a process restarted after SIGKILL or power loss) sees
either no file or the complete file, never a torn one.

Invariants:
1. A blob file at ``root/ab/cdef…`` is visible only once complete and durable
   (temp file + fsync + atomic rename + directory fsync).
2. :meth:`BlobStore.get` never returns bytes whose sha256 differs from the requested
   address: a mismatch raises :class:`Corrupt`, a missing file :class:`NotFound`.
3. Only strings of exactly 64 lowercase hex digits address a blob, so no address can
   name a path outside ``root``; anything else raises :class:`Invalid`.
4. ``put`` is idempotent: storing the same bytes twice yields the same address and one
   file; a present but corrupt copy is replaced by the good bytes.
5. Temporary files (``.tmp-*``) are never reported as blobs.
6. :meth:`BlobStore.sweep_temp` removes a temporary file only when nobody touched it for
   ``older_than_s`` or, with ``writer_gone=True``, when the process that wrote it (its name
   carries the pid) no longer runs on this host.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import secrets
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

from capevo.errors import Corrupt, Invalid, NotFound, TooLarge, Unavailable

SHA256_PATTERN = re.compile(r"[0-9a-f]{64}")
CHUNK_BYTES = 1 << 20
_TMP_PREFIX = ".tmp-"


def validate_sha256(sha256: object) -> str:
    """Return ``sha256`` if it is 64 lowercase hex digits.

    Raises:
        Invalid: for any other value (this is what rules out path traversal).
    """
    if not isinstance(sha256, str) or not SHA256_PATTERN.fullmatch(sha256):
        shown = repr(sha256)[:80]
        raise Invalid(f"blob address must be 64 lowercase hex digits, got {shown}", details={"field": "sha256"})
    return sha256


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """Make the entries of directory ``path`` (new files, renames) durable."""
    # A rename is durable only once the directory entry is; O_DIRECTORY is POSIX-only.
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def append_synced(fd: int, data: bytes) -> None:
    """Write all of ``data`` at the end of the file open on ``fd`` and fsync it.

    Raises:
        OSError: the write or the sync failed; the file is cut back to its old size first, so
            no half record is left for the next append to glue onto.
    """
    before = os.fstat(fd).st_size
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    except OSError:
        with contextlib.suppress(OSError):
            os.ftruncate(fd, before)
        raise


class BlobWriter:
    """One blob written piece by piece into a temporary file, hashed as it goes.

    :meth:`finish` makes it a blob (fsync, then the rename and directory fsync of invariant
    1) and returns its address; :meth:`discard` drops it. Until then nothing is visible, and
    a writer killed meanwhile leaves only a temporary file that :meth:`BlobStore.sweep_temp`
    removes. Not thread-safe: one writer, one thread at a time.
    """

    def __init__(self, store: BlobStore, tmp: Path, fh: BinaryIO, max_bytes: int | None) -> None:
        self._store = store
        self._tmp = tmp
        self._fh: BinaryIO | None = fh
        self._max_bytes = max_bytes
        self._digest = hashlib.sha256()
        self.size = 0

    def write(self, data: bytes | bytearray | memoryview) -> None:
        """Append ``data``.

        Raises:
            TooLarge: past ``max_bytes`` (the writer is discarded).
            Unavailable: the write failed (the writer is discarded).
        """
        if self._fh is None:
            raise Unavailable("this blob writer is finished or discarded")
        size = self.size + memoryview(data).nbytes
        if self._max_bytes is not None and size > self._max_bytes:
            self.discard()
            raise TooLarge(f"artifact exceeds the limit of {self._max_bytes} bytes", details={"limit": self._max_bytes})
        try:
            self._fh.write(data)
        except OSError as exc:
            self.discard()
            raise Unavailable(f"cannot write blob under {self._store.root}: {exc}") from exc
        self._digest.update(data)
        self.size = size

    def finish(self) -> tuple[str, int]:
        """Make the bytes written a durable blob.

        Returns:
            ``(sha256, size)``.

        Raises:
            Unavailable: the filesystem refused (the writer is discarded).
        """
        if self._fh is None:
            raise Unavailable("this blob writer is finished or discarded")
        fh, self._fh = self._fh, None
        sha = self._digest.hexdigest()
        try:
            with fh:
                fh.flush()
                os.fsync(fh.fileno())
            self._store._install(self._tmp, sha, self.size)
            return sha, self.size
        except OSError as exc:
            raise Unavailable(f"cannot write blob under {self._store.root}: {exc}") from exc
        finally:
            with contextlib.suppress(FileNotFoundError):
                self._tmp.unlink()

    def discard(self) -> None:
        """Drop what was written (nothing, after :meth:`finish`)."""
        fh, self._fh = self._fh, None
        if fh is not None:
            fh.close()
            with contextlib.suppress(FileNotFoundError):
                self._tmp.unlink()


def _writer_alive(tmp_name: str) -> bool:
    """Whether the process named in a ``.tmp-<pid>-<token>`` file name may still be writing it."""
    pid_text = tmp_name[len(_TMP_PREFIX) :].split("-", 1)[0]
    if not pid_text.isdigit():
        return True  # not our naming: leave it to the age rule
    pid = int(pid_text)
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # alive but someone else's, or not a pid at all: leave it to the age rule
    return True


def make_dir_durably(path: str | os.PathLike[str]) -> None:
    """``mkdir -p path``, fsyncing the parent of every directory it creates.

    Raises:
        OSError: the directory cannot be created.
    """
    path = Path(path)
    missing: list[Path] = []
    probe = path
    while not probe.exists():
        missing.append(probe)
        if probe.parent == probe:
            break
        probe = probe.parent
    path.mkdir(parents=True, exist_ok=True)
    for created in reversed(missing):
        fsync_dir(created.parent)


class BlobStore:
    """Content-addressed bytes under one directory.

    Safe to use from many threads and processes at once: every write goes through its own
    uniquely named temporary file and an atomic rename.

    Args:
        root: Directory holding the shard directories; created if missing.

    Raises:
        Unavailable: ``root`` cannot be created.
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self._root = Path(root)
        try:
            make_dir_durably(self._root)
        except OSError as exc:
            raise Unavailable(f"cannot create blob directory {self._root}: {exc}") from exc

    @property
    def root(self) -> Path:
        return self._root

    def path_for(self, sha256: str) -> Path:
        """Where the blob ``sha256`` lives (whether or not it exists).

        Raises:
            Invalid: ``sha256`` is not 64 lowercase hex digits.
        """
        sha = validate_sha256(sha256)
        return self._root / sha[:2] / sha[2:]

    def exists(self, sha256: str) -> bool:
        """Whether a file is stored at ``sha256``'s address (its contents are not checked)."""
        return self.path_for(sha256).is_file()

    # --- writing ----------------------------------------------------------------------
    def put(self, data: bytes | bytearray | memoryview) -> tuple[str, int]:
        """Store ``data`` durably.

        Returns:
            ``(sha256, size)`` of ``data``.

        Raises:
            Invalid: ``data`` is not bytes-like.
            Unavailable: the filesystem refused the write (disk full, permissions).
        """
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise Invalid(f"blob data must be bytes, got {type(data).__name__}", details={"field": "artifact"})
        view = memoryview(data)
        return self.put_stream(view[i : i + CHUNK_BYTES] for i in range(0, view.nbytes, CHUNK_BYTES))

    def put_stream(
        self, stream: BinaryIO | Iterable[bytes | memoryview], *, max_bytes: int | None = None
    ) -> tuple[str, int]:
        """Store a large artifact without holding it in memory.

        Args:
            stream: A binary file object (read in 1 MiB chunks) or an iterable of byte chunks.
            max_bytes: Refuse streams longer than this.

        Returns:
            ``(sha256, size)`` of everything read.

        Raises:
            TooLarge: the stream exceeded ``max_bytes`` (nothing is stored).
            Unavailable: the filesystem refused the write.
        """
        chunks: Iterable[bytes | memoryview]
        if hasattr(stream, "read"):
            reader = stream  # type: ignore[assignment]
            chunks = iter(lambda: reader.read(CHUNK_BYTES), b"")  # type: ignore[union-attr]
        else:
            chunks = stream  # type: ignore[assignment]
        writer = self.writer(max_bytes=max_bytes)
        try:
            for chunk in chunks:
                writer.write(chunk)
            return writer.finish()
        finally:
            writer.discard()

    def writer(self, *, max_bytes: int | None = None) -> BlobWriter:
        """A blob written piece by piece (an upload in parts): see :class:`BlobWriter`.

        Raises:
            Unavailable: the temporary file cannot be made.
        """
        tmp = self._new_tmp(self._root / "incoming")
        try:
            fh = open(tmp, "wb")  # noqa: SIM115 -- the writer owns it until finish or discard
        except OSError as exc:
            raise Unavailable(f"cannot write blob under {self._root}: {exc}") from exc
        return BlobWriter(self, tmp, fh, max_bytes)

    def _install(self, tmp: Path, sha: str, size: int) -> None:
        """Move the complete, fsynced ``tmp`` to ``sha``'s address and make the rename durable
        (invariant 1), unless an intact copy is there already (invariant 4)."""
        if self._intact(sha, size):
            return
        final = self.path_for(sha)
        self._ensure_shard(final.parent)
        os.replace(tmp, final)
        fsync_dir(final.parent)

    def _ensure_shard(self, shard: Path) -> None:
        if shard.is_dir():
            return
        shard.mkdir(parents=True, exist_ok=True)
        # The new shard's own entry in root must be durable too, or the blob can vanish.
        fsync_dir(self._root)

    def _new_tmp(self, directory: Path) -> Path:
        directory.mkdir(parents=True, exist_ok=True)
        return directory / f"{_TMP_PREFIX}{os.getpid()}-{secrets.token_hex(8)}"

    def _intact(self, sha: str, size: int) -> bool:
        # Idempotent put: skip the write only when the stored copy is really good.
        path = self.path_for(sha)
        try:
            if path.stat().st_size != size:
                return False
        except OSError:
            return False
        return self.verify(sha) is None

    # --- reading ----------------------------------------------------------------------
    def get(self, sha256: str) -> bytes:
        """The bytes stored at ``sha256``, checked against the address.

        Raises:
            Invalid: malformed address.
            NotFound: no blob at that address.
            Corrupt: the stored bytes hash to something else (they are not returned).
        """
        path = self.path_for(sha256)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise NotFound(f"blob {sha256} is not stored", details={"sha256": sha256}) from None
        except OSError as exc:
            raise Unavailable(f"cannot read blob {sha256}: {exc}") from exc
        actual = hashlib.sha256(data).hexdigest()
        if actual != sha256:
            raise Corrupt(
                f"blob {sha256} is corrupt: its content hashes to {actual}",
                details={"sha256": sha256, "actual": actual},
            )
        return data

    def verify(self, sha256: str) -> str | None:
        """Check one blob without loading it whole.

        Returns:
            ``None`` when intact, else a one-line description of the problem.

        Raises:
            Invalid: malformed address.
        """
        path = self.path_for(sha256)
        digest = hashlib.sha256()
        try:
            with open(path, "rb") as fh:
                for chunk in iter(lambda: fh.read(CHUNK_BYTES), b""):
                    digest.update(chunk)
        except FileNotFoundError:
            return f"blob {sha256}: missing (expected at {path})"
        except OSError as exc:
            return f"blob {sha256}: unreadable: {exc}"
        actual = digest.hexdigest()
        if actual != sha256:
            return f"blob {sha256}: content hashes to {actual} (corrupt or tampered)"
        return None

    def sweep_temp(self, *, older_than_s: float = 3600.0, writer_gone: bool = False) -> int:
        """Delete temporary files a killed writer left behind.

        Args:
            older_than_s: Files untouched for this long go; a live writer's file is younger.
            writer_gone: Also remove younger files whose writer's pid (part of the name) names
                no live process on this host: what a start-up right after SIGKILL finds.

        Returns:
            How many files were removed.
        """
        cutoff = time.time() - older_than_s
        removed = 0
        for tmp in self._root.glob(f"*/{_TMP_PREFIX}*"):
            with contextlib.suppress(FileNotFoundError):
                if (writer_gone and not _writer_alive(tmp.name)) or tmp.stat().st_mtime < cutoff:
                    tmp.unlink()
                    removed += 1
        return removed

    def __iter__(self) -> Iterator[str]:
        """Addresses of every stored blob (temporary files excluded), in no particular order."""
        for shard in self._root.iterdir():
            if len(shard.name) != 2 or not shard.is_dir():
                continue
            for entry in shard.iterdir():
                sha = shard.name + entry.name
                if SHA256_PATTERN.fullmatch(sha):
                    yield sha
