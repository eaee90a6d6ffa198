"""Where the runtime sends trace records: the :class:`TraceSink` protocol and an in-memory fake.

The runtime depends on :class:`TraceSink` only; production passes a
:class:`~capevo.runtime.traces.writer.TraceWriter` (MCAP file), tests may pass a
:class:`MemoryTraceSink`.

Invariants:
1. :class:`MemoryTraceSink` accepts exactly what :class:`TraceWriter` accepts: each record
   must be of its method's type (else :class:`Invalid`) and must encode (it is run through the
   same codec; the sink refuses one that does not at once, the writer when it encodes it), and
   writing after ``close()`` raises :class:`Conflict`.
2. :class:`MemoryTraceSink` keeps records in write order; ``by_topic`` preserves that order.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from capevo.errors import Conflict, Invalid
from capevo.runtime.traces import codec
from capevo.runtime.traces.records import (
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    Intervention,
    PlanStep,
    TraceMetadata,
    TraceRecord,
    UnsafeStep,
)


@runtime_checkable
class TraceSink(Protocol):
    """Accepts the records of one run. Methods raise only :class:`capevo.errors.CapevoError`."""

    def write_plan_step(self, record: PlanStep) -> None: ...

    def write_invocation(self, record: EcmInvocation) -> None: ...

    def write_intervention(self, record: Intervention) -> None: ...

    def write_env_step(self, record: EnvStep) -> None: ...

    def write_unsafe_step(self, record: UnsafeStep) -> None: ...

    def write_episode_summary(self, record: EpisodeSummary) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


WRITE_METHODS: tuple[str, ...] = (
    "write_plan_step",
    "write_invocation",
    "write_intervention",
    "write_env_step",
    "write_unsafe_step",
    "write_episode_summary",
)
"""The :class:`TraceSink` methods that take a record (for wrappers that clock or count them)."""


def check_record(record: Any, expected: type[Any], method: str) -> None:
    """Raise :class:`Invalid` unless ``record`` is an ``expected`` (shared by the sinks)."""
    if not isinstance(record, expected):
        raise Invalid(
            f"{method} takes a {expected.__name__}, got {type(record).__name__}",
            details={"field": "record", "expected": expected.__name__},
        )


class MemoryTraceSink:
    """A :class:`TraceSink` that keeps records in a list; for tests and dry runs.

    Args:
        metadata: Optional metadata, kept for inspection.
    """

    def __init__(self, metadata: TraceMetadata | None = None) -> None:
        self.metadata = metadata
        self.records: list[TraceRecord] = []
        self.closed = False
        self.flushes = 0

    def _add(self, record: Any, expected: type[Any], method: str) -> None:
        if self.closed:
            raise Conflict(f"trace sink is closed; cannot {method}")
        check_record(record, expected, method)
        codec.encode(record)
        self.records.append(record)

    def write_plan_step(self, record: PlanStep) -> None:
        self._add(record, PlanStep, "write_plan_step")

    def write_invocation(self, record: EcmInvocation) -> None:
        self._add(record, EcmInvocation, "write_invocation")

    def write_intervention(self, record: Intervention) -> None:
        self._add(record, Intervention, "write_intervention")

    def write_env_step(self, record: EnvStep) -> None:
        self._add(record, EnvStep, "write_env_step")

    def write_unsafe_step(self, record: UnsafeStep) -> None:
        self._add(record, UnsafeStep, "write_unsafe_step")

    def write_episode_summary(self, record: EpisodeSummary) -> None:
        self._add(record, EpisodeSummary, "write_episode_summary")

    def flush(self) -> None:
        self.flushes += 1

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> MemoryTraceSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def by_topic(self, topic: str) -> list[TraceRecord]:
        """Records of one topic, in write order."""
        return [r for r in self.records if topic == r.TOPIC]

    @property
    def plan_steps(self) -> list[PlanStep]:
        return [r for r in self.records if isinstance(r, PlanStep)]

    @property
    def invocations(self) -> list[EcmInvocation]:
        return [r for r in self.records if isinstance(r, EcmInvocation)]

    @property
    def interventions(self) -> list[Intervention]:
        return [r for r in self.records if isinstance(r, Intervention)]

    @property
    def env_steps(self) -> list[EnvStep]:
        return [r for r in self.records if isinstance(r, EnvStep)]

    @property
    def unsafe_steps(self) -> list[UnsafeStep]:
        return [r for r in self.records if isinstance(r, UnsafeStep)]

    @property
    def episode_summaries(self) -> list[EpisodeSummary]:
        return [r for r in self.records if isinstance(r, EpisodeSummary)]
