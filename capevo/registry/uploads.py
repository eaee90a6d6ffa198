"""The server's uploads in progress: artifacts that arrive in parts (issue 21).

Why parts: zenoh-python hands a query's payload to Python in one call that holds the GIL
(``ZBytes.to_bytes()``, about 28 ms per 64 MiB on a 2-core EPYC), and every resolve the server
answers meanwhile waits for it. So :meth:`capevo.registry.client.Client.publish` sends an
artifact larger than :data:`PART_BYTES` as a run of ``publish`` queries of at most that size,
each header carrying a :class:`~capevo.registry.wire.UploadPart` (and only the first the
spec, which is kept here). Each part goes straight into a blob writer
(:meth:`LocalRegistry.artifact_writer`: a temporary file in the blob store, hashed as it
grows), so the bytes reach the disk once; the last part's arrival publishes them. Nothing is
visible before then, and a server that dies mid-upload loses only the upload (the client sends
it again; the registry sweeps the temporary file when it next opens).

Invariants:
1. A part is taken only at the offset where its upload ends (the first at 0, with the spec),
   within the upload's ``total``, for the same ECM name, and only from the user who sent the
   first part; anything else is refused and leaves the upload as it was.
2. :meth:`Uploads.add` returns the finished writer's upload (bytes, spec, name) exactly once,
   when the last byte arrives, and the upload is then gone.
3. At most ``per_owner`` uploads of one user are in progress: a user's next first part drops
   that user's least recently touched upload (a client sends one upload at a time per thread,
   so the oldest has been given up), and no one else's. At most ``max_uploads`` are in
   progress in all; beyond that a first part is refused ``unavailable``. One untouched for
   ``stale_s`` is dropped (each part waits seconds, not minutes).
4. A dropped upload's writer is discarded; :meth:`Uploads.close` discards them all.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from capevo.errors import Conflict, Invalid, NotFound, TooLarge, Unavailable
from capevo.records import PublishSpec
from capevo.registry.wire import UploadPart
from capevo.storage.blobs import BlobWriter

log = logging.getLogger(__name__)

__all__ = ["MAX_UPLOADS", "PART_BYTES", "PER_OWNER", "STALE_S", "Upload", "Uploads"]

PART_BYTES = 1 << 18
"""Largest part a client sends. Measured on a 2-core EPYC (``bench_resolve_clients.py``), with
parts of 128 KiB to 4 MiB: resolves during back-to-back 64 MiB publishes had p99 1.3, 1.6, 2.6,
3.7, 5.7 and 5.3 ms; 256 KiB keeps the publish rate of one payload (14-15 in 6 s, 12 at
128 KiB) and the resolves' tail below that of raw 64 MiB Zenoh transfers."""
MAX_UPLOADS = 64
PER_OWNER = 4
STALE_S = 600.0


@dataclass(slots=True)
class Upload:
    """One upload in progress: its blob writer and the first part's name and spec."""

    writer: BlobWriter
    name: str
    spec: PublishSpec
    total: int
    touched: float


class Uploads:
    """The uploads in progress on one server.

    Args:
        new_writer: Makes the blob writer of a new upload (``LocalRegistry.artifact_writer``).
        max_artifact_bytes: Largest ``total`` accepted.
        max_uploads: Uploads in progress at once; more get ``unavailable``.
        per_owner: Uploads of one user in progress at once; a next one drops that user's oldest.
        stale_s: Seconds after which an untouched upload is dropped.
    """

    def __init__(
        self,
        new_writer: Callable[[], BlobWriter],
        *,
        max_artifact_bytes: int,
        max_uploads: int = MAX_UPLOADS,
        per_owner: int = PER_OWNER,
        stale_s: float = STALE_S,
    ) -> None:
        self._new_writer = new_writer
        self._max_artifact_bytes = max_artifact_bytes
        self._max_uploads = max_uploads
        self._per_owner = per_owner
        self._stale_s = stale_s
        self._uploads: dict[tuple[str, str], Upload] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._uploads)

    def add(
        self, owner: str, name: str, part: UploadPart, data: bytes, spec: PublishSpec | None = None
    ) -> Upload | None:
        """Take ``data`` as ``part`` of ``owner``'s upload of an artifact for ``name``.

        Args:
            spec: The first part's spec (kept for the publish); later parts carry none.

        Returns:
            The upload when this part completes it (the caller publishes its writer, which
            holds every byte; the upload is then gone here), else None.

        Raises:
            TooLarge: ``part.total`` is over the limit.
            Invalid: an empty part, one that runs past ``part.total``, or a first part without
                a spec.
            NotFound: a later part of an upload not in progress (never begun, dropped, or
                begun on a server that has since restarted).
            Conflict: a part not at the offset where its upload ends, with another total, or
                for another ECM name.
            Unavailable: too many uploads in progress, or the disk refused the bytes.
        """
        if part.total > self._max_artifact_bytes:
            raise TooLarge(
                f"artifact is {part.total} bytes; the limit is {self._max_artifact_bytes}",
                details={"size": part.total, "limit": self._max_artifact_bytes},
            )
        end = part.offset + len(data)
        if not data:
            raise Invalid("part carries no bytes", details={"field": "<payload>"})
        if end > part.total:
            raise Invalid(
                f"part ends at byte {end}, past its upload's total {part.total}", details={"field": "part.total"}
            )
        if part.first and spec is None:
            raise Invalid("the first part of an upload carries the spec", details={"field": "spec"})
        key = (owner, part.upload)
        now = time.monotonic()
        with self._lock:
            self._drop_stale(now)
            upload = self._uploads.get(key)
            if part.first:
                assert spec is not None  # checked above
                if upload is not None:  # the client starts again (a lost reply): from scratch
                    self._discard(key)
                mine = sorted((u.touched, k) for k, u in self._uploads.items() if k[0] == owner)
                if len(mine) >= self._per_owner:
                    log.info("dropped upload %s of %s: %d newer ones are in progress", mine[0][1][1], owner, len(mine))
                    self._discard(mine[0][1])
                elif len(self._uploads) >= self._max_uploads:
                    raise Unavailable(f"registry busy: {self._max_uploads} uploads in progress; retry shortly")
                upload = Upload(self._new_writer(), name, spec, part.total, now)
                self._uploads[key] = upload
            elif upload is None:
                raise NotFound(
                    f"upload {part.upload}: none in progress (never begun, dropped after {self._stale_s:.0f} s idle "
                    "or for newer ones, or the registry restarted); send the artifact again from offset 0",
                    details={"upload": part.upload},
                )
            elif part.offset != upload.writer.size or part.total != upload.total or name != upload.name:
                raise Conflict(
                    f"upload {part.upload}: expected the part of {upload.name!r} at offset {upload.writer.size} of "
                    f"{upload.total}, got one of {name!r} at offset {part.offset} of {part.total}",
                    details={"upload": part.upload, "expected_offset": upload.writer.size},
                )
            try:
                upload.writer.write(data)
            except (TooLarge, Unavailable):
                self._discard(key)
                raise
            upload.touched = now
            if end < upload.total:
                return None
            del self._uploads[key]
            return upload

    def close(self) -> None:
        """Drop every upload in progress."""
        with self._lock:
            for key in list(self._uploads):
                self._discard(key)

    def _drop_stale(self, now: float) -> None:
        for key in [k for k, u in self._uploads.items() if now - u.touched > self._stale_s]:
            log.info("dropped upload %s of %s: idle over %.0f s", key[1], key[0], self._stale_s)
            self._discard(key)

    def _discard(self, key: tuple[str, str]) -> None:
        upload = self._uploads.pop(key, None)
        if upload is not None:
            upload.writer.discard()
