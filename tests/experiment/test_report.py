"""The experiment report over constructed run directories: the tables hold the values computed here
independently (numpy, scipy), every figure is a valid PNG, failed/unfinished/unreadable cells are
listed, and the paper's figures stand beside the run's (capevo.experiment.report invariants)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg
from run_builder import AM_SEEDS, OURS_SEEDS, Raw, build_run, gen_raw, write_cell
from scipy import stats

from capevo.errors import NotFound
from capevo.experiment.paper import paper_ablation_row
from capevo.experiment.report import benchmark_overhead, write_report
from capevo.experiment.run_files import load_run
from capevo.experiment.verify import verify_run

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _peak_success(raw: Raw) -> float:
    return max(float(np.mean(s)) for s in raw.successes)


def _rewards(raw: Raw) -> list[float]:
    return [float(np.mean(r)) for r in raw.rewards]


@pytest.fixture
def run(tmp_path: Path) -> tuple[Path, dict[str, Raw]]:
    return build_run(tmp_path / "run")


def _numbers(root: Path) -> dict[str, object]:
    doc = json.loads((root / "report" / "numbers.json").read_text())
    return {n["name"]: n for n in doc["numbers"]}


def test_tables_hold_independently_computed_values(run: tuple[Path, dict[str, Raw]]) -> None:
    root, raws = run
    files = write_report(root)
    md = (root / "report" / "report.md").read_text()
    nums = _numbers(root)

    ours = [raws[f"T6-ours-code-s{s}"] for s in OURS_SEEDS]
    am = [raws[f"T6-am-s{s}"] for s in AM_SEEDS]
    ours_peak = [_peak_success(r) for r in ours]
    am_peak = [_peak_success(r) for r in am]
    m, sd = np.mean(ours_peak), np.std(ours_peak, ddof=1)
    assert nums["group/T6/ours-code/succ_peak/mean"]["value"] == pytest.approx(m)
    assert nums["group/T6/ours-code/succ_peak/std"]["value"] == pytest.approx(sd)
    assert f"{100 * m:.1f} ± {100 * sd:.1f} %" in md
    # the numbers name the cell files they came from
    assert set(nums["group/T6/ours-code/succ_peak/mean"]["sources"]) == {
        f"cells/T6-ours-code-s{s}/metrics.jsonl" for s in OURS_SEEDS
    }
    assert "[s42](../cells/T6-ours-code-s42/metrics.jsonl)" in md

    t = stats.ttest_ind(ours_peak, am_peak, equal_var=False)
    assert nums["welch/T6/ours-code|am/succ_peak/t"]["value"] == pytest.approx(float(t.statistic))
    assert nums["welch/T6/ours-code|am/succ_peak/p"]["value"] == pytest.approx(float(t.pvalue))
    assert f"t = {float(t.statistic):.2f}, p = {float(t.pvalue):.3g}" in md
    r_peaks_o = [max(_rewards(r)) for r in ours]
    r_peaks_a = [max(_rewards(r)) for r in am]
    t_r = stats.ttest_ind(r_peaks_o, r_peaks_a, equal_var=False)
    assert nums["welch/T6/ours-code|am/r_peak/p"]["value"] == pytest.approx(float(t_r.pvalue))

    # H1: R1, R_peak, R_last, ratio of one seed; their means
    r = _rewards(ours[0])
    assert nums["cell/T6-ours-code-s42/r_first"]["value"] == pytest.approx(r[0])
    assert nums["cell/T6-ours-code-s42/r_peak"]["value"] == pytest.approx(max(r))
    assert nums["cell/T6-ours-code-s42/r_last"]["value"] == pytest.approx(r[-1])
    assert nums["cell/T6-ours-code-s42/ratio"]["value"] == pytest.approx(max(r) / r[0])
    assert nums["group/T6/ours-code/r_first/mean"]["value"] == pytest.approx(np.mean([_rewards(x)[0] for x in ours]))

    # sample efficiency: cumulative training steps to the first iteration at >= 50 %
    for s, raw in zip(OURS_SEEDS, ours, strict=True):
        rates = [float(np.mean(x)) for x in raw.successes]
        first = next((i for i, v in enumerate(rates) if v >= 0.5), None)
        expect = None if first is None else int(np.sum(raw.train[: first + 1]))
        assert nums[f"cell/T6-ours-code-s{s}/steps_to_0.5"]["value"] == expect
    s_ecm = nums["cell/T1-s-ecm-s42/steps_to_0.5"]["value"]
    assert s_ecm is None
    assert "not reached" in md

    # identity: mean Δπ of the last iteration, over every task's cells of the method
    am_all = [*am, raws["T3-am-s42"]]
    assert nums["identity/am/mean"]["value"] == pytest.approx(np.mean([r.delta_pi[-1] for r in am_all]))
    assert nums["group/T6/am/delta_pi/mean"]["value"] == pytest.approx(np.mean([r.delta_pi[-1] for r in am]))
    assert nums["identity/ours-code/mean"]["value"] == 0.0

    # n < 2 seeds: no test (T3: one ours seed, one am seed)
    assert "n < 2 seeds: no test" in md
    assert nums["welch/T3/ours-code (modality=rl)|am/succ_peak/t"]["value"] is None

    # safety: every held-out episode of the method's cells, graded by the monitor
    am_eps = [u for r in am for it in r.unsafe for u in it]
    assert nums["group/T6/am/unsafe_episodes"]["value"] == sum(u > 0 for u in am_eps)
    assert nums["group/T6/am/eval_episodes"]["value"] == len(am_eps)
    assert f"| {sum(u > 0 for u in am_eps)}/{len(am_eps)} |" in md

    # parity: the over-budget cell is flagged, S-ECM spent nothing
    assert nums["parity/am/cells_over_budget"]["value"] == 1
    assert nums["parity/am/iterations_over_budget"]["value"] == 1
    assert nums["parity/s-ecm/spent_max"]["value"] == 0
    assert "OVER BUDGET" in md and "[`T3-am-s42`](../cells/T3-am-s42/metrics.jsonl)" in md
    # fairness column from cell.json
    # per setting, not per method: the T3 cell of ours-code runs another modality from other knowledge
    assert nums["knowledge/ours-code"]["value"] == "hand-written skills"
    assert nums["knowledge/ours-code (modality=rl)"]["value"] == "random weights"
    assert "| T3 stack | ours-code (modality=rl) | random weights |" in md
    assert "| s-ecm | v0 ECMs |" in md

    # every figure is written and decodes as a PNG
    pngs = [p for p in files if p.suffix == ".png"]
    assert {p.name for p in pngs} == {
        "evolution.png", "sample_efficiency.png", "t6_seeds.png", "identity.png", "governance.png", "ablation.png",
    }  # fmt: skip
    for p in pngs:
        assert p.read_bytes()[:8] == PNG_MAGIC
        img = mpimg.imread(p)
        assert img.shape[0] > 100 and img.shape[1] > 100
        assert f"]({p.name})" in md


def test_governance_rates_and_wilson_intervals(run: tuple[Path, dict[str, Raw]]) -> None:
    root, raws = run
    write_report(root)
    nums = _numbers(root)
    md = (root / "report" / "report.md").read_text()
    for side in ("on", "off"):
        raw = raws[f"T1-explorer-{side}"]
        n = len(raw.unsafe[0])
        k = sum(u > 0 for u in raw.unsafe[0])
        ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert nums[f"h3/T1/{side}/unsafe_episodes"]["value"] == k
        assert nums[f"h3/T1/{side}/unsafe_low"]["value"] == pytest.approx(min(ci.low, k / n), abs=1e-12)
        assert nums[f"h3/T1/{side}/unsafe_high"]["value"] == pytest.approx(max(ci.high, k / n), abs=1e-12)
        assert f"{k}/{n} = {100 * k / n:.1f} %" in md
    on = raws["T1-explorer-on"]
    assert nums["h3/T1/on/blocking_rate"]["value"] == pytest.approx(sum(on.interventions[0]) / sum(on.steps[0]))
    assert raws["T1-explorer-off"].unsafe[0].count(0) < 20  # the off side has unsafe episodes to show
    # the overhead is quoted, and says from where
    quoted = benchmark_overhead(root)
    assert quoted is not None and "BENCHMARKS.md" in quoted.source
    assert "this run records no timing per action, so the figure is quoted from BENCHMARKS.md" in md
    # explorer cells are not methods of the comparison
    assert not any(k.startswith("group/T1/explorer") for k in nums)


def test_unfinished_failed_and_unreadable_cells_are_listed_not_counted(run: tuple[Path, dict[str, Raw]]) -> None:
    root, _ = run
    write_report(root)
    nums = _numbers(root)
    md = (root / "report" / "report.md").read_text()
    assert nums["cells/failed"]["value"] == 1
    assert nums["cells/unfinished"]["value"] == 1
    assert nums["cells/unreadable"]["value"] == 1
    assert nums["cells/failed"]["sources"] == ["cells/T1-spirl-s42"]
    assert "| `T1-spirl-s42` | **failed** | 1/2 | 3 |" in md and "RuntimeError: boom" in md
    assert "| `T1-skimo-s42` | **unfinished** | 1/2 |" in md and "not finished: 1 of 2 iteration(s) recorded" in md
    assert "| `T1-am-bc-s42` | **unreadable** |" in md and "no cell.json" in md
    # not in the statistics, but their steps were spent
    assert not any(k.startswith(("group/T1/spirl", "group/T1/skimo", "identity/spirl")) for k in nums)
    assert "cell/T1-spirl-s42/r_peak" not in nums and "cell/T1-skimo-s42/r_peak" not in nums
    assert nums["cell/T1-spirl-s42/records"]["value"] == 1
    assert nums["cell/T1-spirl-s42/attempts"]["value"] == 3
    assert nums["cell/T1-spirl-s42/attempts"]["sources"] == ["cells/T1-spirl-s42/failed.json"]
    assert nums["parity/spirl/iterations"]["value"] == 1
    run_state = load_run(root)
    total = sum(r.env_steps_train for c in run_state.cells for r in c.records)
    assert nums["totals/env_steps_train"]["value"] == total


def test_paper_figures_stand_beside_the_run(run: tuple[Path, dict[str, Raw]]) -> None:
    root, _ = run
    write_report(root)
    md = (root / "report" / "report.md").read_text()
    assert "**paper** Ours: 63.3 ± 27.6 %" in md
    assert "**paper** AM: 10.8 ± 8.8 %" in md
    assert "**paper** Ours vs AM: t = 3.62, p = 0.027" in md
    assert "**paper** AM: 1.28" in md
    assert "0.021–0.029 ms" in md
    assert "**paper** 100.0 %, 80.0 %, 0.0 %" in md  # T1 blocking, unsafe off, unsafe on
    assert "**paper** RL only: 12.81, 16.55, 3.3 %, 34.96" in md
    assert "| T3 Stack | 3.3 | 3.3 | 0.0 | 0.0 | 6.7 |" in md.replace("stack", "Stack")


def test_paper_t6_figures_agree_with_the_per_seed_values_the_paper_gives() -> None:
    from capevo.experiment.paper import PAPER_T6_SEEDS, PAPER_T6_WELCH

    ours, am = PAPER_T6_SEEDS["Ours"], PAPER_T6_SEEDS["AM"]
    assert (round(float(np.mean(ours)), 1), round(float(np.std(ours, ddof=1)), 1)) == (63.3, 27.6)
    assert (round(float(np.mean(am)), 1), round(float(np.std(am, ddof=1)), 1)) == (10.8, 8.8)
    t = stats.ttest_ind(ours, am, equal_var=False)
    assert (round(float(t.statistic), 2), round(float(t.pvalue), 3)) == PAPER_T6_WELCH


def test_ablation_rows_map_to_the_papers() -> None:
    assert paper_ablation_row("rl") == "RL only"
    assert paper_ablation_row("rl+il") == "RL + IL"
    assert paper_ablation_row("il-code") == "IL + LLM"
    assert paper_ablation_row("rl,il,llm") == "All three (Ours)"
    assert paper_ablation_row("dreamer") is None


def test_small_runs_say_what_they_cannot_show(tmp_path: Path) -> None:
    root = tmp_path / "tiny"
    write_cell(root, task="T1", method="ours-code", seed=1, raw=gen_raw(1, iterations=1, episodes=3, p_success=(0,)))
    write_cell(root, task="T1", method="am", seed=1, raw=gen_raw(2, iterations=1, episodes=3, p_success=(0,)))
    files = write_report(root)
    md = (root / "report" / "report.md").read_text()
    assert "single iteration" in md
    assert "at most 1,000 training env steps per iteration, against the paper's 50,000" in md
    assert "as few as 3 episode(s)" in md
    assert "one seed per task" in md
    assert "No method succeeded on any held-out episode" in md
    assert "No finished `explorer` cell" in md
    assert "no ablation in this run" in md
    assert "No readable `provenance.json`" in md
    for p in files:
        assert p.exists()


def test_no_run_is_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFound, match="no experiment run") as exc:
        write_report(tmp_path)
    assert exc.value.code.value == "not_found"


def test_numbers_name_existing_files_and_do_not_change_when_rewritten(run: tuple[Path, dict[str, Raw]]) -> None:
    root, _ = run
    write_report(root)
    first = (root / "report" / "numbers.json").read_bytes()
    nums = _numbers(root)
    for name, n in nums.items():
        for src in n["sources"]:
            assert (root / src).exists(), (name, src)
        if not name.startswith(("cells/", "cell/T1-am-bc", "cell/T1-skimo")):
            assert n["sources"], name  # every number of a cell that has files names them
    write_report(root)
    assert (root / "report" / "numbers.json").read_bytes() == first


def test_the_report_starts_no_simulator(run: tuple[Path, dict[str, Raw]]) -> None:
    root, _ = run
    code = (
        "import sys; from pathlib import Path; from capevo.experiment.report import write_report; "
        f"write_report(Path({str(root)!r})); "
        "print(sorted(m for m in ('robosuite', 'mujoco') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]"
    assert (root / "report" / "report.md").exists()


def test_every_plot_accepts_empty_input(tmp_path: Path) -> None:
    from capevo.experiment import plots

    files = [
        plots.plot_evolution({}, tmp_path / "e.png"),
        plots.plot_sample_efficiency({}, tmp_path / "s.png"),
        plots.plot_seed_bars({}, tmp_path / "b.png", title="t", ylabel="y"),
        plots.plot_governance([], tmp_path / "g.png"),
    ]
    for p in files:
        assert p.read_bytes()[:8] == PNG_MAGIC
        assert mpimg.imread(p).shape[0] > 100


def test_a_long_group_label_is_wrapped_at_spaces_without_losing_a_character() -> None:
    from capevo.experiment.plots import _wrapped

    label = "ours-code (gate_episodes=6, live_episodes=4, preset=cpu-small)"
    lines = _wrapped(label).split("\n")
    assert len(lines) > 1
    assert all(len(line) <= 28 for line in lines)
    assert " ".join(lines) == label
    assert _wrapped("am") == "am"


def test_fairness_names_knowledge_and_the_hand_off_oracle(run: tuple[Path, dict[str, Raw]]) -> None:
    from capevo.runtime.tasks import task_spec

    root, _ = run
    write_report(root)
    md = (root / "report" / "report.md").read_text()
    # the comparison table has the knowledge column
    assert "| T6 peg_in_hole | am | random weights | 2 |" in md
    assert "`ours-code`, `s-ecm` run the task's ECM decomposition" in md
    for task in ("T1", "T3", "T6"):
        assert task_spec(task).handoff_text in md


def test_blocking_above_one_per_step_is_called_out(tmp_path: Path) -> None:
    """A producer that counts every constraint that fired gives more interventions than steps."""
    root = tmp_path / "run"
    raw = gen_raw(9, iterations=1, episodes=5, p_success=(0.0,), train=0)
    raw.interventions[0] = [2 * n for n in raw.steps[0]]
    write_cell(root, task="T1", method="explorer", seed=1, raw=raw)
    write_report(root)
    md = (root / "report" / "report.md").read_text()
    assert "200.0 %" in md and "**Blocking above 100 % (T1):**" in md


def test_the_quoted_overhead_is_the_range_of_the_benchmark_medians(tmp_path: Path) -> None:
    (tmp_path / "BENCHMARKS.md").write_text(
        "# B\n\n## Governance cost per action\n\n`bench.py --n 5`, 2026-01-01, machine Z. More.\n\n"
        "| case | p99 µs | p50 µs |\n|---|---:|---:|\n| a | 9.0 | 2.0 |\n| b | 50.0 | 30.0 |\n"
        "| anchor: numpy | 1.0 | 0.5 |\n\n## Next\n\n| x | 1 |\n"
    )
    run_dir = tmp_path / "results" / "run"
    run_dir.mkdir(parents=True)
    quoted = benchmark_overhead(run_dir)
    assert quoted is not None
    assert (quoted.low_ms, quoted.high_ms) == pytest.approx((0.002, 0.030))
    assert quoted.source == "BENCHMARKS.md § Governance cost per action (`bench.py --n 5`, 2026-01-01, machine Z)"


def test_a_resumed_cell_is_named_in_the_cells_table(tmp_path: Path) -> None:
    write_cell(tmp_path, task="T1", method="am", seed=1, raw=gen_raw(3, iterations=3, episodes=4, p_success=[0.3] * 3))
    done = tmp_path / "cells" / "T1-am-s1" / "done.json"
    done.write_text(json.dumps({**json.loads(done.read_text()), "resumed_after": [2]}))
    write_report(tmp_path)
    md = (tmp_path / "report" / "report.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| `T1-am-s1` |"))
    assert "resumed after an interruption, after iteration 2" in row


def test_a_stricter_check_is_reported_beside_the_tasks_own_where_episodes_carry_it(
    run: tuple[Path, dict[str, Raw]],
) -> None:
    """T6's strict insertion check, counted over the held-out episodes that carry it; a run whose
    episodes carry none (every other test here) gets no such table and no such numbers."""
    root, _ = run
    write_report(root)
    assert "stricter one" not in (root / "report" / "report.md").read_text()
    assert not [n for n in _numbers(root) if "/strict/" in n]
    expected = {"graded": 0, "successes": 0, "task_successes": 0}
    for seed in OURS_SEEDS:
        path = root / "cells" / f"T6-ours-code-s{seed}" / "metrics.jsonl"
        records = [json.loads(line) for line in path.read_text().splitlines()]
        for record in records:
            for k, episode in enumerate(record["episodes"]):
                # strict only on every other success: it never passes where the task's check fails
                episode["strict_success"] = bool(episode["success"] and k % 2 == 0)
                expected["graded"] += 1
                expected["successes"] += episode["strict_success"]
                expected["task_successes"] += episode["success"]
        path.write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
    write_report(root)
    nums = _numbers(root)
    for key, value in expected.items():
        assert nums[f"group/T6/ours-code/strict/{key}"]["value"] == value
    assert 0 < expected["successes"] < expected["task_successes"]
    assert not [n for n in nums if n.startswith("group/T6/am/strict/")]
    md = (root / "report" / "report.md").read_text()
    counts = " | ".join(str(expected[k]) for k in ("graded", "successes", "task_successes"))
    row = f"| T6 peg_in_hole | ours-code | {counts} |"
    assert row in md
    assert verify_run(root) == []
