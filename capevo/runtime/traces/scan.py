"""Lenient sequential MCAP reading: every good record up to the first bad one.

A worker killed mid-run leaves an MCAP with no summary, no footer and possibly half a chunk
at the end. The ``mcap`` library's :class:`~mcap.stream_reader.StreamReader` reads records in
file order and raises where one is truncated or corrupt; this module runs it with chunk and CRC
checks on and stops there instead. What it adds to the library, which has none of it: where
and why reading stopped (:class:`ScanResult`), whether a file is finished without reading it
(:func:`has_footer`), and capevo's errors for a file that cannot be opened.

Invariants:
1. The scanner never reads past the end of the file and never loads a record longer than the
   file, whatever a corrupt length field says.
2. The records of a chunk are yielded all or none: none when the chunk is truncated, fails
   to decompress, fails its CRC or holds a malformed record.
3. After iteration :attr:`McapScan.result` says whether the file was complete (footer and
   closing magic seen) and, if not, why scanning stopped and at which byte offset; in strict
   mode an incomplete or corrupt file raises :class:`Corrupt` instead of stopping.
4. A file that does not start with the MCAP magic raises :class:`Invalid`; a missing file
   raises :class:`NotFound`, an unreadable one :class:`Forbidden`.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Footer, Header, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import MCAP0_MAGIC as MAGIC

from capevo.errors import Corrupt, Forbidden, Invalid, NotFound

_RECORD_HEADER = struct.Struct("<BQ")
_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4

# What a damaged record can raise from the mcap parsers and the decompressors (lz4 raises
# RuntimeError; zstandard's ZstdError is added below).
_PARSE_ERRORS: tuple[type[BaseException], ...] = (
    McapError,
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

_YIELDED = (Header, Metadata, Schema, Channel, Message, Attachment)
"""What a scan yields; indexes, statistics and other summary records are skipped."""

RECOVER_HINT = "salvage what it holds with `capevo trace recover FILE`"


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
        decode_chunks: Decompress chunks and yield their records; False skips them (for
            metadata only).
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
            yield from self._records(f, os.fstat(f.fileno()).st_size)

    def _records(self, f: BinaryIO, size: int) -> Iterator[McapRecord]:
        # A length beyond the file fails at once (invariant 1); the magic is checked above.
        records = StreamReader(f, skip_magic=True, emit_chunks=True, record_size_limit=size).records
        good, chunks, footer = f.tell(), 0, False
        while True:
            try:
                record = next(records)
                inner: list[McapRecord] = [record]
                if isinstance(record, Chunk):
                    inner = breakup_chunk(record, validate_crc=True) if self.decode_chunks else []
            except StopIteration:  # the reader stops after the footer and the closing magic
                self._stop(ScanResult(complete=True, reason="complete", good_bytes=size, size=size, chunks=chunks))
                return
            except _PARSE_ERRORS as exc:
                reason = (
                    f"missing closing magic after the footer at offset {good}"
                    if footer
                    else self._why(f, good, size, exc)
                )
                self._stop(ScanResult(complete=False, reason=reason, good_bytes=good, size=size, chunks=chunks))
                return
            good = f.tell()
            chunks += isinstance(record, Chunk)
            footer = isinstance(record, Footer)
            for r in inner:
                if isinstance(r, _YIELDED):
                    yield r

    @staticmethod
    def _why(f: BinaryIO, offset: int, size: int, exc: BaseException) -> str:
        """Why the record at ``offset`` did not parse, for :attr:`ScanResult.reason`."""
        if offset == size:
            return "file ends without a footer"
        f.seek(offset)
        head = f.read(_RECORD_HEADER.size)
        if len(head) < _RECORD_HEADER.size:
            return f"truncated record at offset {offset}"
        opcode, length = _RECORD_HEADER.unpack(head)
        if opcode == 0:
            return f"invalid opcode 0 at offset {offset}"
        name = _opcode_name(opcode)
        if length > size - offset - _RECORD_HEADER.size:
            return f"truncated {name} record at offset {offset}"
        return f"corrupt {name} record at offset {offset}: {type(exc).__name__}: {exc}"

    def _stop(self, result: ScanResult) -> None:
        self.result = result
        if self.strict and not result.complete:
            raise Corrupt(
                f"trace file {self.path} is damaged or unfinished ({result.reason}); {RECOVER_HINT}",
                details={"path": str(self.path), "offset": result.good_bytes},
            )


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode-0x{opcode:02x}"
