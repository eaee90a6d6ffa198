"""The committed experiment results (``results/*/report``) agree with the code that reads them.

Each results directory whose report is committed holds the cells' raw metrics and the report's
``numbers.json``. ``capevo experiment verify`` recomputes every number from the metrics with
today's code, so a report written by older code that has since gained or changed a number fails
here, and the report must be written again (``capevo experiment report DIR``), not left stale.
A finished grid's ``cells/`` and ``run/cells/`` records are also checked to be ones the report can
read.

Invariants:
1. Every ``results/*/report/numbers.json`` verifies against its directory with no mismatch.
2. Every committed cell record of a run directory (``results/*/run/cells/*``) loads as ``done`` or
   ``failed`` (the runner tries a failed cell again), never ``unfinished`` or ``unreadable``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from capevo.experiment.run_files import load_cell
from capevo.experiment.verify import verify_run

RESULTS = Path(__file__).resolve().parents[1] / "results"
REPORTED = sorted(p.parents[1] for p in RESULTS.glob("*/report/numbers.json"))
RUN_CELLS = sorted(p for p in RESULTS.glob("*/run/cells/*") if p.is_dir() and not p.name.endswith(".partial"))


def test_there_are_committed_reports() -> None:
    # the parametrized test below would pass vacuously if the glob found nothing
    assert len(REPORTED) >= 5, REPORTED


@pytest.mark.parametrize("run_dir", REPORTED, ids=[p.name for p in REPORTED])
def test_committed_report_recomputes_from_its_metrics(run_dir: Path) -> None:
    mismatches = verify_run(run_dir)
    assert mismatches == [], "\n".join(str(m) for m in mismatches[:10])


def test_committed_cells_of_a_running_grid_are_finished() -> None:
    # git keeps a run directory's cells once finished (.gitignore), so that a fresh checkout skips
    # them: a cell committed unfinished would be run again over its records, and one that does
    # not load would be left out of the report
    problems = {}
    for cell_dir in RUN_CELLS:
        cell = load_cell(cell_dir.parents[1], cell_dir.name)
        if cell.status not in ("done", "failed"):
            problems[f"{cell_dir.parents[2].name}/{cell_dir.name}"] = cell.problem
    assert problems == {}
