"""Check a run's learner env steps against the learner's own MCAP traces (issue 20, parity).

Every metrics row records ``learner_steps``, the env steps its learners reported spending. The
code learners (CEM, hybrid) also trace every episode they run to ``traces/learner/``. This script
sums those traces per iteration and prints both counts, so an accounting fault in the loop shows
up without trusting the loop: before commit c898386 a chain that learned the same ECM twice
dropped the first update's steps from both its cap and its count (``results/h1/README.md``).

An episode belongs to the iteration whose ``started_at`` precedes its trace file's last write.
Neural learners (SAC, BC) run episodes outside the traced evaluator, so their rows show 0 traced.

    .venv/bin/python benchmarks/diag_learner_steps.py /tmp/h1          # an experiment directory
    .venv/bin/python benchmarks/diag_learner_steps.py /tmp/evo/report  # one evolve report directory

Exits 1 when a code learner's row disagrees with its traces.
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
from pathlib import Path


def evolve_dirs(root: Path) -> list[Path]:
    """``root`` itself if it is an evolve report directory, else every cell's ``evolve/`` under it."""
    if (root / "metrics.jsonl").is_file():
        return [root]
    return sorted(p.parent for p in root.glob("cells/*/evolve/metrics.jsonl"))


def traced_per_iteration(report: Path) -> tuple[list[dict], list[int]]:
    """The metrics rows of ``report`` and the env steps its learner traces hold per row."""
    from capevo.runtime.traces.summary import summarize

    rows = [json.loads(line) for line in (report / "metrics.jsonl").read_text().splitlines() if line.strip()]
    starts = [float(r["started_at"]) for r in rows]
    traced = [0] * len(rows)
    for path in (report / "traces" / "learner").rglob("*.mcap"):
        k = bisect.bisect_right(starts, path.stat().st_mtime) - 1
        if k >= 0:
            traced[k] += sum(e.steps for e in summarize(path).episodes)
    return rows, traced


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="an experiment directory or an evolve report directory")
    args = parser.parse_args(argv)
    reports = evolve_dirs(args.root)
    if not reports:
        parser.error(f"{args.root}: no metrics.jsonl here or under cells/*/evolve/")
    bad = 0
    print("| run | iteration | learner | learner_steps | traced | |")
    print("|---|---|---|---|---|---|")
    for report in reports:
        rows, traced = traced_per_iteration(report)
        name = report.parent.name if report.name == "evolve" else str(report)
        for row, count in zip(rows, traced, strict=True):
            learner = str(row.get("learner") or "")
            neural = count == 0 and learner not in ("cem", "hybrid")
            ok = neural or int(row.get("learner_steps") or 0) == count
            bad += not ok
            flag = "" if ok else "**differs**"
            print(f"| {name} | {row['iteration']} | {learner} | {row.get('learner_steps')} | {count} | {flag} |")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
