"""A cell whose process died resumes after its last complete record (capevo.experiment.runner,
"Inside a cell"; invariants 5-6): real Ray, real robosuite episodes, a SIGKILLed driver, and the
two methods that resume (ours through evolve's resume, AM with PPO from its checkpoint)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from capevo.baselines.base import CellSpec, EpisodeResult, IterationRecord
from capevo.experiment import runner
from capevo.experiment.config import parse_yaml
from capevo.experiment.methods import make_method
from capevo.experiment.runner import run_cell, run_experiment

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
GRID = """
name: resume
tasks: [T1]
seeds: [1]
iterations: 4
budget: {env_steps_per_iteration: 600, eval_episodes: 2, horizon: 40}
methods:
  - {method: ours-code, options: {preset: tiny}}
  - {method: am, options: {n_steps: 200}}
"""
NAMES = ("T1-ours-code-s1", "T1-am-s1")


def _lines(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True) if path.exists() else []


def test_a_cell_killed_mid_run_resumes_after_its_last_record_and_keeps_it(tmp_path: Path) -> None:
    grid, run_dir, work = tmp_path / "grid.yaml", tmp_path / "run", tmp_path / "work"
    grid.write_text(GRID, encoding="utf-8")
    cmd = [sys.executable, "-m", "capevo", "experiment", "run", str(grid), "--out", str(run_dir)]
    driver = subprocess.Popen(
        [*cmd, "--workers", "2", "--work-dir", str(work), "--no-report"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: Ray's workers die with it, as in a crash
    )
    try:
        deadline = time.monotonic() + 600
        while not any(_lines(work / n / "metrics.jsonl") for n in NAMES):
            assert driver.poll() is None, "the driver ended before any iteration finished"
            assert time.monotonic() < deadline, "no iteration finished"
            time.sleep(0.1)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(driver.pid, signal.SIGKILL)
        driver.wait(timeout=30)
    time.sleep(1.0)  # the process group's workers are gone before the files are read
    at_kill = {n: _lines(work / n / "metrics.jsonl") for n in NAMES}
    assert not list(run_dir.glob("cells/*/done.json"))

    summary = run_experiment(parse_yaml(GRID), run_dir, workers=2, work_dir=work)
    assert sorted(summary.done) == sorted(NAMES) and summary.failed == ()
    resumed = 0
    for name in NAMES:
        d = run_dir / "cells" / name
        kept = at_kill[name]
        records = [IterationRecord.from_dict(json.loads(line)) for line in _lines(d / "metrics.jsonl")]
        assert [r.iteration for r in records] == [1, 2, 3, 4]
        attempts = [json.loads(line) for line in _lines(d / "resumes.jsonl")]
        done = json.loads((d / "done.json").read_text())
        assert done["env_steps_train"] == sum(r.env_steps_train for r in records)
        if kept:
            resumed += 1
            # the records written before the kill are kept byte for byte; the rest were run after
            assert _lines(d / "metrics.jsonl")[: len(kept)] == kept
            assert [a["after_iteration"] for a in attempts] == [0, len(kept)]
            assert attempts[1]["capevo_sha256"] == runner.CODE_SHA256
            assert done["resumed_after"] == [len(kept)]
        else:
            # nothing finished: started over in an emptied directory
            assert [a["after_iteration"] for a in attempts] == [0] and "resumed_after" not in done
        if name == "T1-am-s1":
            # PPO went on from its checkpoint: every iteration spent the budget and moved the policy
            assert all(r.env_steps_train == 600 and r.delta_pi > 0 for r in records)
            if kept:
                assert "resumed from checkpoints/iteration-" in records[len(kept)].notes
        else:
            # evolve resumed its own run: one evolve iteration per record, no iteration run twice
            evolve = [json.loads(line) for line in _lines(d / "evolve" / "metrics.jsonl")]
            assert [row["iteration"] for row in evolve] == [0, 1, 2, 3]
    assert resumed >= 1
    # finished cells leave nothing behind in the work directory
    assert not [p for p in work.iterdir() if p.name in NAMES]


def _cell() -> CellSpec:
    return parse_yaml(GRID).cells()[0]


def _record(i: int) -> IterationRecord:
    episode = EpisodeResult(seed=7, success=False, reward=0.5, steps=10, unsafe_steps=0, interventions=0)
    return IterationRecord(
        iteration=i, episodes=(episode,), env_steps_train=600, env_steps_eval=10, delta_pi=0.0, wall_s=1.0
    )


def _interrupted(d: Path, cell: CellSpec, lines: list[bytes], *, code: str | None = None) -> None:
    d.mkdir(parents=True)
    (d / "cell.json").write_text(json.dumps({"cell": cell.to_dict(), "knowledge": ""}), encoding="utf-8")
    attempt = {"after_iteration": 0, "capevo_sha256": code or runner.CODE_SHA256}
    (d / "resumes.jsonl").write_text(json.dumps(attempt) + "\n", encoding="utf-8")
    (d / "metrics.jsonl").write_bytes(b"".join(lines))


def _line(i: int) -> bytes:
    return runner._dumps(_record(i).to_dict())


def test_which_records_an_interrupted_cell_keeps(tmp_path: Path) -> None:
    cell = _cell()
    ours = make_method(cell.method)
    # a torn last line (the process died while writing it) is dropped; the complete ones are kept
    _interrupted(tmp_path / "torn", cell, [_line(1), _line(2), _line(3)[:25]])
    assert [r.iteration for r in runner._kept_records(tmp_path / "torn", cell, ours)] == [1, 2]
    # records begun by other code, or another cell's settings, or a method that cannot resume: none
    _interrupted(tmp_path / "code", cell, [_line(1)], code="f" * 64)
    assert runner._kept_records(tmp_path / "code", cell, ours) == []
    other = CellSpec.from_dict({**cell.to_dict(), "iterations": 5})
    _interrupted(tmp_path / "settings", other, [_line(1)])
    assert runner._kept_records(tmp_path / "settings", cell, ours) == []
    s_ecm = CellSpec.from_dict({**cell.to_dict(), "method": "s-ecm", "options": {}})
    _interrupted(tmp_path / "s-ecm", s_ecm, [_line(1)])
    assert runner._kept_records(tmp_path / "s-ecm", s_ecm, make_method("s-ecm")) == []
    # a gap in the numbering ends what is kept
    _interrupted(tmp_path / "gap", cell, [_line(1), _line(3)])
    assert [r.iteration for r in runner._kept_records(tmp_path / "gap", cell, ours)] == [1]
    # AM resumes with PPO only (SAC's replay buffer is not saved)
    am = CellSpec.from_dict({**cell.to_dict(), "method": "am", "options": {}})
    assert make_method("am").resumes(am)
    assert not make_method("am").resumes(CellSpec.from_dict({**am.to_dict(), "options": {"algo": "sac"}}))


def test_a_cell_whose_method_raised_starts_over(tmp_path: Path) -> None:
    from capevo.errors import Invalid

    bad = CellSpec.from_dict({**_cell().to_dict(), "method": "explorer", "options": {"no_such_option": 1}})
    with pytest.raises(Invalid, match="no_such_option"):
        run_cell(bad.to_dict(), "T1-explorer-s1", runner.CODE_SHA256, str(tmp_path))
    assert not (tmp_path / "T1-explorer-s1").exists()
