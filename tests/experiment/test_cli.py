"""``capevo experiment report|verify|run`` as a user runs them (a subprocess): verify exits 0 on a run
just reported and 1 with the mismatch on stderr after a metric was edited; errors are one
``error [code]`` line (capevo.cli.experiment invariants 1-2)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from run_builder import build_run

REPO = Path(__file__).resolve().parents[2]


def _capevo(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "capevo", "experiment", *args], cwd=REPO, capture_output=True, text=True, timeout=120
    )


def test_report_then_verify_then_a_tampered_metric_fails_verify(tmp_path: Path) -> None:
    root, _ = build_run(tmp_path / "run")
    report = _capevo("report", str(root))
    assert report.returncode == 0, report.stderr
    assert str(root / "report" / "report.md") in report.stdout.splitlines()
    ok = _capevo("verify", str(root))
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("ok")

    metrics = root / "cells" / "T6-am-s7" / "metrics.jsonl"
    lines = metrics.read_text().splitlines(keepends=True)
    row = json.loads(lines[0])
    row["success_rate"] += 0.1
    lines[0] = json.dumps(row, sort_keys=True) + "\n"
    metrics.write_text("".join(lines))
    bad = _capevo("verify", str(root))
    assert bad.returncode == 1
    assert "cells/T6-am-s7/metrics.jsonl:1:success_rate" in bad.stderr and "1 mismatch" in bad.stderr


def test_errors_are_one_line_with_their_code(tmp_path: Path) -> None:
    missing = _capevo("verify", str(tmp_path / "nothing"))
    assert missing.returncode == 4 and missing.stderr.startswith("error [not_found]")
    grid = tmp_path / "bad.yaml"
    grid.write_text("tasks: [T9]\nseeds: [1]\niterations: 1\nbudget: {env_steps_per_iteration: 1, eval_episodes: 1}\n"
                    "methods: [s-ecm]\n")  # fmt: skip
    bad = _capevo("run", str(grid), "--out", str(tmp_path / "out"))
    assert bad.returncode == 3 and bad.stderr.startswith("error [invalid]: tasks[0]: unknown task 'T9'")
    assert not (tmp_path / "out").exists()


def test_a_run_directory_of_other_cell_settings_is_refused_before_anything_runs(tmp_path: Path) -> None:
    from capevo.errors import Invalid
    from capevo.experiment.config import parse_yaml
    from capevo.experiment.runner import run_experiment

    text = "tasks: [T1]\nseeds: [1]\niterations: 1\nbudget: {env_steps_per_iteration: 9, eval_episodes: 1}\n"
    first = parse_yaml(text + "methods: [s-ecm]\n")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "experiment.json").write_text(json.dumps(first.to_dict()))
    changed = parse_yaml(text.replace("eval_episodes: 1", "eval_episodes: 2") + "methods: [s-ecm]\n")
    with pytest.raises(Invalid) as info:
        run_experiment(changed, run_dir)
    assert info.value.details["field"] == "run_dir" and "T1-s-ecm-s1" in info.value.message
    assert not (run_dir / "cells").exists()
    assert json.loads((run_dir / "experiment.json").read_text()) == first.to_dict()
