"""``verify_run`` recomputes every number of a report from the raw metrics: it accepts a run just
reported, and names exactly the numbers an edit changed (capevo.experiment.verify invariants)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from run_builder import build_run

from capevo.errors import Corrupt, NotFound
from capevo.experiment.report import write_report
from capevo.experiment.verify import check_run, verify_run


@pytest.fixture
def reported(tmp_path: Path) -> Path:
    root, _ = build_run(tmp_path / "run")
    write_report(root)
    return root


def _edit_line(path: Path, line: int, edit: Callable[[dict[str, Any]], object]) -> None:
    lines = path.read_text().splitlines(keepends=True)
    row = json.loads(lines[line])
    edit(row)
    lines[line] = json.dumps(row, sort_keys=True) + "\n"
    path.write_text("".join(lines))


def test_a_run_just_reported_verifies(reported: Path) -> None:
    assert verify_run(reported) == []


def test_learner_steps_that_differ_from_their_traces_are_reported_and_fail_verify(tmp_path: Path) -> None:
    """Invariant 4: a cell's ``learner_steps_traced`` (counted on its host from the code learner's
    traces) must equal the loop's own count; a neural learner's row is not traced, not checked."""
    root, _ = build_run(tmp_path / "run")
    done = root / "cells" / "T6-ours-code-s42" / "done.json"
    doc = json.loads(done.read_text())
    doc["learner_steps_traced"] = [
        {"iteration": 0, "learner": "cem", "recorded": 700, "traced": 700},
        {"iteration": 1, "learner": "hybrid/cem", "recorded": 600, "traced": 900},  # the loop missed 300
        {"iteration": 2, "learner": "rl/rl-vm-1", "recorded": 800, "traced": 0},  # SAC: its env traces nothing
    ]
    done.write_text(json.dumps(doc))
    write_report(root)
    text = (root / "report" / "report.md").read_text()
    assert "2 iteration(s) checked, **1 differ**" in text
    assert verify_run(root) == [
        "cells/T6-ours-code-s42/done.json:iteration 1:learner_steps: reported 600, recomputed '900 traced' "
        "(cells/T6-ours-code-s42/done.json)"
    ]


def test_an_interrupted_attempts_learner_steps_are_accounted_not_a_mismatch(tmp_path: Path) -> None:
    """A resumed cell's interrupted attempt traced learner steps of its own (capevo.evolve.audit):
    discarded when the redo learned again, recorded when it gated that attempt's candidate."""
    root, _ = build_run(tmp_path / "run")
    done = root / "cells" / "T6-ours-code-s42" / "done.json"
    doc = json.loads(done.read_text())
    doc["learner_steps_traced"] = [
        {"iteration": 0, "learner": "cem", "recorded": 700, "traced": 700, "interrupted": 0},
        {"iteration": 1, "learner": "cem", "recorded": 600, "traced": 600, "interrupted": 250},  # learned again
        {"iteration": 2, "learner": "cem", "recorded": 800, "traced": 500, "interrupted": 300},  # gated its candidate
    ]
    doc["resumed_after"] = [1, 2]
    done.write_text(json.dumps(doc))
    write_report(root)
    text = (root / "report" / "report.md").read_text()
    assert "3 iteration(s) checked, all equal. Interrupted attempts" in text and "spent 250 learner" in text
    assert verify_run(root) == []


def test_an_edited_derived_field_is_the_one_mismatch(reported: Path) -> None:
    metrics = reported / "cells" / "T6-am-s7" / "metrics.jsonl"

    def edit(row: dict[str, Any]) -> None:
        row["success_rate"] = row["success_rate"] + 0.1

    _edit_line(metrics, 1, edit)
    out = verify_run(reported)
    assert len(out) == 1
    assert out[0].startswith("cells/T6-am-s7/metrics.jsonl:2:success_rate: reported ")


def test_an_edited_delta_pi_names_exactly_the_numbers_built_on_it(reported: Path) -> None:
    """Δπ of the last iteration of one AM cell feeds that cell's Δπ, the (T6, am) group's mean and
    std, and the method's mean and std over all its cells; nothing else."""
    metrics = reported / "cells" / "T6-am-s7" / "metrics.jsonl"
    _edit_line(metrics, 2, lambda row: row.update(delta_pi=5.0))
    mismatches = check_run(reported)
    assert {m.name for m in mismatches} == {
        "cell/T6-am-s7/delta_pi",
        "group/T6/am/delta_pi/mean",
        "group/T6/am/delta_pi/std",
        "identity/am/mean",
        "identity/am/std",
    }
    cell = next(m for m in mismatches if m.name == "cell/T6-am-s7/delta_pi")
    assert cell.reported == pytest.approx(1.2) and cell.recomputed == 5.0
    assert cell.sources == ("cells/T6-am-s7/metrics.jsonl",)
    text = [str(m) for m in mismatches]
    assert "cell/T6-am-s7/delta_pi: reported 1.2, recomputed 5.0 (cells/T6-am-s7/metrics.jsonl)" in [
        t.replace("1.2000000000000002", "1.2") for t in text
    ]


def test_an_edited_number_in_numbers_json_is_the_one_mismatch(reported: Path) -> None:
    path = reported / "report" / "numbers.json"
    doc = json.loads(path.read_text())
    entry = next(n for n in doc["numbers"] if n["name"] == "h3/T1/off/unsafe_episodes")
    entry["value"] += 1
    path.write_text(json.dumps(doc))
    out = verify_run(reported)
    assert len(out) == 1 and out[0].startswith("h3/T1/off/unsafe_episodes: reported ")


def test_a_cell_finished_after_the_report_is_reported(reported: Path) -> None:
    (reported / "cells" / "T1-skimo-s42" / "done.json").write_text(json.dumps({"wall_s": 1.0, "attempts": 1}))
    names = {m.name for m in check_run(reported)}
    assert "cells/unfinished" in names and "cells/done" in names
    assert "cell/T1-skimo-s42/r_peak" in names  # recomputed only: reported is absent
    absent = next(m for m in check_run(reported) if m.name == "cell/T1-skimo-s42/r_peak")
    assert absent.reported == "<absent>"


def test_a_lost_cell_is_reported(reported: Path) -> None:
    metrics = reported / "cells" / "T3-ours-code-s42" / "metrics.jsonl"
    metrics.unlink()
    names = {m.name for m in check_run(reported)}
    assert "cell/T3-ours-code-s42/r_peak" in names
    lost = next(m for m in check_run(reported) if m.name == "cell/T3-ours-code-s42/r_peak")
    assert lost.recomputed == "<absent>"


def test_no_report_is_not_found_and_a_foreign_file_is_corrupt(tmp_path: Path) -> None:
    root, _ = build_run(tmp_path / "run")
    with pytest.raises(NotFound, match="write the report first") as exc:
        verify_run(root)
    assert exc.value.code.value == "not_found"
    (root / "report").mkdir()
    (root / "report" / "numbers.json").write_text("[1, 2]")
    with pytest.raises(Corrupt, match="not a report's numbers file") as exc2:
        verify_run(root)
    assert exc2.value.code.value == "corrupt"
