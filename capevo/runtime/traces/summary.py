"""Per-episode overview of a trace file (what ``capevo trace summary`` prints).

An episode with an ``/episode/summary`` record is reported from it. An episode that has env
steps but no summary (the worker died mid-episode) is reported from its steps and
interventions, marked ``finished=False``, with success unknown.

Invariants:
1. Episodes appear once each, in order of first appearance in the file.
2. A finished episode's row equals its summary record (reward, steps, interventions,
   success, unsafe steps, seed, duration).
3. An unfinished episode's reward is the sum of its step rewards, its steps the number of
   its env steps, its interventions the number of its intervention records.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capevo.runtime.traces.reader import TraceReader
from capevo.runtime.traces.records import EnvStep, EpisodeSummary, Intervention, TraceMetadata


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeRow:
    """One episode of a trace."""

    episode: int
    finished: bool
    success: bool | None
    total_reward: float
    steps: int
    interventions: int
    unsafe_steps: int | None = None
    seed: int | None = None
    duration_s: float | None = None
    capability_set: Mapping[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "episode": self.episode,
            "finished": self.finished,
            "success": self.success,
            "total_reward": _json_float(self.total_reward),
            "steps": self.steps,
            "interventions": self.interventions,
            "unsafe_steps": self.unsafe_steps,
            "seed": self.seed,
            "duration_s": _json_float(self.duration_s),
            "capability_set": dict(sorted(self.capability_set.items())),
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class TraceSummary:
    """The episodes of one trace file, with its metadata."""

    path: str
    metadata: TraceMetadata
    complete: bool
    """The file is finished (False: the worker crashed; the rows cover what survived)."""
    episodes: tuple[EpisodeRow, ...]
    topic_counts: Mapping[str, int]

    @property
    def success_rate(self) -> float | None:
        known = [e.success for e in self.episodes if e.success is not None]
        return sum(known) / len(known) if known else None

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "run_id": self.metadata.run_id,
            "task": self.metadata.task,
            "registry_revision": self.metadata.registry_revision,
            "complete": self.complete,
            "success_rate": self.success_rate,
            "topic_counts": dict(self.topic_counts),
            "episodes": [e.to_dict() for e in self.episodes],
        }


def _json_float(value: float | None) -> float | None:
    if value is None or value != value or value in (float("inf"), float("-inf")):
        return None
    return value


def summarize(path: str | os.PathLike[str], *, allow_incomplete: bool = True) -> TraceSummary:
    """Summarize the episodes of the trace at ``path``.

    Args:
        path: A trace file.
        allow_incomplete: Summarize an unfinished (crashed) file from what it holds; False
            raises :class:`Corrupt` for it instead.

    Raises:
        NotFound, Invalid, Forbidden: missing, not an MCAP file, unreadable.
        Corrupt: no capevo metadata, a message does not decode, or an unfinished file with
            ``allow_incomplete`` false.
    """
    reader = TraceReader(path, allow_incomplete=allow_incomplete)
    metadata = reader.metadata()
    order: list[int] = []
    summaries: dict[int, EpisodeSummary] = {}
    rewards: dict[int, float] = {}
    steps: dict[int, int] = {}
    interventions: dict[int, int] = {}
    counts: dict[str, int] = {}

    def seen(episode: int) -> None:
        if episode not in rewards:
            order.append(episode)
            rewards[episode] = 0.0
            steps[episode] = 0
            interventions[episode] = 0

    for record in reader.records():
        counts[record.TOPIC] = counts.get(record.TOPIC, 0) + 1
        if isinstance(record, EnvStep):
            seen(record.episode)
            rewards[record.episode] += record.reward
            steps[record.episode] += 1
        elif isinstance(record, Intervention):
            seen(record.episode)
            interventions[record.episode] += 1
        elif isinstance(record, EpisodeSummary):
            seen(record.episode)
            summaries[record.episode] = record
    rows = []
    for ep in order:
        s = summaries.get(ep)
        if s is not None:
            rows.append(
                EpisodeRow(
                    episode=ep,
                    finished=True,
                    success=s.success,
                    total_reward=s.total_reward,
                    steps=s.steps,
                    interventions=s.interventions,
                    unsafe_steps=s.unsafe_steps,
                    seed=s.seed,
                    duration_s=s.duration_s,
                    capability_set=s.capability_set,
                )
            )
        else:
            rows.append(
                EpisodeRow(
                    episode=ep,
                    finished=False,
                    success=None,
                    total_reward=rewards[ep],
                    steps=steps[ep],
                    interventions=interventions[ep],
                )
            )
    return TraceSummary(
        path=str(Path(path)),
        metadata=metadata,
        complete=reader.complete and (reader.scan_result is None or reader.scan_result.complete),
        episodes=tuple(rows),
        topic_counts=counts,
    )
