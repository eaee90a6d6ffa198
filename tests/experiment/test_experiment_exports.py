"""``capevo.experiment`` re-exports exactly its public API, each name resolving to its home module."""

from __future__ import annotations

import importlib

import capevo.experiment as experiment

PUBLIC = {
    "ExperimentConfig": "config",
    "MethodEntry": "config",
    "load_config": "config",
    "make_experiment": "config",
    "preset_names": "config",
    "make_method": "methods",
    "method_names": "methods",
    "GridProgress": "progress",
    "RecordingGridProgress": "progress",
    "RichGridProgress": "progress",
    "write_report": "report",
    "RunSummary": "runner",
    "run_experiment": "runner",
    "verify_run": "verify",
}


def test_all_is_the_public_api_and_each_name_is_its_home_modules() -> None:
    assert sorted(experiment.__all__) == sorted(PUBLIC)
    for name, module in PUBLIC.items():
        home = importlib.import_module(f"capevo.experiment.{module}")
        assert getattr(experiment, name) is getattr(home, name)
