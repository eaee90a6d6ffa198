"""The report, the plots and the ``evolve`` command's error handling, without a simulator.

The report is written from a run of the loop over fakes (see ``evolve_support``); the command
is invoked in process with click's runner on report directories that must be refused before
any episode runs.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from evolve_support import ParamUpdater, ScriptedEvaluator, fake_config, make_loop, reach_at_least, seeded_registry

from capevo.cli.evolve import evolve
from capevo.evolve.config import make_config
from capevo.evolve.plots import active_steps, plot_progress, plot_timeline
from capevo.evolve.report import describe_v0, v0_statement, write_report
from capevo.evolve.state import RunManifest, save_manifest

PNG = b"\x89PNG\r\n\x1a\n"


def test_report_states_v0_result_gate_and_identity(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=ScriptedEvaluator(registry, reach_at_least(1)),
        updater=ParamUpdater(registry),
        config=fake_config(iterations=2),
    )
    result = loop.run()
    files = write_report(loop.report_dir, registry=registry, final=result.final)
    names = {f.name for f in files}
    assert {"report.md", "metrics.csv", "progress.png", "timeline.png"} <= names
    for f in files:
        assert f.is_file()
        if f.suffix == ".png":
            assert f.read_bytes()[:8] == PNG and f.stat().st_size > 10_000
    text = (loop.report_dir / "report.md").read_text()
    assert "Version 0 is **manual creation**" in text and "deliberately left untuned" in text
    assert "| `pick.reach` | code | manual |" in text
    # the hand-off oracle is named (issue 19): the predicates read exact simulator state
    assert "| hand-offs | hand-offs between ECMs read exact simulator state" in text and "grasped" in text
    # start vs final on the same seeds, with the paired test
    assert "| start (iteration 0, live seeds) | grasp@0, lift@0, reach@0 | 0/3 = 0%" in text
    assert "| final (same seeds) | grasp@0, lift@0, reach@1 | 3/3 = 100%" in text
    assert "exact McNemar p = 0.125" in text
    # what search changed: the final set's code ECMs past v0, parameter by parameter
    assert "## What search changed" in text and "| `pick.reach` | 1 | gain 3 → 4.5 |" in text
    # the gate table: N, intervals, p-values, decision
    assert "| 0 | `pick.reach` v1 | v0 | paired | 8 | 8/8" in text and "**promote**" in text
    assert result.identity_hash in text and "unchanged every time" in text
    assert "policy drift Δπ per iteration: 0, 0" in text
    # the version history from the registry
    assert "| `pick.reach` | 1 | clone | 0 | param-fake | active | publish → gate → promote |" in text
    # rewriting from disk alone (journal, metrics, registry) gives the same Markdown body
    again = write_report(loop.report_dir, registry=registry)
    assert again[0].read_text().split("\n", 3)[3] == text.split("\n", 3)[3]


def test_v0_statement_names_neural_seeds(tmp_path: Path) -> None:
    rows = [{"kind": "neural", "origin": "manual"}]
    assert "randomly initialised SAC policies" in v0_statement(rows)
    assert v0_statement([]) == "The registry holds no version 0 of this task's ECMs."
    registry = seeded_registry(tmp_path)
    described = describe_v0(registry, "pick")
    assert [d["name"] for d in described] == ["pick.reach", "pick.grasp", "pick.lift"]
    assert described[0]["params"]["gain"] == 3.0


def test_plots_of_an_empty_run_are_still_pngs(tmp_path: Path) -> None:
    assert plot_progress([], tmp_path / "p.png").read_bytes()[:8] == PNG
    assert plot_timeline({}, tmp_path / "t.png").read_bytes()[:8] == PNG
    assert active_steps([]) == []


def _write_manifest(report: Path, root: Path, **changes: object) -> None:
    fields = {
        "task": "pick",
        "modality": "code",
        "seed": 0,
        "perturbations": True,
        "config": make_config("tiny"),
        "identity_hash": "00" * 32,
        "mode": "embedded",
        "registry": str(root.resolve()),
        "learner": "local",
        "created_at": 1.0,
    }
    fields.update(changes)
    report.mkdir(parents=True, exist_ok=True)
    save_manifest(report, RunManifest(**fields))  # type: ignore[arg-type]


def test_cli_refuses_to_continue_a_run_of_another_agent(tmp_path: Path) -> None:
    root, report = tmp_path / "data", tmp_path / "report"
    _write_manifest(report, root)
    result = CliRunner().invoke(
        evolve, ["--task", "T1", "--preset", "tiny", "--root", str(root), "--report-dir", str(report)]
    )
    assert result.exit_code == 14, result.output
    assert "error [identity_violation]: the agent's identity changed since this run started" in result.output
    assert not root.exists()  # refused before the registry was created or seeded


def test_cli_refuses_other_settings_in_the_same_report_dir(tmp_path: Path) -> None:
    from capevo.agent import DecompositionPolicy, EpisodicMemory, IdentityMemory, PersistentAgent

    identity = IdentityMemory.default()
    agent = PersistentAgent(DecompositionPolicy(identity=identity), identity, EpisodicMemory(tmp_path / "m.jsonl"))
    root, report = tmp_path / "data", tmp_path / "report"
    _write_manifest(report, root, identity_hash=agent.identity_hash, modality="il")
    result = CliRunner().invoke(
        evolve, ["--task", "T1", "--preset", "tiny", "--root", str(root), "--report-dir", str(report)]
    )
    assert result.exit_code == 3, result.output
    assert "error [invalid]: this report directory holds a run with other settings (modality: 'il' -> 'code')" in (
        result.output
    )


def test_cli_usage_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    bad = runner.invoke(evolve, ["--task", "T9", "--root", str(tmp_path / "d"), "--report-dir", str(tmp_path / "r")])
    assert bad.exit_code == 3 and "error [invalid]: unknown task 'T9'" in bad.output
    remote = runner.invoke(evolve, ["--task", "T1", "--learner", "remote", "--root", str(tmp_path / "d")])
    assert remote.exit_code == 3 and "give --connect ENDPOINT with --learner remote" in remote.output
    missing = runner.invoke(evolve, ["--task", "T1", "--report-only", "--report-dir", str(tmp_path / "none")])
    assert missing.exit_code == 4 and "holds no evolve run" in missing.output


def test_cli_report_only_rewrites_the_report(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    loop = make_loop(
        tmp_path,
        registry=registry,
        evaluator=ScriptedEvaluator(registry, reach_at_least(1)),
        updater=ParamUpdater(registry),
        config=fake_config(iterations=1),
    )
    loop.run()
    registry.close()
    result = CliRunner().invoke(
        evolve,
        [
            "--task",
            "T1",
            "--report-only",
            "--root",
            str(tmp_path / "registry"),
            "--report-dir",
            str(loop.report_dir),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    files = json.loads(result.output)["files"]
    assert any(f.endswith("report.md") for f in files) and any(f.endswith("timeline.png") for f in files)


@pytest.mark.parametrize("preset", ["tiny", "cpu-small", "paper"])
def test_cli_help_lists_the_preset(preset: str) -> None:
    out = CliRunner().invoke(evolve, ["--help"]).output
    assert preset in out and "--connect" in out and "--perturbations / --no-perturbations" in out
