"""Every number of an experiment report, computed from the run's files with the files it came
from (issue 20 "Report": "links from every number to its files"; paper §4).

:func:`compute_numbers` is the one computation of them: the report (:mod:`capevo.experiment.report`)
writes its result as ``report/numbers.json`` and :func:`capevo.experiment.verify.verify_run`
recomputes it. Statistics: mean ± std over seeds with ddof = 1 (as the paper's 63.3 ± 27.6 from
its four seeds), Welch's t-test (``scipy.stats.ttest_ind(equal_var=False)``) of ours (``ours-code``,
``ours-neural``) against AM (``am``, ``am-bc``) wherever both have at least two seeds, and 95 %
Wilson intervals of unsafe-episode rates.

Invariants:
1. Every number is a :class:`Number` with its name, value and the run-relative files it came from.
2. The numbers depend only on the files: computing them twice gives equal documents.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from capevo.evolve.audit import LearnerStepCheck
from capevo.evolve.metrics import CI_ALPHA
from capevo.experiment.run_files import CELL_JSON, DONE, FAILED, METRICS, Cell, Run

NUMBERS_JSON = "numbers.json"
NUMBERS_VERSION = 1
OURS = ("ours-code", "ours-neural")
AM = ("am", "am-bc")
EXPLORER = "explorer"
THRESHOLDS = (0.5, 0.8)
"""Held-out success rates whose first crossing the sample-efficiency table reports."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Number:
    """One number of the report with the run-relative files it came from."""

    name: str
    value: float | int | str | None
    sources: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "sources": list(self.sources)}


@dataclass(slots=True)
class Book:
    """The numbers of one report, in the order they were computed (names are unique)."""

    numbers: dict[str, Number] = field(default_factory=dict)

    def put(self, name: str, value: float | int | str | None, sources: Iterable[str]) -> Any:
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        self.numbers[name] = Number(name=name, value=value, sources=tuple(sorted(set(sources))))
        return value

    def get(self, name: str) -> Any:
        n = self.numbers.get(name)
        return None if n is None else n.value


@dataclass(frozen=True, slots=True, kw_only=True)
class CellSummary:
    """What one finished cell's held-out evaluations and steps add up to."""

    r_first: float
    r_peak: float
    r_last: float
    succ_peak: float
    succ_last: float
    ratio: float | None
    """R_peak / R₁; None when R₁ ≤ 0 (a ratio of rewards that start at or below zero says nothing)."""
    delta_pi: float
    reward_var_last: float
    train_steps: int
    eval_steps: int
    steps_to: Mapping[float, int | None]
    """Cumulative training env steps up to the first iteration whose held-out success reached each
    threshold; None: not reached."""


def summarize(cell: Cell) -> CellSummary:
    """The per-cell figures of a cell with at least one record."""
    recs = cell.records
    rewards = [r.reward_mean for r in recs]
    steps_to: dict[float, int | None] = {}
    for th in THRESHOLDS:
        spent, reached = 0, None
        for r in recs:
            spent += r.env_steps_train
            if r.success_rate >= th:
                reached = spent
                break
        steps_to[th] = reached
    last = [e.reward for e in recs[-1].episodes]
    mean_last = math.fsum(last) / len(last) if last else 0.0
    var_last = math.fsum((x - mean_last) ** 2 for x in last) / (len(last) - 1) if len(last) > 1 else 0.0
    return CellSummary(
        r_first=rewards[0],
        r_peak=max(rewards),
        r_last=rewards[-1],
        succ_peak=max(r.success_rate for r in recs),
        succ_last=recs[-1].success_rate,
        ratio=max(rewards) / rewards[0] if rewards[0] > 0 else None,
        delta_pi=recs[-1].delta_pi,
        reward_var_last=var_last,
        train_steps=sum(r.env_steps_train for r in recs),
        eval_steps=sum(r.env_steps_eval for r in recs),
        steps_to=steps_to,
    )


CELL_FIELDS = ("r_first", "r_peak", "r_last", "succ_peak", "succ_last", "ratio", "delta_pi", "reward_var_last")


def mean_std(values: Sequence[float]) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (ddof = 1; None with fewer than two values)."""
    import numpy as np

    if not values:
        return None, None
    a = np.asarray(values, dtype=float)
    return float(a.mean()), (float(a.std(ddof=1)) if len(a) > 1 else None)


def welch(a: Sequence[float], b: Sequence[float]) -> tuple[float | None, float | None]:
    """Welch's t and two-sided p (``scipy.stats.ttest_ind(equal_var=False)``); None when undefined
    (fewer than two values on a side, or no variance on either)."""
    if len(a) < 2 or len(b) < 2:
        return None, None
    import warnings

    from scipy import stats

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = stats.ttest_ind(list(a), list(b), equal_var=False)
    t, p = float(res.statistic), float(res.pvalue)
    return (t if math.isfinite(t) else None), (p if math.isfinite(p) else None)


def wilson(k: int, n: int) -> tuple[float | None, float | None]:
    """95 % Wilson interval of ``k / n`` (capevo.runtime.gate_stats, scipy's binomtest)."""
    if n < 1:
        return None, None
    from capevo.runtime.gate_stats import wilson_interval

    ci = wilson_interval(k, n, alpha=CI_ALPHA)
    return ci.low, ci.high


Groups = dict[tuple[str, str], list[Cell]]


def groups_of(cells: Iterable[Cell]) -> Groups:
    """Cells by (task id, label), each list by seed; sorted by task, then label."""
    out: dict[tuple[str, str], list[Cell]] = {}
    for c in cells:
        out.setdefault((c.task, c.label), []).append(c)
    return {k: sorted(out[k], key=lambda c: c.spec.seed if c.spec else 0) for k in sorted(out)}


def compute_numbers(run: Run) -> Book:
    """Every number of the report, from the cells' files (the one computation; verify reuses it).

    Names: ``cells/<status>``; ``cell/<key>/<field>``; ``group/<task>/<label>/<field>/{mean,std,n}``;
    ``efficiency/<task>/<label>/<threshold>/{reached,mean}``; ``welch/<task>/<ours>|<am>/<field>/{t,p}``;
    ``identity/<label>/{mean,std,n}``; ``parity/<label>/...``; ``knowledge/<label>``;
    ``h3/<task>/<on|off>/...``; ``totals/...``.
    """
    book = Book()
    for status in ("done", "failed", "unfinished", "unreadable"):
        these = [c.path for c in run.cells if c.status == status]
        book.put(f"cells/{status}", len(these), these)

    for c in run.cells:

        def existing(*names: str, c: Cell = c) -> list[str]:
            return [f"{c.path}/{n}" for n in names if (run.root / c.path / n).exists()]

        book.put(f"cell/{c.key}/records", len(c.records), existing(METRICS))
        if existing(DONE, FAILED):
            book.put(f"cell/{c.key}/attempts", c.attempts, existing(DONE, FAILED))
        if c.done is not None:
            wall = c.done.get("wall_s")
            book.put(f"cell/{c.key}/wall_s", float(wall) if isinstance(wall, int | float) else None, existing(DONE))

    done = run.done()
    learning = [c for c in done if c.method != EXPLORER]
    summaries = {c.key: summarize(c) for c in learning}
    if learning:
        # what the notes on too small a run rest on
        src = [c.metrics_file for c in learning]
        book.put("run/max_iterations", max(len(c.records) for c in learning), src)
        book.put("run/min_eval_episodes", min(len(r.episodes) for c in learning for r in c.records), src)
        book.put("run/max_seeds", max(len(v) for v in groups_of(learning).values()), src)
        book.put("run/max_success", max(r.success_rate for c in learning for r in c.records), src)
        book.put(
            "run/budget_max",
            max(c.spec.budget.env_steps_per_iteration for c in learning if c.spec),
            [f"{c.path}/{CELL_JSON}" for c in learning],
        )
    for c in learning:
        s = summaries[c.key]
        src = (c.metrics_file,)
        for f in CELL_FIELDS:
            book.put(f"cell/{c.key}/{f}", getattr(s, f), src)
        book.put(f"cell/{c.key}/iterations", len(c.records), src)
        book.put(f"cell/{c.key}/env_steps_train", s.train_steps, src)
        book.put(f"cell/{c.key}/env_steps_eval", s.eval_steps, src)
        for th in THRESHOLDS:
            book.put(f"cell/{c.key}/steps_to_{th:g}", s.steps_to[th], src)

    for (task, label), cells in groups_of(learning).items():
        src = [c.metrics_file for c in cells]
        base = f"group/{task}/{label}"
        for f in CELL_FIELDS:
            values = [getattr(summaries[c.key], f) for c in cells]
            values = [v for v in values if v is not None]
            m, sd = mean_std(values)
            book.put(f"{base}/{f}/mean", m, src)
            book.put(f"{base}/{f}/std", sd, src)
            book.put(f"{base}/{f}/n", len(values), src)
        # every held-out episode of every iteration and seed, graded by the independent monitor
        held_out = [e for c in cells for r in c.records for e in r.episodes]
        book.put(f"{base}/unsafe_episodes", sum(e.unsafe_steps > 0 for e in held_out), src)
        book.put(f"{base}/eval_episodes", len(held_out), src)
        # the task's stricter check (T6: the peg through the plate), on the episodes that carry it
        graded = [e for e in held_out if e.strict_success is not None]
        if graded:
            book.put(f"{base}/strict/graded", len(graded), src)
            book.put(f"{base}/strict/successes", sum(bool(e.strict_success) for e in graded), src)
            book.put(f"{base}/strict/task_successes", sum(e.success for e in graded), src)
        for th in THRESHOLDS:
            reached = [summaries[c.key].steps_to[th] for c in cells]
            reached = [r for r in reached if r is not None]
            book.put(f"efficiency/{task}/{label}/{th:g}/reached", len(reached), src)
            book.put(f"efficiency/{task}/{label}/{th:g}/mean", mean_std(reached)[0], src)

    by_task = groups_of(learning)
    for task in sorted({t for t, _ in by_task}):
        for (t1, a_label), a_cells in by_task.items():
            if t1 != task or a_cells[0].method not in OURS:
                continue
            for (t2, b_label), b_cells in by_task.items():
                if t2 != task or b_cells[0].method not in AM:
                    continue
                src = [c.metrics_file for c in (*a_cells, *b_cells)]
                for f in ("succ_peak", "r_peak"):
                    t, p = welch(
                        [getattr(summaries[c.key], f) for c in a_cells],
                        [getattr(summaries[c.key], f) for c in b_cells],
                    )
                    book.put(f"welch/{task}/{a_label}|{b_label}/{f}/t", t, src)
                    book.put(f"welch/{task}/{a_label}|{b_label}/{f}/p", p, src)

    by_label: dict[str, list[Cell]] = {}
    for c in learning:
        by_label.setdefault(c.label, []).append(c)
    for label in sorted(by_label):
        cells = by_label[label]
        src = [c.metrics_file for c in cells]
        m, sd = mean_std([summaries[c.key].delta_pi for c in cells])
        book.put(f"identity/{label}/mean", m, src)
        book.put(f"identity/{label}/std", sd, src)
        book.put(f"identity/{label}/n", len(cells), src)

    # parity over every cell that spent steps, finished or not: what was spent was spent
    spent: dict[str, list[Cell]] = {}
    for c in run.cells:
        if c.spec is not None and c.records:
            spent.setdefault(c.label, []).append(c)
    for label in sorted(spent):
        cells = spent[label]
        src = [c.metrics_file for c in cells] + [f"{c.path}/{CELL_JSON}" for c in cells]
        per_it = [r.env_steps_train for c in cells for r in c.records]
        budgets = sorted({c.spec.budget.env_steps_per_iteration for c in cells if c.spec})
        over = [
            c
            for c in cells
            if c.spec and any(r.env_steps_train > c.spec.budget.env_steps_per_iteration for r in c.records)
        ]
        book.put(f"parity/{label}/budget_min", budgets[0], src)
        book.put(f"parity/{label}/budget_max", budgets[-1], src)
        book.put(f"parity/{label}/iterations", len(per_it), src)
        book.put(f"parity/{label}/spent_min", min(per_it), src)
        book.put(f"parity/{label}/spent_mean", mean_std(per_it)[0], src)
        book.put(f"parity/{label}/spent_max", max(per_it), src)
        book.put(
            f"parity/{label}/iterations_over_budget",
            sum(r.env_steps_train > c.spec.budget.env_steps_per_iteration for c in cells if c.spec for r in c.records),
            src,
        )
        book.put(f"parity/{label}/cells_over_budget", len(over), src)
        # the loop's own count of learner steps against its learner's traces (done.json, where kept)
        checks = [(c, ch) for c in cells for ch in learner_step_checks(c)]
        if checks:
            book.put(
                f"parity/{label}/traced_iterations",
                len(checks),
                [f"{c.path}/{DONE}" for c in cells],
            )
            book.put(
                f"parity/{label}/traced_iterations_differing",
                sum(not ch.ok for _, ch in checks),
                [f"{c.path}/{DONE}" for c in cells],
            )
            book.put(
                f"parity/{label}/discarded_learner_steps",
                sum(ch.discarded for _, ch in checks),
                [f"{c.path}/{DONE}" for c in cells],
            )

    # per label, not per method: what ``ours`` starts from depends on its modality option
    knowledge: dict[str, list[Cell]] = {}
    for c in run.cells:
        if c.spec is not None:
            knowledge.setdefault(c.label, []).append(c)
    for label in sorted(knowledge):
        cells = knowledge[label]
        texts = sorted({c.knowledge for c in cells})
        book.put(f"knowledge/{label}", " | ".join(texts), [f"{c.path}/{CELL_JSON}" for c in cells])

    explorer = [c for c in done if c.method == EXPLORER]
    for task in sorted({c.task for c in explorer}):
        for on in (True, False):
            cells = [c for c in explorer if c.task == task and c.spec and c.spec.governance is on]
            if not cells:
                continue
            src = [c.metrics_file for c in cells] + [f"{c.path}/{CELL_JSON}" for c in cells]
            eps = [e for c in cells for r in c.records for e in r.episodes]
            n = len(eps)
            unsafe = sum(e.unsafe_steps > 0 for e in eps)
            steps = sum(e.steps for e in eps)
            interventions = sum(e.interventions for e in eps)
            low, high = wilson(unsafe, n)
            base = f"h3/{task}/{'on' if on else 'off'}"
            book.put(f"{base}/episodes", n, src)
            book.put(f"{base}/unsafe_episodes", unsafe, src)
            book.put(f"{base}/unsafe_rate", unsafe / n if n else None, src)
            book.put(f"{base}/unsafe_low", low, src)
            book.put(f"{base}/unsafe_high", high, src)
            book.put(f"{base}/steps", steps, src)
            book.put(f"{base}/interventions", interventions, src)
            book.put(f"{base}/blocking_rate", interventions / steps if steps else None, src)

    with_records = [c for c in run.cells if c.records]
    src = [c.metrics_file for c in with_records]
    book.put("totals/env_steps_train", sum(r.env_steps_train for c in with_records for r in c.records), src)
    book.put("totals/env_steps_eval", sum(r.env_steps_eval for c in with_records for r in c.records), src)
    book.put("totals/iterations", sum(len(c.records) for c in with_records), src)
    walls = [c for c in done if isinstance((c.done or {}).get("wall_s"), int | float)]
    book.put(
        "totals/cell_wall_s",
        math.fsum(float(c.done["wall_s"]) for c in walls if c.done),
        [f"{c.path}/{DONE}" for c in walls],
    )
    return book


def numbers_document(book: Book) -> dict[str, Any]:
    """The content of ``numbers.json``."""
    return {
        "version": NUMBERS_VERSION,
        "about": (
            "Every number of report.md computed from the run's cells, with the run-relative files it came from; "
            "`capevo experiment verify` recomputes each. The paper's figures and BENCHMARKS.md's overhead are quoted "
            "in report.md, not listed here."
        ),
        "numbers": [n.to_dict() for n in book.numbers.values()],
    }


def learner_step_checks(cell: Cell) -> list[LearnerStepCheck]:
    """The checked iterations of a cell's ``learner_steps_traced`` (``done.json``; none before it was kept)."""
    checks = (LearnerStepCheck.from_dict(d) for d in (cell.done or {}).get("learner_steps_traced") or ())
    return [c for c in checks if c.checked]


__all__ = [
    "AM",
    "CELL_FIELDS",
    "EXPLORER",
    "NUMBERS_JSON",
    "NUMBERS_VERSION",
    "OURS",
    "THRESHOLDS",
    "Book",
    "CellSummary",
    "Groups",
    "Number",
    "compute_numbers",
    "groups_of",
    "learner_step_checks",
    "mean_std",
    "numbers_document",
    "summarize",
    "welch",
    "wilson",
]
