"""The trace and worker benchmarks still run against the code (tiny budgets; no timing is judged).

A benchmark drives the runtime through its public seams (sinks, writers, the episode loop); when
one of those changes, the script is the first thing to break, and nobody runs it until a figure
is wanted. These runs only check that each completes and reports what it measured.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import _common  # noqa: E402
import bench_traces_loop  # noqa: E402
import bench_worker  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def results_in(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    logging.getLogger("robosuite").setLevel(logging.ERROR)
    return tmp_path


def test_trace_loop_benchmark_measures_every_part_of_a_real_episode(results_in: Path) -> None:
    result = bench_traces_loop.measure("T1", 1, [1, 64], ["lz4", "none"])
    rows = result["rows"]
    assert [(row["batch"], row["compression"]) for row in rows] == [(1, "lz4"), (1, "none"), (64, "lz4"), (64, "none")]
    for row in rows:
        assert row["steps"] > 0 and row["bytes_per_step"] > 100  # a file with every step in it
        assert row["gross_write_us_per_step_median"] > 0 and row["env_step_cpu_ms"] > 0
        assert row["background_us_per_step_median"] >= 0
    # the same episodes, so the same records: lz4's files are the smaller
    assert len({row["steps"] for row in rows}) == 1
    assert all(rows[i]["bytes_per_step"] < rows[i + 1]["bytes_per_step"] for i in (0, 2))
    assert result["clock_floor_us_per_call"] > 0


def test_worker_benchmark_runs_its_variants_and_breakdown(results_in: Path) -> None:
    assert bench_worker.main(["--rounds", "1", "--seeds", "1", "--horizon", "12", "--out", "smoke"]) == 0
    saved = json.loads((results_in / "smoke.json").read_text())
    assert saved["benchmark"] == "smoke"
    text = json.dumps(saved, ensure_ascii=False)
    assert "trace writes" in text and "governance R(a, Φ)" in text
