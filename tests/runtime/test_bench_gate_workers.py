"""benchmarks/bench_gate_workers.py still runs against the code, at a tiny setting; no timing is judged.

Its own check matters here: with 1 and with 2 workers the gate ran the same episodes, or the
script stops (``SystemExit``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import _common  # noqa: E402
import bench_gate_workers  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]


def test_the_gate_benchmark_runs_both_settings_on_the_same_episodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    argv = ["--rounds", "2", "--episodes", "4", "--horizon", "15", "--out", "smoke"]
    assert bench_gate_workers.main(argv) == 0
    saved = json.loads((tmp_path / "smoke.json").read_text())
    assert saved["same_episodes"] is True and saved["params"]["episodes"] == 4
    runs = saved["runs"]
    assert [r["round"] for r in runs["1"]] == [r["round"] for r in runs["2"]] == [0, 1]
    assert all(r["episodes"] == 8 for r in runs["1"] + runs["2"])  # both sides of 4 paired seeds
    assert all(r["workers"] == ["bench-w1"] for r in runs["1"])
    assert all(r["workers"] == ["bench-w1", "bench-w2"] for r in runs["2"])
