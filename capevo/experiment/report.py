"""The report of an experiment run: ``RUN_DIR/report/report.md``, its PNG figures and ``numbers.json``
(issue 20 "Report", mirroring the paper's §4 tables and figures).

Sections and tables are numbered as the paper's source numbers them (§4 is "Evaluation"; Table 1
is the notation table of §2), with their LaTeX labels beside them.

The report reads the run directory only (``experiment.json``, ``provenance.json`` and
``cells/<key>/{cell.json, metrics.jsonl, done.json, failed.json}``, as the harness's runner
writes them) and needs no simulator. Its sections mirror the paper's evaluation:

* **Evolution (H1, paper §4.2, Table 3 ``tab:evolution``):** R₁, R_peak, R_last, Succ_peak and
  R_peak/R₁ per task and method, from the held-out evaluation after every iteration, with
  reward and success curves (mean and every seed).
* **Method comparison (H2, §4.3, Tables 4 and 5, Figure ``fig:t6-flagship``):** peak success
  and peak reward as mean ± std over seeds (std with ddof = 1, as the paper's 63.3 ± 27.6
  from its four seeds), and Welch's t-test (``scipy.stats.ttest_ind(equal_var=False)``) of ours
  (``ours-code``, ``ours-neural``) against AM (``am``, ``am-bc``) wherever both have at least two
  seeds. A per-seed plot for T6. A peak over iterations is the paper's statistic; it is biased
  upward by the evaluation's noise, so the table also gives the last iteration's success, and
  the held-out episodes (every iteration and seed) the independent safety monitor graded unsafe.
  Where held-out episodes carry a task's stricter check (T6: the peg through the plate, which
  robosuite's success does not require), a table counts it beside the task's own success.
* **Sample efficiency:** the cumulative training env steps each cell spent before its held-out
  success first reached 50 % and 80 %, and success against env steps.
* **Identity (§4.4, Figure ``fig:identity-drift``):** Δπ of the last iteration, mean per method.
* **Governance (H3, §4.5, Table 7 ``tab:safety``):** from the ``explorer`` cells, governance on
  and off: blocking rate (interventions per step), unsafe-episode rate with 95 % Wilson
  intervals. The run records no timing per action, so the overhead is quoted from
  BENCHMARKS.md's "Governance cost per action" and labelled as such.
* **Ablation (§4.6, Table 8 ``tab:ablation``):** T3 cells whose options name a learning
  modality (``options["modality"]`` or ``options["modalities"]``).
* **Fairness:** each method's ``knowledge`` (from ``cell.json``, also a column of the comparison),
  the hand-off asymmetry (ours and S-ECM hand off between ECMs on predicates over exact simulator
  state, :attr:`capevo.runtime.tasks.TaskSpec.handoff_text`; the baselines do not get those
  signals) and the budget parity check.
* **Settings and provenance**, and every cell with its status.

What is computed and what is quoted: every number of the run comes from
:func:`capevo.experiment.numbers.compute_numbers` (the one computation, which
:func:`capevo.experiment.verify.verify_run` repeats), read from the run directory by
:mod:`capevo.experiment.run_files`, and is written with the files it came from into
``numbers.json``. The paper's figures are the constants of :mod:`capevo.experiment.paper`, labelled
"paper" wherever they appear; the governance overhead is quoted from BENCHMARKS.md.

Invariants:
1. :func:`write_report` reads nothing outside the run directory except BENCHMARKS.md (for the
   quoted overhead) and starts no simulator.
2. Only finished cells enter the statistics; failed, unfinished and unreadable cells are listed in
   the report with the reason, never dropped (:mod:`capevo.experiment.run_files`).
3. Every number of the run shown in ``report.md``'s tables is an entry of ``numbers.json``.
4. Writing the report twice from the same files gives equal ``numbers.json``.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.evolve.metrics import write_atomically
from capevo.experiment.numbers import (
    AM,
    EXPLORER,
    NUMBERS_JSON,
    OURS,
    THRESHOLDS,
    Book,
    Groups,
    compute_numbers,
    groups_of,
    numbers_document,
)
from capevo.experiment.paper import (
    PAPER_ABLATION,
    PAPER_BUDGET,
    PAPER_COLUMN,
    PAPER_DELTA_PI,
    PAPER_EVOLUTION,
    PAPER_GOVERNANCE,
    PAPER_METHODS,
    PAPER_PEAK_REWARD,
    PAPER_PEAK_SUCCESS,
    PAPER_T6_SEEDS,
    PAPER_T6_WELCH,
    paper_ablation_row,
)
from capevo.experiment.run_files import (
    CELL_JSON,
    CELLS,
    DONE,
    EXPERIMENT_JSON,
    FAILED,
    METRICS,
    PROVENANCE_JSON,
    Cell,
    Run,
    handoff_text,
    load_run,
    modality_of,
    task_title,
    uses_decomposition,
)

REPORT_DIR = "report"
REPORT_MD = "report.md"

EVOLUTION_PNG = "evolution.png"
T6_SEEDS_PNG = "t6_seeds.png"
EFFICIENCY_PNG = "sample_efficiency.png"
IDENTITY_PNG = "identity.png"
GOVERNANCE_PNG = "governance.png"
ABLATION_PNG = "ablation.png"

FLAGSHIP_TASK = "T6"

# --- quoted: the governance overhead from BENCHMARKS.md -------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class QuotedOverhead:
    low_ms: float
    high_ms: float
    source: str
    """The file and section, and the line that names its command."""


def benchmark_overhead(run_dir: Path) -> QuotedOverhead | None:
    """The p50 range of BENCHMARKS.md's "Governance cost per action" table (its anchor row left out),
    from the first BENCHMARKS.md above the run directory or beside the capevo package."""
    import capevo

    candidates = [p / "BENCHMARKS.md" for p in (run_dir.resolve(), *run_dir.resolve().parents)]
    candidates.append(Path(capevo.__file__).resolve().parents[1] / "BENCHMARKS.md")
    for path in candidates:
        if not path.is_file():
            continue
        text = path.read_text(encoding="utf-8")
        m = re.search(r"^## Governance cost per action\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
        if not m:
            continue
        section = m.group(1)
        rows = [
            [c.strip() for c in line.strip().strip("|").split("|")]
            for line in section.splitlines()
            if line.lstrip().startswith("|")
        ]
        # the column is found by its header ("p50 µs" or "p50 ms"), not by its position
        col = next((i for i, h in enumerate(rows[0]) if "p50" in h), None) if rows else None
        if col is None:
            continue
        scale = 1.0 if "ms" in rows[0][col] else 1e-3
        p50 = []
        for cols in rows[1:]:
            if len(cols) > col and not cols[0].startswith("anchor"):
                try:
                    p50.append(float(cols[col]) * scale)
                except ValueError:
                    continue
        if not p50:
            continue
        # the section's first sentence names the command, the date and the machine
        first = " ".join(section.strip().split("\n\n", 1)[0].split()).split(". ", 1)[0]
        first = first if len(first) <= 200 else first[:199] + "…"
        return QuotedOverhead(
            low_ms=min(p50),
            high_ms=max(p50),
            source=f"{path.name} § Governance cost per action ({first})",
        )
    return None


# --- Markdown -------------------------------------------------------------------------------------


def _pct(x: Any) -> str:
    return "-" if x is None else f"{100 * float(x):.1f} %"


def _r(x: Any) -> str:
    return "-" if x is None else f"{float(x):.2f}"


def _steps(x: Any) -> str:
    return "-" if x is None else f"{float(x):,.0f}"


def _p(x: Any) -> str:
    return "-" if x is None else f"{float(x):.3g}"


def _esc(text: str) -> str:
    return text.replace("|", "\\|")


def _pm(book: Book, base: str, fmt: Any) -> str:
    """``mean ± std`` of a group field (std shown only with two or more seeds)."""
    m, sd = book.get(f"{base}/mean"), book.get(f"{base}/std")
    if m is None:
        return "-"
    return fmt(m) if sd is None else f"{fmt(m)} ± {fmt(sd)}"


def _pm_pct(book: Book, base: str) -> str:
    m, sd = book.get(f"{base}/mean"), book.get(f"{base}/std")
    if m is None:
        return "-"
    return f"{100 * m:.1f} %" if sd is None else f"{100 * m:.1f} ± {100 * sd:.1f} %"


def _links(cells: Sequence[Cell], name: str = METRICS) -> str:
    return " ".join(f"[s{c.spec.seed if c.spec else '?'}](../{c.path}/{name})" for c in cells)


def _few_notes(run: Run, book: Book, learning: Sequence[Cell]) -> list[str]:
    """What the run is too small to show (issue 20: where a budget is too small, say so)."""
    if not learning:
        return ["No learning cell finished: there is nothing to compare."]
    notes = []
    if book.get("run/max_iterations") < 2:
        notes.append(
            "Every cell ran a single iteration: R_peak, R_last and R₁ are the same evaluation, so these tables "
            "cannot show evolution over iterations."
        )
    budget = book.get("run/budget_max")
    if budget < PAPER_BUDGET:
        notes.append(
            f"The budget is at most {_steps(budget)} training env steps per iteration, against the paper's "
            f"{PAPER_BUDGET:,} per ECM per iteration: compare directions, not levels, with the paper's figures."
        )
    eps = book.get("run/min_eval_episodes")
    if eps < 30:
        notes.append(
            f"Held-out evaluations have as few as {eps} episode(s): a success rate moves in steps of "
            f"{100 / max(eps, 1):.0f} points, and peak-over-iterations values are biased upward by that noise "
            "(the paper used 30)."
        )
    if book.get("run/max_seeds") < 2:
        notes.append("Every method has one seed per task: no standard deviation and no test can be given.")
    if book.get("run/max_success") == 0:
        notes.append("No method succeeded on any held-out episode: only rewards can be compared.")
    return notes


def markdown(run: Run, book: Book, overhead: QuotedOverhead | None, figures: Mapping[str, str]) -> str:
    """``report.md`` (see the module docstring); ``figures`` maps each written figure's key to its file."""
    learning = [c for c in run.done() if c.method != EXPLORER]
    groups = groups_of(learning)
    L: list[str] = []
    add = L.append
    preset = (run.config or {}).get("preset") or (run.config or {}).get("name") or "-"
    add(f"# capevo experiment: {run.root.name}")
    add("")
    add(
        f"*Written {time.strftime('%Y-%m-%d %H:%M:%SZ', time.gmtime())} from `{CELLS}/`; preset `{preset}`. "
        f"Cells: {book.get('cells/done')} finished, {book.get('cells/failed')} failed, "
        f"{book.get('cells/unfinished')} unfinished, {book.get('cells/unreadable')} unreadable. Every number of "
        f"the run is in [`{NUMBERS_JSON}`]({NUMBERS_JSON}) with the files it came from; `capevo experiment verify` "
        "recomputes them. Rows marked **paper** quote the paper's published figures; they are not measured here.*"
    )
    add("")
    add(
        "All rewards and success rates are from the held-out evaluation after each iteration (seeds no learner, "
        "gate or live episode uses, the same for every method of a task and seed). Standard deviations are over "
        "seeds (ddof = 1)."
    )
    add("")
    notes = _few_notes(run, book, learning)
    if notes:
        add("**What this run is too small to show.**")
        add("")
        for n in notes:
            add(f"- {n}")
        add("")
    for section in (_evolution, _comparison, _efficiency, _identity):
        section(add, book, groups, figures)
    _governance(add, run, book, overhead, figures)
    _ablation(add, book, learning, figures)
    _fairness(add, run, book)
    _settings(add, run, book)
    _cells(add, run, book)
    return "\n".join(L) + "\n"


def _figure(add: Callable[[str], None], figures: Mapping[str, str], key: str, alt: str) -> None:
    if key in figures:
        add(f"![{alt}]({figures[key]})")
        add("")


def _evolution(add: Callable[[str], None], book: Book, groups: Groups, figures: Mapping[str, str]) -> None:
    add("## Evolution over iterations (H1; paper §4.2, Table 3)")
    add("")
    if not groups:
        add("No learning cell finished.")
        add("")
        return
    add("| task | method | seeds | R₁ | R_peak | R_last | Succ_peak | R_peak/R₁ | files |")
    add("|---|---|---|---|---|---|---|---|---|")
    for task in sorted({t for t, _ in groups}):
        for (t, label), cells in groups.items():
            if t != task:
                continue
            b = f"group/{t}/{label}"
            add(
                f"| {task_title(t)} | {_esc(label)} | {book.get(b + '/r_first/n')} | {_pm(book, b + '/r_first', _r)} | "
                f"{_pm(book, b + '/r_peak', _r)} | {_pm(book, b + '/r_last', _r)} | "
                f"{_pm_pct(book, b + '/succ_peak')} | {_ratio(book, b)} | {_links(cells)} |"
            )
        if task in PAPER_EVOLUTION:
            r1, rp, r20, sp, ratio = PAPER_EVOLUTION[task]
            add(
                f"| {task_title(task)} | **paper** (Ours, Table 3; R_last = R₂₀) | - | {r1:.2f} | {rp:.2f} | "
                f"{r20:.2f} | {sp:.1f} % | {ratio:.1f}× | - |"
            )
    add("")
    add(
        "R₁ is the first iteration's evaluation; R_peak/R₁ is left out (-) where R₁ ≤ 0. The paper ran 20 "
        "iterations of 50,000 env steps per ECM; compare the shape, not the scale, when this run is smaller."
    )
    add("")
    _figure(add, figures, "evolution", "evolution")


def _comparison(add: Callable[[str], None], book: Book, groups: Groups, figures: Mapping[str, str]) -> None:
    add("## Method comparison (H2; paper §4.3, Tables 4 and 5)")
    add("")
    if not groups:
        add("No learning cell finished.")
        add("")
        return
    add(
        "| task | method | starts from | seeds | peak success | last success | peak reward | "
        "unsafe held-out episodes | paper peak success | paper peak reward | files |"
    )
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    for (t, label), cells in groups.items():
        b = f"group/{t}/{label}"
        col = PAPER_COLUMN.get(cells[0].method)
        ps = PAPER_PEAK_SUCCESS.get(t, {}).get(col) if col else None
        pr = PAPER_PEAK_REWARD.get(t, {}).get(col) if col else None
        add(
            f"| {task_title(t)} | {_esc(label)} | {_esc(book.get(f'knowledge/{label}') or '-')} | "
            f"{book.get(b + '/succ_peak/n')} | {_pm_pct(book, b + '/succ_peak')} | "
            f"{_pm_pct(book, b + '/succ_last')} | {_pm(book, b + '/r_peak', _r)} | "
            f"{book.get(b + '/unsafe_episodes')}/{book.get(b + '/eval_episodes')} | "
            f"{f'**paper** {col}: {ps} %' if ps else '-'} | {f'**paper** {col}: {pr:.2f}' if pr is not None else '-'} "
            f"| {_links(cells)} |"
        )
    add("")
    add(
        "Unsafe held-out episodes: of every held-out evaluation episode of every iteration and seed, those with a "
        "step the independent safety monitor graded unsafe (what governance let through)."
    )
    add("")
    strict = [(t, label) for (t, label) in groups if book.get(f"group/{t}/{label}/strict/graded") is not None]
    if strict:
        add(
            "Success above is the task's own check (robosuite's `_check_success`, as in the paper). Where a task "
            "also has a stricter one (T6: the peg's tip through the plate, which robosuite's check does not "
            "require; `capevo.runtime.tasks.peg_in_hole`), on the same held-out episodes:"
        )
        add("")
        add("| task | method | held-out episodes | strict check passed | task's success |")
        add("|---|---|---|---|---|")
        for t, label in strict:
            b = f"group/{t}/{label}/strict"
            add(
                f"| {task_title(t)} | {_esc(label)} | {book.get(b + '/graded')} | {book.get(b + '/successes')} | "
                f"{book.get(b + '/task_successes')} |"
            )
        add("")
    add("Welch's t-test (`scipy.stats.ttest_ind(equal_var=False)`) of per-seed peaks, ours against AM:")
    add("")
    add("| task | ours | AM | seeds | peak success: t, p | peak reward: t, p | paper |")
    add("|---|---|---|---|---|---|---|")
    pairs = 0
    for (t, a_label), a_cells in groups.items():
        for (t2, b_label), b_cells in groups.items():
            if t2 != t or a_cells[0].method not in OURS or b_cells[0].method not in AM:
                continue
            pairs += 1
            base = f"welch/{t}/{a_label}|{b_label}"
            na, nb = book.get(f"group/{t}/{a_label}/succ_peak/n"), book.get(f"group/{t}/{b_label}/succ_peak/n")
            tests = [
                "n < 2 seeds: no test"
                if min(na, nb) < 2
                else "undefined (no variance on either side)"
                if book.get(f"{base}/{f}/t") is None
                else f"t = {book.get(f'{base}/{f}/t'):.2f}, p = {_p(book.get(f'{base}/{f}/p'))}"
                for f in ("succ_peak", "r_peak")
            ]
            paper = (
                f"**paper** Ours vs AM: t = {PAPER_T6_WELCH[0]}, p = {PAPER_T6_WELCH[1]} (4 vs 4 seeds, success)"
                if t == FLAGSHIP_TASK
                else "-"
            )
            add(
                f"| {task_title(t)} | {_esc(a_label)} | {_esc(b_label)} | {na} vs {nb} | {tests[0]} | {tests[1]} | "
                f"{paper} |"
            )
    if not pairs:
        add("| - | - | - | - | no task has both ours and AM finished | - | - |")
    add("")
    add("The paper's Table 4 in full (peak success %, T6 Ours and AM over four seeds, the rest seed 42):")
    add("")
    add("| **paper** task | " + " | ".join(PAPER_METHODS) + " |")
    add("|---|" + "---|" * len(PAPER_METHODS))
    for t, row in PAPER_PEAK_SUCCESS.items():
        add(f"| {task_title(t)} | " + " | ".join(row[m] for m in PAPER_METHODS) + " |")
    add("")
    add(
        "The paper's §4.3 text says every method scores 0 % on T2–T5, but its Table 4 gives T3 3.3 % (Ours, AM) "
        "and 6.7 % (SkiMo); the table is quoted as published."
    )
    add("")
    _figure(add, figures, "t6", "T6 per seed")


def _efficiency(add: Callable[[str], None], book: Book, groups: Groups, figures: Mapping[str, str]) -> None:
    add("## Sample efficiency")
    add("")
    if not groups:
        add("No learning cell finished.")
        add("")
        return
    add(
        "Training env steps (cumulative `env_steps_train`, the held-out evaluation not counted) spent before the "
        "held-out success first reached 50 % and 80 %; the mean is over the seeds that reached it."
    )
    add("")
    add(
        "| task | method | ≥ 50 %: seeds reached | mean steps | ≥ 80 %: seeds reached | mean steps | per seed | files |"
    )
    add("|---|---|---|---|---|---|---|---|")
    for (t, label), cells in groups.items():
        cols = []
        n = book.get(f"group/{t}/{label}/r_first/n")
        for th in THRESHOLDS:
            base = f"efficiency/{t}/{label}/{th:g}"
            k = book.get(f"{base}/reached")
            cols += [f"{k}/{n}", "not reached" if not k else _steps(book.get(f"{base}/mean"))]
        per_seed = "; ".join(
            f"s{c.spec.seed if c.spec else '?'}: "
            + ", ".join(
                "not reached"
                if book.get(f"cell/{c.key}/steps_to_{th:g}") is None
                else _steps(book.get(f"cell/{c.key}/steps_to_{th:g}"))
                for th in THRESHOLDS
            )
            for c in cells
        )
        add(f"| {task_title(t)} | {_esc(label)} | {' | '.join(cols)} | {per_seed} | {_links(cells)} |")
    add("")
    _figure(add, figures, "efficiency", "sample efficiency")


def _identity(add: Callable[[str], None], book: Book, groups: Groups, figures: Mapping[str, str]) -> None:
    add("## Identity: Δπ (paper §4.4)")
    add("")
    if not groups:
        add("No learning cell finished.")
        add("")
        return
    add("| method | cells | mean Δπ (last iteration) | per task | paper Δπ | files |")
    add("|---|---|---|---|---|---|")
    for label in sorted({label for _, label in groups}):
        cells = [c for (_, lab), cs in groups.items() if lab == label for c in cs]
        per_task = ", ".join(
            f"{t}: {_r(book.get(f'group/{t}/{label}/delta_pi/mean'))}" for t, lab in groups if lab == label
        )
        col = PAPER_COLUMN.get(cells[0].method)
        paper = f"**paper** {col}: {PAPER_DELTA_PI[col]:.2f}" if col else "-"
        add(
            f"| {_esc(label)} | {book.get(f'identity/{label}/n')} | {_pm(book, f'identity/{label}', _r)} | "
            f"{per_task} | {paper} | {_links(cells)} |"
        )
    add("")
    add(
        "Δπ is each method's own measure of how far the agent's decision policy moved since iteration 0 (the "
        "tensors each baseline's docstring names); 0 for ours by construction, where the agent is frozen. The "
        "paper's figures are means over its six tasks."
    )
    add("")
    _figure(add, figures, "identity", "identity")


def _ratio(book: Book, base: str) -> str:
    m, sd = book.get(f"{base}/ratio/mean"), book.get(f"{base}/ratio/std")
    n = book.get(f"{base}/ratio/n")
    if m is None:
        return "-"
    text = f"{m:.1f}×" if sd is None else f"{m:.1f} ± {sd:.1f}×"
    return text if n == book.get(f"{base}/r_first/n") else f"{text} ({n} seed(s) with R₁ > 0)"


def _governance(add: Any, run: Run, book: Book, overhead: QuotedOverhead | None, figures: Mapping[str, str]) -> None:
    add("## Governance (H3; paper §4.5, Table 7)")
    add("")
    explorer = [c for c in run.done() if c.method == EXPLORER]
    if not explorer:
        add(f"No finished `{EXPLORER}` cell in this run: no governance figures.")
        add("")
    else:
        add(
            f"From the `{EXPLORER}` cells (the aggressive exploratory policy), every held-out episode of every "
            "iteration. Blocking rate: governance interventions per executed step, with governance on; with it "
            "off, the steps governance would have changed (the explorer's counting governor). Unsafe: "
            "episodes with a step the independent safety monitor graded unsafe, with 95 % Wilson intervals. The "
            "blocking rate has no interval: steps of one episode are not independent draws."
        )
        add("")
        add(
            "| task | episodes on / off | blocking rate (on) | would block (off) | unsafe on | unsafe off | "
            "paper: blocking, unsafe off, unsafe on | files |"
        )
        add("|---|---|---|---|---|---|---|---|")
        for task in sorted({c.task for c in explorer}):
            cells = [c for c in explorer if c.task == task]

            def rate(side: str, task: str = task) -> str:
                b = f"h3/{task}/{side}"
                if book.get(f"{b}/episodes") is None:
                    return f"no governance-{side} cell"
                return (
                    f"{book.get(f'{b}/unsafe_episodes')}/{book.get(f'{b}/episodes')} = "
                    f"{_pct(book.get(f'{b}/unsafe_rate'))} [{_pct(book.get(f'{b}/unsafe_low'))}, "
                    f"{_pct(book.get(f'{b}/unsafe_high'))}]"
                )

            def block(side: str, task: str = task) -> str:
                b = f"h3/{task}/{side}"
                if book.get(f"{b}/episodes") is None:
                    return "-"
                return (
                    f"{book.get(f'{b}/interventions')}/{book.get(f'{b}/steps')} = "
                    f"{_pct(book.get(f'{b}/blocking_rate'))}"
                )

            on_n, off_n = book.get(f"h3/{task}/on/episodes"), book.get(f"h3/{task}/off/episodes")
            paper = PAPER_GOVERNANCE.get(task)
            ptext = f"**paper** {paper[0]:.1f} %, {paper[1]:.1f} %, {paper[2]:.1f} %" if paper else "-"
            add(
                f"| {task_title(task)} | {on_n if on_n is not None else 0} / {off_n if off_n is not None else 0} | "
                f"{block('on')} | {block('off')} | {rate('on')} | {rate('off')} | {ptext} | {_links(cells)} |"
            )
        add("")
        over = [
            t
            for t in sorted({c.task for c in explorer})
            for side in ("on", "off")
            if (book.get(f"h3/{t}/{side}/blocking_rate") or 0.0) > 1.0
        ]
        if over:
            add(
                f"**Blocking above 100 % ({', '.join(sorted(set(over)))}):** these cells' `interventions` count every "
                "constraint that fired (several per step), not the steps governance changed, which "
                "`EpisodeResult.interventions` is meant to count; the ratio overstates the paper's fraction of "
                "actions modified or rejected and is not comparable with it."
            )
            add("")
    if overhead is None:
        add(
            "Overhead per action: this run records no timing per action and no BENCHMARKS.md with a governance "
            "figure was found; **paper**: 0.021–0.029 ms (Table 7)."
        )
    else:
        add(
            f"Overhead per action: this run records no timing per action, so the figure is quoted from "
            f"{overhead.source}: {overhead.low_ms:.4f}–{overhead.high_ms:.4f} ms (the range of its cases' medians); "
            "**paper**: 0.021–0.029 ms (Table 7)."
        )
    add("")
    _figure(add, figures, "governance", "governance")


def _ablation(add: Any, book: Book, learning: Sequence[Cell], figures: Mapping[str, str]) -> None:
    add("## Learning-modality ablation on T3 (paper §4.6, Table 8)")
    add("")
    cells = [c for c in learning if c.task == "T3" and c.spec and modality_of(c.spec) is not None]
    if not cells:
        add("No finished T3 cell names a learning modality (`options.modality`): no ablation in this run.")
        add("")
        return
    add("| configuration | modality | seeds | R_final | R_peak | Succ_peak | σ²_final | paper (Table 8) | files |")
    add("|---|---|---|---|---|---|---|---|---|")
    for (t, label), group in groups_of(cells).items():
        b = f"group/{t}/{label}"
        modality = modality_of(group[0].spec) if group[0].spec else ""
        row = paper_ablation_row(modality or "")
        paper = "-"
        if row:
            rf, rp, sp, var = PAPER_ABLATION[row]
            paper = f"**paper** {row}: {rf:.2f}, {rp:.2f}, {sp:.1f} %, {var:.2f}"
        add(
            f"| {_esc(label)} | {modality} | {len(group)} | {_pm(book, b + '/r_last', _r)} | "
            f"{_pm(book, b + '/r_peak', _r)} | {_pm_pct(book, b + '/succ_peak')} | "
            f"{_pm(book, b + '/reward_var_last', _r)} | {paper} | {_links(group)} |"
        )
    add("")
    add("σ²_final: sample variance of the last evaluation's episode rewards, mean over seeds.")
    add("")
    _figure(add, figures, "ablation", "ablation")


def _fairness(add: Any, run: Run, book: Book) -> None:
    add("## Fairness: what each method starts from, and what it spent")
    add("")
    methods = sorted({c.method for c in run.cells if c.spec})
    if not methods:
        add("No readable cell.")
        add("")
        return
    add("| method | knowledge it starts from | cells |")
    add("|---|---|---|")
    for label in sorted({c.label for c in run.cells if c.spec}):
        cells = [c for c in run.cells if c.spec and c.label == label]
        add(f"| {_esc(label)} | {_esc(book.get(f'knowledge/{label}') or '-')} | {_links(cells, CELL_JSON)} |")
    add("")
    decomposed = sorted(m for m in methods if uses_decomposition(m))
    if decomposed:
        add(
            f"Hand-offs: {', '.join(f'`{m}`' for m in decomposed)} run the task's ECM decomposition, whose "
            "termination and applicability predicates read exact simulator state; the other methods act on the "
            "task's (perturbed) observation and reward (`capevo.baselines.governed_env`) and do not get these "
            "signals. Per task:"
        )
        add("")
        for task in sorted({c.task for c in run.cells if c.spec}):
            add(f"- {task_title(task)}: {handoff_text(task)}")
        add("")
    add(
        "Budget parity: training env steps each iteration actually spent (`env_steps_train`) against the budget "
        "per iteration, over every recorded iteration (finished or not)."
    )
    add("")
    add(
        "| method | budget / iteration | iterations | spent min | mean | max | iterations over budget "
        "| cells over budget |"
    )
    add("|---|---|---|---|---|---|---|---|")
    labels = sorted({c.label for c in run.cells if c.spec and c.records})
    for label in labels:
        b = f"parity/{label}"
        lo, hi = book.get(f"{b}/budget_min"), book.get(f"{b}/budget_max")
        budget = _steps(lo) if lo == hi else f"{_steps(lo)}–{_steps(hi)}"
        over = book.get(f"{b}/cells_over_budget")
        add(
            f"| {_esc(label)} | {budget} | {book.get(f'{b}/iterations')} | {_steps(book.get(f'{b}/spent_min'))} | "
            f"{_steps(book.get(f'{b}/spent_mean'))} | {_steps(book.get(f'{b}/spent_max'))} | "
            f"{book.get(f'{b}/iterations_over_budget')} | {'**' + str(over) + ' OVER BUDGET**' if over else '0'} |"
        )
    add("")
    over_cells = [
        c
        for c in run.cells
        if c.spec and any(r.env_steps_train > c.spec.budget.env_steps_per_iteration for r in c.records)
    ]
    if over_cells:
        add("Cells over budget: " + ", ".join(f"[`{c.key}`](../{c.metrics_file})" for c in over_cells) + ".")
    else:
        add("No cell spent more than its budget in any iteration.")
    add("")
    traced = [label for label in labels if book.get(f"parity/{label}/traced_iterations") is not None]
    if traced:
        add(
            "The learner steps in `env_steps_train` are the loop's own sum. Each cell also counted, on the host "
            "that ran it, the steps in its code learners' MCAP traces (`learner_steps_traced` in `done.json`; "
            "`capevo.evolve.audit`):"
        )
        add("")
        for label in traced:
            n = book.get(f"parity/{label}/traced_iterations")
            bad = book.get(f"parity/{label}/traced_iterations_differing")
            verdict = "all equal" if not bad else f"**{bad} differ**"
            lost = book.get(f"parity/{label}/discarded_learner_steps")
            extra = (
                f" Interrupted attempts (cells resumed after an interruption) also spent {_steps(lost)} learner "
                "env steps that their iteration's redo learned again; they are not in `env_steps_train`."
                if lost
                else ""
            )
            add(f"- {_esc(label)}: {n} iteration(s) checked, {verdict}.{extra}")
        add("")


def _settings(add: Any, run: Run, book: Book) -> None:
    add("## Settings and provenance")
    add("")
    add(
        f"Env steps spent by every recorded iteration: {_steps(book.get('totals/env_steps_train'))} training, "
        f"{_steps(book.get('totals/env_steps_eval'))} held-out evaluation, over {book.get('totals/iterations')} "
        f"iteration(s); wall time of the finished cells (sum of `done.json`): "
        f"{book.get('totals/cell_wall_s'):.0f} s."
    )
    add("")
    prov = run.provenance
    if prov:
        add(f"Provenance ([`{PROVENANCE_JSON}`](../{PROVENANCE_JSON})):")
        add("")
        add("| | |")
        add("|---|---|")
        for k, v in prov.items():
            add(f"| {_esc(str(k))} | {_esc(_plain(v))} |")
        add("")
    else:
        add(f"No readable `{PROVENANCE_JSON}`.")
        add("")
    cfg = run.config
    if cfg:
        add(f"Configuration ([`{EXPERIMENT_JSON}`](../{EXPERIMENT_JSON})):")
        add("")
        yaml_texts = {k: v for k, v in cfg.items() if isinstance(v, str) and "\n" in v}
        rest = {k: v for k, v in cfg.items() if k not in yaml_texts}
        add("```json")
        add(json.dumps(rest, indent=2, sort_keys=True, default=str))
        add("```")
        for k, v in yaml_texts.items():
            add("")
            add(f"`{k}`:")
            add("")
            add("```yaml")
            add(v.rstrip("\n"))
            add("```")
        add("")
    else:
        add(f"No readable `{EXPERIMENT_JSON}`.")
        add("")


def _commit(done: Mapping[str, Any] | None) -> str:
    """The short commit that ran a cell (``done.json``), ``-`` for cells from before it was kept."""
    commit = (done or {}).get("capevo_commit")
    if not isinstance(commit, str) or not commit:
        return "-"
    return f"`{commit[:9]}{'-dirty' if commit.endswith('-dirty') else ''}`"


def _plain(v: Any) -> str:
    """A provenance value as text: mappings as ``key value, ...``, a command list as its words."""
    if isinstance(v, Mapping):
        return ", ".join(f"{k} {_plain(x)}" for k, x in v.items())
    if isinstance(v, list | tuple):
        return " ".join(str(x) for x in v) if all(isinstance(x, str) for x in v) else json.dumps(v)
    return str(v)


def _cells(add: Any, run: Run, book: Book) -> None:
    add("## Cells")
    add("")
    if not run.cells:
        add("The run has no cell.")
        return
    add(
        "| cell | status | iterations | attempts | commit | R₁ | R_peak | Succ_peak | Δπ | train steps | eval steps | "
        "wall s | note | files |"
    )
    add("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c in run.cells:
        planned = c.spec.iterations if c.spec else "?"
        k = f"cell/{c.key}"
        files = [f"[cell.json](../{c.path}/{CELL_JSON})"]
        if (run.root / c.metrics_file).exists():
            files.append(f"[metrics](../{c.metrics_file})")
        for name in (DONE, FAILED):
            if (run.root / c.path / name).exists():
                files.append(f"[{name}](../{c.path}/{name})")
        shown = book.get(f"{k}/iterations") is not None
        attempts, wall = book.get(f"{k}/attempts"), book.get(f"{k}/wall_s")
        add(
            f"| `{c.key}` | {'**' + c.status + '**' if c.status != 'done' else c.status} | "
            f"{book.get(k + '/records')}/{planned} | {attempts if attempts is not None else '-'} | "
            f"{_commit(c.done)} | {_r(book.get(k + '/r_first')) if shown else '-'} | "
            f"{_r(book.get(k + '/r_peak')) if shown else '-'} | "
            f"{_pct(book.get(k + '/succ_peak')) if shown else '-'} | "
            f"{_r(book.get(k + '/delta_pi')) if shown else '-'} | "
            f"{_steps(book.get(k + '/env_steps_train')) if shown else '-'} | "
            f"{_steps(book.get(k + '/env_steps_eval')) if shown else '-'} | "
            f"{f'{wall:.0f}' if wall is not None else '-'} | {_esc(c.problem) or '-'} | {' '.join(files)} |"
        )
    add("")
    add(
        "Only finished cells enter the tables above; a failed or unfinished cell's steps still count in the totals "
        "and the budget parity. Explorer cells appear only in the governance table."
    )


# --- writing ----------------------------------------------------------------------------------------


def _figures(run: Run, book: Book, out: Path) -> dict[str, Path]:
    from capevo.experiment import plots

    done = run.done()
    learning = [c for c in done if c.method != EXPLORER]
    written: dict[str, Path] = {}
    groups = groups_of(learning)
    if groups:
        series: dict[str, dict[str, list[list[tuple[int, float, float]]]]] = {}
        eff: dict[str, dict[str, list[list[tuple[int, float]]]]] = {}
        for (t, label), cells in groups.items():
            series.setdefault(t, {})[label] = [
                [(r.iteration, r.reward_mean, r.success_rate) for r in c.records] for c in cells
            ]
            curves = []
            for c in cells:
                spent, pts = 0, []
                for r in c.records:
                    spent += r.env_steps_train
                    pts.append((spent, r.success_rate))
                curves.append(pts)
            eff.setdefault(t, {})[label] = curves
        written["evolution"] = plots.plot_evolution(
            series, out / EVOLUTION_PNG, titles={t: task_title(t) for t in series}
        )
        written["efficiency"] = plots.plot_sample_efficiency(
            eff, out / EFFICIENCY_PNG, titles={t: task_title(t) for t in eff}
        )
        t6 = {
            label: [book.get(f"cell/{c.key}/succ_peak") * 100 for c in cells]
            for (t, label), cells in groups.items()
            if t == FLAGSHIP_TASK
        }
        if t6:
            paper = {
                f"paper {m}": list(PAPER_T6_SEEDS.get(m, ()))
                or [float(PAPER_PEAK_SUCCESS[FLAGSHIP_TASK][m].split()[0])]
                for m in PAPER_METHODS
            }
            written["t6"] = plots.plot_seed_bars(
                t6,
                out / T6_SEEDS_PNG,
                title=f"{task_title(FLAGSHIP_TASK)}: peak held-out success per seed (bars: mean ± std)",
                ylabel="peak success (%)",
                paper=paper,
            )
        labels = sorted({c.label for c in learning})
        drift = {label: [book.get(f"cell/{c.key}/delta_pi") for c in learning if c.label == label] for label in labels}
        written["identity"] = plots.plot_seed_bars(
            drift,
            out / IDENTITY_PNG,
            title="Δπ at the last iteration (bars: mean ± std over cells; dots: cells)",
            ylabel="Δπ",
            paper={f"paper {m}": [v] for m, v in PAPER_DELTA_PI.items()},
        )
        abl = [c for c in learning if c.task == "T3" and c.spec and modality_of(c.spec) is not None]
        if abl:
            by = groups_of(abl)
            written["ablation"] = plots.plot_seed_bars(
                {label: [book.get(f"cell/{c.key}/r_peak") for c in cells] for (_, label), cells in by.items()},
                out / ABLATION_PNG,
                title="T3 ablation: peak held-out reward per learning modality",
                ylabel="R_peak",
                paper={f"paper {k}": [v[1]] for k, v in PAPER_ABLATION.items()},
            )
    explorer_tasks = sorted({c.task for c in done if c.method == EXPLORER})
    if explorer_tasks:
        rows = []
        for t in explorer_tasks:
            row: dict[str, Any] = {"task": t}
            for side in ("on", "off"):
                row[side] = {
                    "rate": book.get(f"h3/{t}/{side}/unsafe_rate"),
                    "low": book.get(f"h3/{t}/{side}/unsafe_low"),
                    "high": book.get(f"h3/{t}/{side}/unsafe_high"),
                }
            row["blocking"] = book.get(f"h3/{t}/on/blocking_rate")
            row["paper"] = PAPER_GOVERNANCE.get(t)
            rows.append(row)
        written["governance"] = plots.plot_governance(rows, out / GOVERNANCE_PNG)
    return written


def write_report(run_dir: Path) -> list[Path]:
    """Write ``report/report.md``, its figures and ``report/numbers.json`` for a run directory.

    Args:
        run_dir: The run directory (``cells/`` and, optionally, ``experiment.json``,
            ``provenance.json``).

    Returns:
        The files written: ``report.md``, ``numbers.json``, then the figures.

    Raises:
        NotFound: ``run_dir`` holds no run.
    """
    run = load_run(run_dir)
    book = compute_numbers(run)
    out = run.root / REPORT_DIR
    out.mkdir(parents=True, exist_ok=True)
    figures = _figures(run, book, out)
    text = markdown(run, book, benchmark_overhead(run.root), {k: p.name for k, p in figures.items()})
    md, nums = out / REPORT_MD, out / NUMBERS_JSON
    write_atomically(nums, (json.dumps(numbers_document(book), indent=1, allow_nan=False) + "\n").encode())
    write_atomically(md, text.encode())
    return [md, nums, *figures.values()]


__all__ = ["QuotedOverhead", "benchmark_overhead", "markdown", "write_report"]
