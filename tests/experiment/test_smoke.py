"""The ``smoke`` preset end to end (issue 20 "Must be shown"): every method on T1 and T6, one seed, two
iterations, tiny budgets, through real Ray on 2 CPUs and real robosuite episodes; the report is
written and ``verify`` recomputes every number of it from the raw metrics.

The slowest test of the package: the whole grid, about 4-5 minutes on 2 quiet cores.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from capevo.baselines.base import IterationRecord
from capevo.experiment.config import make_experiment
from capevo.experiment.methods import method_names
from capevo.experiment.report import write_report
from capevo.experiment.runner import run_experiment
from capevo.experiment.verify import verify_run

pytestmark = pytest.mark.slow


def test_the_smoke_grid_runs_every_method_and_its_report_verifies(tmp_path: Path) -> None:
    config = make_experiment("smoke")
    run_dir = tmp_path / "smoke"
    summary = run_experiment(config, run_dir, workers=2, retries=0)
    assert summary.failed == (), [
        json.loads((run_dir / "cells" / k / "failed.json").read_text()) for k in summary.failed
    ]
    assert sorted(summary.done) == sorted(config.cell_names())
    ran = {json.loads((run_dir / "cells" / k / "cell.json").read_text())["cell"]["method"] for k in summary.done}
    assert ran == set(method_names()) - {"ours"}  # "ours" is ours-code / ours-neural by option

    budget = config.budget.env_steps_per_iteration
    for name, cell in config.cell_names().items():
        lines = (run_dir / "cells" / name / "metrics.jsonl").read_text().splitlines()
        records = [IterationRecord.from_dict(json.loads(line)) for line in lines]
        assert [r.iteration for r in records] == list(range(1, cell.iterations + 1)), name
        for r in records:
            # budget parity: no method spends more training steps than an iteration's budget
            assert 0 <= r.env_steps_train <= budget, (name, r.iteration, r.env_steps_train)
            assert [e.seed for e in r.episodes] == list(cell.eval_seeds())
            # T6's strict insertion check rides along on every method's held-out episodes; other tasks have none
            assert all(isinstance(e.strict_success, bool) == (cell.task == "T6") for e in r.episodes), name
        if cell.method in ("ours-code", "ours-neural", "s-ecm", "explorer"):
            assert all(r.delta_pi == 0.0 for r in records), name
        if cell.method in ("s-ecm", "explorer"):
            assert all(r.env_steps_train == 0 for r in records), name
        if cell.method == "ours-code":
            # counted on the cell's host from its learner's traces, one per evolve iteration
            done = json.loads((run_dir / "cells" / name / "done.json").read_text())
            assert len(done["learner_steps_traced"]) == cell.iterations, name

    files = write_report(run_dir)
    assert (run_dir / "report" / "report.md") in files and (run_dir / "report" / "numbers.json").is_file()
    assert verify_run(run_dir) == []  # also: every traced learner count equals the loop's (verify invariant 4)
    numbers = {n["name"]: n["value"] for n in json.loads((run_dir / "report" / "numbers.json").read_text())["numbers"]}
    t6_groups = [
        k.removesuffix("/eval_episodes") for k in numbers if k.startswith("group/T6/") and k.endswith("/eval_episodes")
    ]
    assert t6_groups and all(numbers[f"{g}/strict/graded"] == numbers[f"{g}/eval_episodes"] for g in t6_groups)
    assert not [k for k in numbers if k.startswith("group/T1/") and "/strict/" in k]
