"""The methods capevo is compared against (issue 20, paper §5.2), one module per method, and the
record types every method of the experiment harness shares (:mod:`capevo.baselines.base`)."""

from __future__ import annotations

from capevo.baselines.base import Budget, CellSpec, Emit, EpisodeResult, IterationRecord, Method

__all__ = ["Budget", "CellSpec", "Emit", "EpisodeResult", "IterationRecord", "Method"]
