"""Check a run's learner env steps against the learner's own MCAP traces (issue 20, parity).

Every metrics row records ``learner_steps``, the env steps its learners reported spending. The
code learners (CEM, hybrid) also trace every episode they run to ``traces/learner/``. This script
sums those traces per iteration and prints both counts, so an accounting fault in the loop shows
up without trusting the loop: before commit c898386 a chain that learned the same ECM twice
dropped the first update's steps from both its cap and its count (``results/h1/README.md``).

The counting is :func:`capevo.evolve.audit.learner_step_checks`, which the experiment harness also
runs on each cell's host (``learner_steps_traced`` in ``done.json``, checked by ``capevo experiment
verify``). Neural learners (SAC, BC) run episodes outside the traced evaluator and are not checked.

    .venv/bin/python benchmarks/diag_learner_steps.py /tmp/h1          # an experiment directory
    .venv/bin/python benchmarks/diag_learner_steps.py /tmp/evo/report  # one evolve report directory

Exits 1 when a code learner's row disagrees with its traces.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def evolve_dirs(root: Path) -> list[Path]:
    """``root`` itself if it is an evolve report directory, else every cell's ``evolve/`` under it."""
    if (root / "metrics.jsonl").is_file():
        return [root]
    return sorted(p.parent for p in root.glob("cells/*/evolve/metrics.jsonl"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="an experiment directory or an evolve report directory")
    args = parser.parse_args(argv)
    reports = evolve_dirs(args.root)
    if not reports:
        parser.error(f"{args.root}: no metrics.jsonl here or under cells/*/evolve/")
    from capevo.evolve.audit import learner_step_checks

    bad = 0
    print("| run | iteration | learner | learner_steps | traced | |")
    print("|---|---|---|---|---|---|")
    for report in reports:
        name = report.parent.name if report.name == "evolve" else str(report)
        for c in learner_step_checks(report):
            bad += not c.ok
            flag = "" if c.ok else "**differs**"
            shown = c.traced if c.checked else "(not traced)"
            print(f"| {name} | {c.iteration} | {c.learner} | {c.recorded} | {shown} | {flag} |")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
