"""Lenient sequential MCAP reading: every good record up to the first bad one.

A worker killed mid-run leaves an MCAP with no summary, no footer and possibly half a chunk
at the end. The mcap package's readers either need the footer (seeking reader) or raise on
the first short read (stream reader), losing the records already parsed in a chunk. This
scanner frames each record itself (opcode + length, checked against the file size before
reading), parses the body with the mcap package's record classes, decompresses and
CRC-checks a chunk as a whole, and yields its records only when the whole chunk is good.

Invariants:
1. The scanner never reads past the end of the file and never allocates more than the
   bytes left in the file for one record, whatever a corrupt length field says.
2. The records of a chunk are yielded all or none: none when the chunk is truncated, fails
   to decompress, fails its CRC or holds a malformed record.
3. After iteration :attr:`McapScan.result` says whether the file was complete (footer and
   closing magic seen) and, if not, why scanning stopped and at which byte offset; in strict
   mode an incomplete or corrupt file raises :class:`Corrupt` instead of stopping.
4. A file that does not start with the MCAP magic raises :class:`Invalid`; a missing file
   raises :class:`NotFound`, an unreadable one :class:`Forbidden`.
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import CRCValidationError, breakup_chunk

from capevo.errors import Corrupt, Forbidden, Invalid, NotFound
from capevo.runtime.traces.mcapfile import MAGIC

_RECORD_HEADER = struct.Struct("<BQ")
_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4

# What a damaged chunk or record can raise from the mcap parsers and the decompressors
# (lz4 raises RuntimeError, zstandard raises ZstdError, a subclass of Exception).
_PARSE_ERRORS: tuple[type[BaseException], ...] = (
    McapError,
    CRCValidationError,
    struct.error,
    ValueError,
    UnicodeDecodeError,
    RuntimeError,
    MemoryError,
    EOFError,
)
try:
    import zstandard

    _PARSE_ERRORS = (*_PARSE_ERRORS, zstandard.ZstdError)
except ImportError:  # pragma: no cover - zstandard ships with mcap's usual installs
    pass

RECOVER_HINT = "salvage what it holds with `capevo trace recover FILE`"

_BODY_PARSERS = {
    Opcode.HEADER: Header.read,
    Opcode.METADATA: Metadata.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
}


@dataclass(frozen=True, slots=True, kw_only=True)
class ScanResult:
    """How a scan ended."""

    complete: bool
    """The file ended with a footer and the closing magic."""
    reason: str
    """``"complete"``, or why scanning stopped (truncated or corrupt record, and where)."""
    good_bytes: int
    """Offset just past the last record that parsed."""
    size: int
    """File size in bytes."""
    chunks: int
    """Chunks that decoded (or were skipped when chunks are not decoded)."""


def open_trace_file(path: str | os.PathLike[str]) -> BinaryIO:
    """Open ``path`` for reading, mapping OS errors to capevo errors (invariant 4)."""
    p = Path(path)
    try:
        return p.open("rb")
    except FileNotFoundError:
        raise NotFound(f"trace file not found: {p}", details={"path": str(p)}) from None
    except IsADirectoryError:
        raise Invalid(f"trace path is a directory, not an MCAP file: {p}", details={"path": str(p)}) from None
    except PermissionError:
        raise Forbidden(f"no permission to read trace file: {p}", details={"path": str(p)}) from None
    except OSError as exc:
        raise Invalid(f"cannot open trace file {p}: {exc.strerror or exc}", details={"path": str(p)}) from None


def _check_magic(f: BinaryIO, path: Path) -> None:
    magic = f.read(len(MAGIC))
    if magic != MAGIC:
        what = "an empty file" if not magic else "bad magic bytes"
        raise Invalid(f"not an MCAP file ({what}): {path}", details={"path": str(path)})


def has_footer(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` ends with a footer record and the closing magic (a finished file).

    Raises:
        NotFound, Forbidden, Invalid: as :func:`open_trace_file`; Invalid for a non-MCAP file.
    """
    p = Path(path)
    with open_trace_file(p) as f:
        _check_magic(f, p)
        size = os.fstat(f.fileno()).st_size
        if size < 2 * len(MAGIC) + _FOOTER_RECORD_SIZE:
            return False
        f.seek(size - len(MAGIC) - _FOOTER_RECORD_SIZE)
        tail = f.read(_FOOTER_RECORD_SIZE + len(MAGIC))
    opcode, length = _RECORD_HEADER.unpack_from(tail)
    return opcode == Opcode.FOOTER and length == _FOOTER_RECORD_SIZE - 9 and tail[-len(MAGIC) :] == MAGIC


class McapScan:
    """Iterate the good records of one MCAP file in file order.

    Yields :class:`Header`, :class:`Metadata`, :class:`Schema`, :class:`Channel`,
    :class:`Message` and :class:`Attachment` records; indexes, statistics and other summary
    records are skipped.

    Args:
        path: The MCAP file.
        decode_chunks: Decompress chunks and yield their records; False skips chunks (fast,
            for metadata only).
        strict: Raise :class:`Corrupt` on a damaged or unfinished file instead of stopping.

    Raises:
        NotFound, Forbidden, Invalid: when iteration starts (see :func:`open_trace_file`).
        Corrupt: in strict mode, at the first bad record or at an unfinished end.
    """

    def __init__(self, path: str | os.PathLike[str], *, decode_chunks: bool = True, strict: bool = False) -> None:
        self.path = Path(path)
        self.decode_chunks = decode_chunks
        self.strict = strict
        self.result: ScanResult | None = None

    def __iter__(self) -> Iterator[McapRecord]:
        with open_trace_file(self.path) as f:
            _check_magic(f, self.path)
            size = os.fstat(f.fileno()).st_size
            yield from self._records(f, size)

    def _stop(self, *, complete: bool, reason: str, offset: int, size: int, chunks: int) -> None:
        self.result = ScanResult(complete=complete, reason=reason, good_bytes=offset, size=size, chunks=chunks)
        if self.strict and not complete:
            raise Corrupt(
                f"trace file {self.path} is damaged or unfinished ({reason}); {RECOVER_HINT}",
                details={"path": str(self.path), "offset": offset},
            )

    def _records(self, f: BinaryIO, size: int) -> Iterator[McapRecord]:
        offset = len(MAGIC)
        chunks = 0
        while True:
            head = f.read(_RECORD_HEADER.size)
            if not head:
                self._stop(complete=False, reason="file ends without a footer", offset=offset, size=size, chunks=chunks)
                return
            if len(head) < _RECORD_HEADER.size:
                reason = f"truncated record at offset {offset}"
                self._stop(complete=False, reason=reason, offset=offset, size=size, chunks=chunks)
                return
            opcode, length = _RECORD_HEADER.unpack(head)
            body_start = offset + _RECORD_HEADER.size
            if opcode == 0 or length > size - body_start:
                what = "invalid opcode 0" if opcode == 0 else f"truncated {_opcode_name(opcode)} record"
                self._stop(complete=False, reason=f"{what} at offset {offset}", offset=offset, size=size, chunks=chunks)
                return
            if opcode == Opcode.CHUNK and not self.decode_chunks:
                f.seek(length, io.SEEK_CUR)
                offset = body_start + length
                chunks += 1
                continue
            body = f.read(length)
            try:
                records = self._parse(opcode, body)
            except _PARSE_ERRORS as exc:
                self._stop(
                    complete=False,
                    reason=f"corrupt {_opcode_name(opcode)} record at offset {offset}: {type(exc).__name__}: {exc}",
                    offset=offset,
                    size=size,
                    chunks=chunks,
                )
                return
            offset = body_start + length
            if opcode == Opcode.CHUNK:
                chunks += 1
            for record in records:
                if isinstance(record, Footer):
                    complete = f.read(len(MAGIC)) == MAGIC
                    reason = "complete" if complete else f"missing closing magic after the footer at offset {offset}"
                    self._stop(complete=complete, reason=reason, offset=offset, size=size, chunks=chunks)
                    return
                if not isinstance(record, DataEnd):
                    yield record

    @staticmethod
    def _parse(opcode: int, body: bytes) -> list[McapRecord]:
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == Opcode.CHUNK:
            return breakup_chunk(Chunk.read(stream), validate_crc=True)
        if opcode == Opcode.MESSAGE:
            return [Message.read(stream, len(body))]
        parser = _BODY_PARSERS.get(opcode)  # type: ignore[call-overload]
        return [] if parser is None else [parser(stream)]


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode-0x{opcode:02x}"
