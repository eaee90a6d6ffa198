"""TraceReader: typed records and metadata back out of a trace file.

Reading is sequential (file order = write order), through the lenient scanner of
:mod:`capevo.runtime.traces.scan`, so the same code reads finished files and, when asked,
the unfinished file of a crashed worker.

Invariants:
1. Records come back in the order they were written, typed by their topic's record class.
2. By default an unfinished file (no footer) raises :class:`Corrupt` naming
   ``capevo trace recover`` when the reader is opened, and a file damaged in the middle
   raises it when reading reaches the damage. With ``allow_incomplete=True`` every record up
   to the damage is returned and :attr:`TraceReader.scan_result` says why reading stopped.
3. Messages on channels whose topic is not a trace topic, or whose encoding is not
   ``json``, are skipped, not errors (other tools may add channels to a trace file).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

from mcap.records import Channel, Message, Metadata

from capevo.errors import Corrupt
from capevo.runtime.traces import codec
from capevo.runtime.traces.records import (
    MESSAGE_ENCODING,
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    Intervention,
    PlanStep,
    TraceMetadata,
    TraceRecord,
    UnsafeStep,
    record_type,
)
from capevo.runtime.traces.records import topics as all_topics
from capevo.runtime.traces.scan import RECOVER_HINT, McapScan, ScanResult, has_footer

R = TypeVar("R")


class TraceReader:
    """Read one trace file.

    Args:
        path: The MCAP file.
        allow_incomplete: Read an unfinished or damaged file up to the damage instead of
            raising :class:`Corrupt`.

    Raises:
        NotFound: no such file. Invalid: not an MCAP file. Forbidden: unreadable.
        Corrupt: unfinished or damaged and ``allow_incomplete`` is false.
    """

    def __init__(self, path: str | os.PathLike[str], *, allow_incomplete: bool = False) -> None:
        self.path = Path(path)
        self.allow_incomplete = allow_incomplete
        self.complete = has_footer(self.path)
        if not self.complete and not allow_incomplete:
            raise Corrupt(
                f"trace file {self.path} is unfinished (no footer; the writer was killed or is still "
                f"writing); {RECOVER_HINT}, or read it with allow_incomplete=True",
                details={"path": str(self.path)},
            )
        self.scan_result: ScanResult | None = None

    def __enter__(self) -> TraceReader:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def _scan(self, *, decode_chunks: bool = True) -> McapScan:
        return McapScan(self.path, decode_chunks=decode_chunks, strict=not self.allow_incomplete)

    def metadata_records(self) -> dict[str, dict[str, str]]:
        """Every MCAP metadata record: ``{name: {key: value}}`` (a later duplicate name wins)."""
        out: dict[str, dict[str, str]] = {}
        for record in self._scan(decode_chunks=False):
            if isinstance(record, Metadata):
                out[record.name] = dict(record.metadata)
        return out

    def metadata(self) -> TraceMetadata:
        """The run's :class:`TraceMetadata`.

        Raises:
            Corrupt: the file has no ``capevo.run`` metadata or it does not parse.
        """
        return TraceMetadata.from_mcap(self.metadata_records())

    def records(self, topics: Iterable[str] | None = None) -> Iterator[TraceRecord]:
        """Records of the given topics (all trace topics by default), in write order.

        Raises:
            Invalid: a requested topic is not a trace topic.
            Corrupt: a message does not decode, or (strict mode) the file is damaged.
        """
        if isinstance(topics, str):
            topics = [topics]
        wanted = set(all_topics() if topics is None else topics)
        for topic in wanted:
            record_type(topic)
        channels: dict[int, str] = {}
        scan = self._scan()
        for record in scan:
            if isinstance(record, Channel):
                if record.topic in wanted and record.message_encoding == MESSAGE_ENCODING:
                    channels[record.id] = record.topic
            elif isinstance(record, Message):
                topic = channels.get(record.channel_id)
                if topic is not None:
                    yield codec.decode(topic, record.data)
        self.scan_result = scan.result

    def _typed(self, cls: type[R]) -> Iterator[R]:
        yield from self.records([cls.TOPIC])  # type: ignore[attr-defined,misc]

    def plan_steps(self) -> Iterator[PlanStep]:
        return self._typed(PlanStep)

    def invocations(self) -> Iterator[EcmInvocation]:
        return self._typed(EcmInvocation)

    def interventions(self) -> Iterator[Intervention]:
        return self._typed(Intervention)

    def env_steps(self) -> Iterator[EnvStep]:
        return self._typed(EnvStep)

    def unsafe_steps(self) -> Iterator[UnsafeStep]:
        return self._typed(UnsafeStep)

    def episode_summaries(self) -> Iterator[EpisodeSummary]:
        return self._typed(EpisodeSummary)

    def topic_counts(self) -> dict[str, int]:
        """Messages per trace topic (decodes nothing but the MCAP framing)."""
        counts = dict.fromkeys(all_topics(), 0)
        channels: dict[int, str] = {}
        for record in self._scan():
            if isinstance(record, Channel) and record.topic in counts:
                channels[record.id] = record.topic
            elif isinstance(record, Message) and record.channel_id in channels:
                counts[channels[record.channel_id]] += 1
        return counts
