"""The grid runner on real Ray (num_cpus 2), real robosuite episodes and real files: cells finish,
a failing cell is retried and reported while the others finish, a finished cell is never redone,
and a run whose driver was SIGKILLed resumes (capevo.experiment.runner invariants 1-4)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from capevo.baselines.base import IterationRecord
from capevo.experiment.config import parse_yaml
from capevo.experiment.progress import RecordingGridProgress
from capevo.experiment.runner import run_experiment

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
GRID = """
name: runner-test
tasks: [T1]
seeds: [1, 2]
iterations: 2
budget: {env_steps_per_iteration: 100, eval_episodes: 2, horizon: 30}
methods:
  - s-ecm
  # a real failure on every attempt: an option the explorer does not know (checked when it runs)
  - {method: explorer, seeds: [1], options: {no_such_option: 1}}
"""


def _snapshot(cell_dir: Path) -> dict[str, tuple[int, str]]:
    return {
        str(p.relative_to(cell_dir)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
        for p in sorted(cell_dir.rglob("*"))
        if p.is_file()
    }


def _records(cell_dir: Path) -> list[IterationRecord]:
    lines = (cell_dir / "metrics.jsonl").read_text(encoding="utf-8").splitlines()
    return [IterationRecord.from_dict(json.loads(line)) for line in lines]


def test_cells_finish_a_failing_cell_is_retried_and_reported_and_nothing_is_redone(tmp_path: Path) -> None:
    config = parse_yaml(GRID)
    run_dir = tmp_path / "run"
    progress = RecordingGridProgress()
    summary = run_experiment(config, run_dir, workers=2, retries=1, progress=progress)
    assert sorted(summary.done) == ["T1-s-ecm-s1", "T1-s-ecm-s2"] and summary.skipped == ()
    assert summary.failed == ("T1-explorer-s1",)

    # the failed cell: failed.json after 1 + 1 attempts, and the retry was announced
    failed = json.loads((run_dir / "cells" / "T1-explorer-s1" / "failed.json").read_text())
    assert failed["attempts"] == 2 and "no_such_option" in failed["error"] and "Traceback" in failed["traceback"]
    assert not (run_dir / "cells" / "T1-explorer-s1" / "done.json").exists()
    assert any(c == "message" and "retrying T1-explorer-s1" in a["text"] for c, a in progress.calls)
    assert [a["ok"] for c, a in progress.calls if c == "cell_finished"].count(False) == 1

    # the finished cells: cell.json, metrics (invariant 2), done.json sums (invariant 3), traces
    for seed in (1, 2):
        d = run_dir / "cells" / f"T1-s-ecm-s{seed}"
        cell = json.loads((d / "cell.json").read_text())
        assert cell["cell"]["method"] == "s-ecm" and cell["cell"]["seed"] == seed and cell["knowledge"]
        records = _records(d)
        assert [r.iteration for r in records] == [1, 2]
        held_out = [2_000_000_000 + 1000 * seed + j for j in range(2)]
        assert all([e.seed for e in r.episodes] == held_out for r in records)
        done = json.loads((d / "done.json").read_text())
        assert done["env_steps_train"] == sum(r.env_steps_train for r in records) == 0
        assert done["env_steps_eval"] == sum(r.env_steps_eval for r in records) > 0
        assert done["attempts"] == 1
        assert list(d.glob("traces/**/*.mcap")) and (d / "registry").is_dir()
    assert not list((run_dir / "cells").glob("*.partial"))
    experiment = json.loads((run_dir / "experiment.json").read_text())
    assert experiment["name"] == "runner-test" and experiment["yaml"] == GRID
    provenance = json.loads((run_dir / "provenance.json").read_text())
    assert provenance["packages"]["ray"] == "2.60.0" and provenance["cells"]["failed"] == 1
    assert provenance["machine"]["cores"] and provenance["wall_s"] > 0
    assert "earlier_runs" not in provenance
    # each cell says which code ran it: here the driver's own checkout
    for seed in (1, 2):
        done = json.loads((run_dir / "cells" / f"T1-s-ecm-s{seed}" / "done.json").read_text())
        assert "capevo_commit" in done and done["capevo_commit"] == provenance["capevo_commit"]
        assert done["capevo_sha256"] == provenance["capevo_sha256"] and len(done["capevo_sha256"]) == 64

    # again: the finished cells are skipped and untouched, the failed one is tried again
    before = {k: _snapshot(run_dir / "cells" / k) for k in summary.done}
    again = run_experiment(config, run_dir, workers=2, retries=0)
    assert sorted(again.skipped) == sorted(summary.done) and again.done == ()
    assert again.failed == ("T1-explorer-s1",)
    assert json.loads((run_dir / "cells" / "T1-explorer-s1" / "failed.json").read_text())["attempts"] == 1
    assert {k: _snapshot(run_dir / "cells" / k) for k in summary.done} == before
    # the resumed run's provenance keeps the first run's, whose cells it reused
    resumed = json.loads((run_dir / "provenance.json").read_text())
    assert resumed["cells"]["skipped"] == 2 and resumed["earlier_runs"] == [provenance]


def _finished(run_dir: Path) -> list[str]:
    """Cells whose directory was renamed from ``<name>.partial`` after their ``done.json``."""
    return sorted(p.parent.name for p in run_dir.glob("cells/*/done.json") if not p.parent.name.endswith(".partial"))


def test_a_run_whose_driver_was_sigkilled_resumes_without_redoing_finished_cells(tmp_path: Path) -> None:
    grid = tmp_path / "grid.yaml"
    grid.write_text(
        "name: kill\ntasks: [T1]\nseeds: [1, 2, 3, 4]\niterations: 2\n"
        "budget: {env_steps_per_iteration: 100, eval_episodes: 3, horizon: 60}\nmethods: [s-ecm]\n",
        encoding="utf-8",
    )
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "capevo", "experiment", "run", str(grid), "--out", str(run_dir), "--workers", "1"]
    driver = subprocess.Popen(
        [*cmd, "--no-report"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: Ray's helpers are ours to clean up
    )
    try:
        deadline = time.monotonic() + 180
        # a finished cell is a renamed directory; ``<name>.partial/done.json`` is the moment before
        while not _finished(run_dir):
            assert driver.poll() is None, "the driver ended before any cell finished"
            assert time.monotonic() < deadline, "no cell finished"
            time.sleep(0.1)
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait(timeout=30)
    finally:
        # a SIGKILLed driver leaves Ray's agents of its session behind: end that process group
        with contextlib.suppress(ProcessLookupError):
            os.killpg(driver.pid, signal.SIGKILL)
    finished = _finished(run_dir)
    assert 1 <= len(finished) < 4, finished
    before = {k: _snapshot(run_dir / "cells" / k) for k in finished}

    summary = run_experiment(parse_yaml(grid.read_text(encoding="utf-8")), run_dir, workers=2)
    assert sorted(summary.skipped) == finished
    assert sorted(summary.done + summary.skipped) == [f"T1-s-ecm-s{s}" for s in (1, 2, 3, 4)]
    assert summary.failed == ()
    assert {k: _snapshot(run_dir / "cells" / k) for k in finished} == before
    for k in summary.done:
        assert [r.iteration for r in _records(run_dir / "cells" / k)] == [1, 2]
    assert not list((run_dir / "cells").glob("*.partial"))


DRIVER = """
import sys
from pathlib import Path

import capevo
from capevo.errors import Conflict
from capevo.experiment.config import parse_yaml
from capevo.experiment.runner import CODE_COMMIT, run_experiment

print("driver code", Path(capevo.__file__).resolve().parents[1], CODE_COMMIT, flush=True)
try:
    run_experiment(parse_yaml(sys.argv[1]), Path(sys.argv[2]), workers=1)
except Conflict as exc:
    print("refused:", exc.message, flush=True)
    sys.exit(3)
"""


def test_a_grid_refuses_ray_workers_that_import_other_code_than_the_driver(tmp_path: Path) -> None:
    # The driver's code is a changed copy of capevo (one line more), committed in a git repository
    # of its own, reached through PYTHONPATH; the driver starts in this checkout, as a run started
    # from the repository with a worktree on PYTHONPATH does. Ray puts the driver's working
    # directory first on its workers' path, so their capevo is this checkout's.
    other = tmp_path / "other"
    other.mkdir()
    subprocess.run(["cp", "-r", str(REPO / "capevo"), str(other / "capevo")], check=True)
    with open(other / "capevo" / "__init__.py", "a", encoding="utf-8") as f:
        f.write("# a change only the driver's copy has\n")
    git = ["git", "-C", str(other), "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "a copy"], check=True)
    script = tmp_path / "drive.py"
    script.write_text(DRIVER, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": str(other)}
    proc = subprocess.run(
        [sys.executable, str(script), GRID, str(tmp_path / "run")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert f"driver code {other}" in proc.stdout, proc.stdout + proc.stderr[-2000:]
    assert proc.returncode == 3, proc.stdout + proc.stderr[-3000:]
    assert f"from {REPO} (commit" in proc.stdout and "start capevo experiment run from the directory" in proc.stdout
    # refused before any cell ran: no cell directory, and the provenance names the driver's code
    assert not list((tmp_path / "run" / "cells").iterdir())
    provenance = json.loads((tmp_path / "run" / "provenance.json").read_text())
    other_head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True)
    assert provenance["capevo_commit"] == other_head.stdout.strip()


def test_a_cell_refuses_to_run_with_other_code_than_the_drivers(monkeypatch: pytest.MonkeyPatch) -> None:
    # a worker on another host of a cluster, whose checkout holds other code
    from capevo.errors import Conflict
    from capevo.experiment import runner

    assert len(runner.CODE_SHA256) == 64
    monkeypatch.setattr(runner, "CODE_SHA256", "a" * 64)
    with pytest.raises(Conflict, match="imported other capevo code than the driver's") as caught:
        runner.run_cell({"not": "read"}, "T1-s-ecm-s1", "b" * 64)
    assert caught.value.details["driver_sha256"] == "b" * 64
    # the same code, or a driver that sends none (an older one), runs
    runner.check_same_code("a" * 64)
    runner.check_same_code(None)
