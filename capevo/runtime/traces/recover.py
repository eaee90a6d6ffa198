"""Salvage the trace of a crashed worker into a finished MCAP file.

A worker killed with SIGKILL leaves a file with no summary and no footer, possibly ending in
half a chunk. :func:`recover` reads it with the lenient scanner (every good record up to
the first bad one) and writes a finished copy: same header profile, same metadata records
plus a ``capevo.recovery`` record saying what was salvaged, same schemas, channels and
messages (with their log/publish times and sequence numbers).

Invariants:
1. The output holds every message the scanner yields from the input, in input order, with
   identical topic, payload, log time, publish time and sequence; nothing else but a
   ``capevo.recovery`` metadata record is added.
2. The output is a finished MCAP (readable by ``mcap.reader.make_reader``, with summary and
   footer), written atomically: a temporary file in the same directory is renamed over the
   target only when complete.
3. The input is never modified; the output path must differ from it, and an existing output
   is replaced only with ``overwrite=True`` (:class:`Conflict` otherwise).
4. Recovering a finished file yields an equivalent finished file (``complete`` is true).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.records import Attachment, Channel, Header, McapRecord, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from capevo.errors import Conflict, Invalid, Unavailable
from capevo.runtime.traces.scan import McapScan

RECOVERY_METADATA = "capevo.recovery"


@dataclass(frozen=True, slots=True, kw_only=True)
class RecoverReport:
    """What :func:`recover` salvaged."""

    source: str
    output: str
    complete: bool
    """The source was already a finished file."""
    reason: str
    """Why reading the source stopped (``"complete"`` for a finished file)."""
    messages: int
    messages_by_topic: Mapping[str, int] = field(default_factory=dict)
    chunks: int = 0
    metadata_records: int = 0
    dropped_messages: int = 0
    """Messages whose channel record was lost (they cannot be decoded, so are not copied)."""
    good_bytes: int = 0
    source_bytes: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "output": self.output,
            "complete": self.complete,
            "reason": self.reason,
            "messages": self.messages,
            "messages_by_topic": dict(self.messages_by_topic),
            "chunks": self.chunks,
            "metadata_records": self.metadata_records,
            "dropped_messages": self.dropped_messages,
            "good_bytes": self.good_bytes,
            "source_bytes": self.source_bytes,
        }


def default_output(path: str | os.PathLike[str]) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap`` beside it."""
    p = Path(path)
    return p.with_name(f"{p.stem}.recovered.mcap")


def recover(
    path: str | os.PathLike[str], out_path: str | os.PathLike[str], *, overwrite: bool = False
) -> RecoverReport:
    """Write a finished copy of everything readable in the (possibly crashed) trace ``path``.

    Args:
        path: The source MCAP file, finished or not.
        out_path: Where to write the finished copy.
        overwrite: Replace ``out_path`` if it exists.

    Returns:
        A :class:`RecoverReport` with message counts and why reading stopped.

    Raises:
        NotFound: no source file. Invalid: the source is not an MCAP file, or ``out_path``
            is the source. Conflict: ``out_path`` exists and ``overwrite`` is false.
        Unavailable: the output cannot be written.
    """
    src = Path(path)
    dst = Path(out_path)
    if dst.exists() and src.exists() and dst.resolve() == src.resolve():
        raise Invalid(f"recover output must differ from the source: {dst}", details={"field": "out_path"})
    if dst.exists() and not overwrite:
        raise Conflict(
            f"recover output already exists: {dst} (pass overwrite to replace it)", details={"path": str(dst)}
        )
    scan = McapScan(src)
    records = iter(scan)
    # Pull the first record before creating anything, so a missing or non-MCAP source
    # fails without leaving an output behind.
    first = next(records, None)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with tmp.open("wb") as f:
            report = _copy(src, dst, first, records, scan, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, dst)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise Unavailable(f"cannot write recovered trace {dst}: {exc.strerror or exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return report


def _copy(
    src: Path, dst: Path, first: McapRecord | None, records: Iterator[McapRecord], scan: McapScan, f: BinaryIO
) -> RecoverReport:
    writer = Writer(f, compression=CompressionType.LZ4)
    header = first if isinstance(first, Header) else Header(profile="", library="")
    writer.start(profile=header.profile, library=(header.library + "; recovered by capevo").lstrip("; "))
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    channel_topics: dict[int, str] = {}
    by_topic: dict[str, int] = {}
    metadata_records = 0
    dropped = 0
    messages = 0
    pending = [first] if first is not None and not isinstance(first, Header) else []
    for record in _chain(pending, records):
        if isinstance(record, Metadata):
            writer.add_metadata(record.name, dict(record.metadata))
            metadata_records += 1
        elif isinstance(record, Schema):
            if record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            if record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), dict(record.metadata)
                )
                channel_topics[record.id] = record.topic
        elif isinstance(record, Message):
            new_id = channel_ids.get(record.channel_id)
            if new_id is None:
                dropped += 1
                continue
            writer.add_message(
                channel_id=new_id,
                log_time=record.log_time,
                data=record.data,
                publish_time=record.publish_time,
                sequence=record.sequence,
            )
            messages += 1
            topic = channel_topics[record.channel_id]
            by_topic[topic] = by_topic.get(topic, 0) + 1
        elif isinstance(record, Attachment):
            writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
    result = scan.result
    if result is None:  # pragma: no cover - the loop above drained the scan, which always sets it
        raise RuntimeError("scan ended without a result")
    writer.add_metadata(
        RECOVERY_METADATA,
        {
            "source": str(src),
            "source_complete": json.dumps(result.complete),
            "stop_reason": result.reason,
            "messages": str(messages),
            "dropped_messages": str(dropped),
            "recovered_at": f"{time.time():.3f}",
        },
    )
    writer.finish()
    return RecoverReport(
        source=str(src),
        output=str(dst),
        complete=result.complete,
        reason=result.reason,
        messages=messages,
        messages_by_topic=by_topic,
        chunks=result.chunks,
        metadata_records=metadata_records,
        dropped_messages=dropped,
        good_bytes=result.good_bytes,
        source_bytes=result.size,
    )


def _chain(first: list[McapRecord], rest: Iterator[McapRecord]) -> Iterator[McapRecord]:
    yield from first
    yield from rest
