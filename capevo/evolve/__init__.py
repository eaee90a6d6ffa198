"""The closed loop behind ``capevo evolve``: execute, collect experience, learn, gate, promote or roll back.

- :func:`run_evolution` / :class:`EvolveOptions`: assemble a run (embedded or over Zenoh) and run it.
- :class:`EvolutionLoop`: the loop itself, over any registry, evaluator and updater.
- :func:`make_config` / :class:`EvolveConfig`: the budget presets ``tiny``, ``cpu-small``, ``paper``.
- :class:`MetricsLog` / :class:`IterationMetrics`: per-iteration metrics, appended durably.
- :func:`write_report`: the Markdown report and its plots.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from capevo._lazy import lazy_getattr

if TYPE_CHECKING:
    from capevo.evolve.config import CemSettings, EvolveConfig, config_names, make_config
    from capevo.evolve.learners import Proposal, RemoteCandidates, UpdateRequest, make_updater
    from capevo.evolve.loop import EvolutionLoop, EvolveResult, FinalEvaluation, ensure_v0
    from capevo.evolve.metrics import IterationMetrics, MetricsLog, outcome_stats, read_metrics
    from capevo.evolve.progress import ProgressSink, RecordingProgress, RichProgress
    from capevo.evolve.report import write_report
    from capevo.evolve.run import EvolveOptions, run_evolution

_HOMES = {
    "CemSettings": "capevo.evolve.config",
    "EvolveConfig": "capevo.evolve.config",
    "config_names": "capevo.evolve.config",
    "make_config": "capevo.evolve.config",
    "Proposal": "capevo.evolve.learners",
    "RemoteCandidates": "capevo.evolve.learners",
    "UpdateRequest": "capevo.evolve.learners",
    "make_updater": "capevo.evolve.learners",
    "EvolutionLoop": "capevo.evolve.loop",
    "EvolveResult": "capevo.evolve.loop",
    "FinalEvaluation": "capevo.evolve.loop",
    "ensure_v0": "capevo.evolve.loop",
    "IterationMetrics": "capevo.evolve.metrics",
    "MetricsLog": "capevo.evolve.metrics",
    "outcome_stats": "capevo.evolve.metrics",
    "read_metrics": "capevo.evolve.metrics",
    "ProgressSink": "capevo.evolve.progress",
    "RecordingProgress": "capevo.evolve.progress",
    "RichProgress": "capevo.evolve.progress",
    "write_report": "capevo.evolve.report",
    "EvolveOptions": "capevo.evolve.run",
    "run_evolution": "capevo.evolve.run",
}
__all__ = [
    "CemSettings",
    "EvolutionLoop",
    "EvolveConfig",
    "EvolveOptions",
    "EvolveResult",
    "FinalEvaluation",
    "IterationMetrics",
    "MetricsLog",
    "ProgressSink",
    "Proposal",
    "RecordingProgress",
    "RemoteCandidates",
    "RichProgress",
    "UpdateRequest",
    "config_names",
    "ensure_v0",
    "make_config",
    "make_updater",
    "outcome_stats",
    "read_metrics",
    "run_evolution",
    "write_report",
]
__getattr__ = lazy_getattr(__name__, _HOMES)
