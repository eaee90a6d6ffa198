"""``capevo.evolve`` re-exports exactly its public API, each name resolving to its home module."""

from __future__ import annotations

import importlib

import capevo.evolve as evolve

PUBLIC = {
    "CemSettings": "config",
    "EvolveConfig": "config",
    "config_names": "config",
    "make_config": "config",
    "Proposal": "learners",
    "RemoteCandidates": "learners",
    "UpdateRequest": "learners",
    "make_updater": "learners",
    "EvolutionLoop": "loop",
    "EvolveResult": "loop",
    "FinalEvaluation": "loop",
    "ensure_v0": "loop",
    "IterationMetrics": "metrics",
    "MetricsLog": "metrics",
    "outcome_stats": "metrics",
    "read_metrics": "metrics",
    "ProgressSink": "progress",
    "RecordingProgress": "progress",
    "RichProgress": "progress",
    "write_report": "report",
    "EvolveOptions": "run",
    "run_evolution": "run",
}


def test_all_matches_the_public_api() -> None:
    assert sorted(evolve.__all__) == sorted(PUBLIC)
    for name, module in PUBLIC.items():
        home = importlib.import_module(f"capevo.evolve.{module}")
        assert getattr(evolve, name) is getattr(home, name)


def test_the_command_is_a_click_command_named_evolve() -> None:
    import click

    from capevo.cli.evolve import evolve as command

    assert isinstance(command, click.Command) and command.name == "evolve"
