"""Issue 18's "one run": the governance rates and the runtime worker's overhead, back to back.

BENCHMARKS.md asks for the governance-rate table (paper Φ and the default per-task Φ, governance
on and off, the aggressive explorer and the adversarial ECMs) and the worker overhead measured in
the same run. This script runs the two benchmarks one after the other in one invocation, so they
share the code state, the date and the machine, and records the load before, between and after:

1. ``bench_governance_rates.py --episodes E --horizon H --jobs J --fresh`` (every job rerun);
2. ``bench_worker.py --rounds R --seeds S`` under the default Φ, then under the paper Φ.

Each writes its own results file as before (``bench_governance_rates_adversarial.json``,
``bench_worker.json``, ``bench_worker_paper.json``); this script adds ``safety_run.json`` with
the commands, the loads and the wall time of each part.

    .venv/bin/python benchmarks/bench_safety_run.py [--episodes 50] [--horizon 100] [--jobs 2]
        [--rounds 6] [--seeds 6]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save_results

HERE = Path(__file__).resolve().parent


def _part(args: list[str]) -> dict[str, Any]:
    """Run one benchmark script to completion in a child process, timing it and sampling the load."""
    load_before = os.getloadavg()
    started = time.perf_counter()
    subprocess.run([sys.executable, *args], check=True)
    return {
        "command": "benchmarks/" + " ".join(args).replace(str(HERE) + "/", ""),
        "seconds": time.perf_counter() - started,
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--seeds", type=int, default=6)
    args = parser.parse_args(argv)
    rates = str(HERE / "bench_governance_rates.py")
    worker = str(HERE / "bench_worker.py")
    parts = [
        _part(
            [
                rates,
                "--episodes",
                str(args.episodes),
                "--horizon",
                str(args.horizon),
                "--jobs",
                str(args.jobs),
                "--fresh",
            ]
        ),
        _part([worker, "--rounds", str(args.rounds), "--seeds", str(args.seeds), "--phi", "task"]),
        _part(
            [
                worker,
                "--rounds",
                str(args.rounds),
                "--seeds",
                str(args.seeds),
                "--phi",
                "paper",
                "--out",
                "bench_worker_paper",
            ]
        ),
    ]
    command = "benchmarks/bench_safety_run.py " + " ".join(sys.argv[1:] if argv is None else argv)
    path = save_results("safety_run", {"command": command.strip(), "cpus": os.cpu_count(), "parts": parts})
    print(f"results: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
