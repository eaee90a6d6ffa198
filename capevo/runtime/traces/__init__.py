"""MCAP run traces: JSON-schema channels Foxglove opens, crash-safe writing, salvage, export.

Topics (schemas in :mod:`capevo.runtime.traces.records`):

- ``/plan``                    :class:`PlanStep`
- ``/ecm/invocation``          :class:`EcmInvocation`
- ``/governance/intervention`` :class:`Intervention`
- ``/env/step``                :class:`EnvStep`
- ``/safety/unsafe``           :class:`UnsafeStep` (a step the safety monitor graded unsafe)
- ``/episode/summary``         :class:`EpisodeSummary`

Write with :class:`TraceWriter` (or inject :class:`MemoryTraceSink` in tests), read with
:class:`TraceReader`, salvage a crashed worker's file with :func:`recover`, and hand
experience to learners with :func:`export_transitions`.
"""

from __future__ import annotations

from capevo.runtime.traces.export import (
    EXPORT_FORMATS,
    EpisodeSelection,
    Transitions,
    export_transitions,
    iter_env_steps,
    parse_episodes,
)
from capevo.runtime.traces.reader import TraceReader
from capevo.runtime.traces.records import (
    NOT_ENFORCED_PREFIX,
    PACKAGES,
    TRACE_FORMAT,
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    FloatVector,
    Intervention,
    Outcome,
    PlanStep,
    TraceMetadata,
    TraceRecord,
    UnsafeStep,
    package_versions,
    record_type,
    topics,
)
from capevo.runtime.traces.recover import RecoverReport, default_output, recover
from capevo.runtime.traces.sink import MemoryTraceSink, TraceSink
from capevo.runtime.traces.summary import EpisodeRow, TraceSummary, summarize
from capevo.runtime.traces.writer import (
    COMPRESSIONS,
    DEFAULT_COMPRESSION,
    TraceWriter,
    check_compression,
)

__all__ = [
    "COMPRESSIONS",
    "DEFAULT_COMPRESSION",
    "EXPORT_FORMATS",
    "NOT_ENFORCED_PREFIX",
    "PACKAGES",
    "TRACE_FORMAT",
    "EcmInvocation",
    "EnvStep",
    "EpisodeRow",
    "EpisodeSelection",
    "EpisodeSummary",
    "FloatVector",
    "Intervention",
    "MemoryTraceSink",
    "Outcome",
    "PlanStep",
    "RecoverReport",
    "TraceMetadata",
    "TraceReader",
    "TraceRecord",
    "TraceSink",
    "TraceSummary",
    "TraceWriter",
    "Transitions",
    "UnsafeStep",
    "check_compression",
    "default_output",
    "export_transitions",
    "iter_env_steps",
    "package_versions",
    "parse_episodes",
    "record_type",
    "recover",
    "summarize",
    "topics",
]
