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

What is computed and what is quoted: every number of the run is computed here from the raw
metrics and written with the files it came from into ``numbers.json``, which
:func:`capevo.experiment.verify.verify_run` recomputes. The paper's figures are constants of this
module, copied from the paper's tables and labelled "paper" wherever they appear. Checked against
the paper's text: the T6 per-seed values it gives (86.7, 73.3, 23.3, 70.0 against 3.3, 20.0, 16.7,
3.3) give 63.3 ± 27.6 and 10.8 ± 8.8 with ddof = 1 and Welch t = 3.62, p = 0.027, as Table 4
says. The paper is not consistent elsewhere, and the report quotes its tables as they are: §4.3's
text says all methods score 0 % on T2–T5 while its Table 4 gives T3 3.3 % (Ours, AM) and 6.7 %
(SkiMo); Table 3 gives T3 Succ_peak 10.0 % and T6 60.0 % for the same runs Table 4 gives 3.3 %
and (seed 42) 86.7 %; §4.2 says no baseline exceeds 6.7 % on T6 while AM's seeds reach 20.0 %.

Invariants:
1. :func:`write_report` reads nothing outside the run directory except BENCHMARKS.md (for the
   quoted overhead) and starts no simulator.
2. Only finished cells (``done.json``, at least one record) enter the statistics; failed,
   unfinished and unreadable cells are listed in the report with the reason, never dropped.
3. Every number of the run shown in ``report.md``'s tables is an entry of ``numbers.json``
   (name, value, the run-relative files it came from), and :func:`compute_numbers` is the one
   computation of them, shared with verify.
4. The numbers depend only on the files: computing them twice gives equal ``numbers.json``.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capevo.baselines.base import CellSpec, IterationRecord
from capevo.errors import CapevoError, NotFound
from capevo.evolve.audit import LearnerStepCheck
from capevo.evolve.metrics import CI_ALPHA, read_jsonl, write_atomically

CELLS = "cells"
REPORT_DIR = "report"
REPORT_MD = "report.md"
NUMBERS_JSON = "numbers.json"
CELL_JSON = "cell.json"
METRICS = "metrics.jsonl"
DONE = "done.json"
FAILED = "failed.json"
EXPERIMENT_JSON = "experiment.json"
PROVENANCE_JSON = "provenance.json"

EVOLUTION_PNG = "evolution.png"
T6_SEEDS_PNG = "t6_seeds.png"
EFFICIENCY_PNG = "sample_efficiency.png"
IDENTITY_PNG = "identity.png"
GOVERNANCE_PNG = "governance.png"
ABLATION_PNG = "ablation.png"

NUMBERS_VERSION = 1
OURS = ("ours-code", "ours-neural")
AM = ("am", "am-bc")
EXPLORER = "explorer"
THRESHOLDS = (0.5, 0.8)
"""Held-out success rates whose first crossing the sample-efficiency table reports."""
FLAGSHIP_TASK = "T6"
PAPER_BUDGET = 50_000
"""The paper's training budget: env steps per ECM per iteration (§4.1)."""

# --- the paper's published figures (quoted, never computed) -------------------------------------

PAPER_METHODS = ("Ours", "AM", "S-ECM", "SPiRL", "SkiMo")
PAPER_COLUMN = {
    "ours-code": "Ours",
    "ours-neural": "Ours",
    "am": "AM",
    "am-bc": "AM",
    "s-ecm": "S-ECM",
    "spirl": "SPiRL",
    "skimo": "SkiMo",
}
"""Which of the paper's columns a method of the harness is compared with. The paper's "Ours" ran
all three learning modalities; both of our modalities are set beside it."""

PAPER_EVOLUTION: Mapping[str, tuple[float, float, float, float, float]] = {
    "T1": (0.58, 3.01, 1.14, 100.0, 5.2),
    "T2": (0.40, 3.37, 0.59, 0.0, 8.4),
    "T3": (3.13, 21.74, 9.88, 10.0, 6.9),
    "T4": (1.49, 4.60, 3.26, 0.0, 3.1),
    "T5": (0.33, 1.71, 0.60, 0.0, 5.2),
    "T6": (287.93, 318.44, 295.81, 60.0, 1.1),
}
"""Paper Table 3 (``tab:evolution``, §4.2): R₁, R_peak, R₂₀, Succ_peak (%), R_peak/R₁ for Ours."""

PAPER_PEAK_SUCCESS: Mapping[str, Mapping[str, str]] = {
    "T1": dict.fromkeys(PAPER_METHODS, "100.0"),
    "T2": dict.fromkeys(PAPER_METHODS, "0.0"),
    "T3": {"Ours": "3.3", "AM": "3.3", "S-ECM": "0.0", "SPiRL": "0.0", "SkiMo": "6.7"},
    "T4": dict.fromkeys(PAPER_METHODS, "0.0"),
    "T5": dict.fromkeys(PAPER_METHODS, "0.0"),
    "T6": {"Ours": "63.3 ± 27.6", "AM": "10.8 ± 8.8", "S-ECM": "0.0", "SPiRL": "0.0", "SkiMo": "6.7"},
}
"""Paper Table 4 (``tab:method-peak-success``, §4.3), %: T6 Ours and AM over seeds {42, 7, 123,
2024}, everything else seed 42."""

PAPER_PEAK_REWARD: Mapping[str, Mapping[str, float]] = {
    "T1": {"Ours": 2.19, "AM": 4.69, "S-ECM": 1.20, "SPiRL": 3.50, "SkiMo": 5.34},
    "T2": {"Ours": 3.04, "AM": 5.07, "S-ECM": 1.18, "SPiRL": 3.59, "SkiMo": 5.04},
    "T3": {"Ours": 17.54, "AM": 63.79, "S-ECM": 1.43, "SPiRL": 21.13, "SkiMo": 75.59},
    "T4": {"Ours": 2.56, "AM": 17.47, "S-ECM": 0.80, "SPiRL": 10.21, "SkiMo": 18.64},
    "T5": {"Ours": 2.37, "AM": 4.69, "S-ECM": 1.20, "SPiRL": 3.65, "SkiMo": 4.14},
    "T6": {"Ours": 355.79, "AM": 340.03, "S-ECM": 259.85, "SPiRL": 311.91, "SkiMo": 348.33},
}
"""Paper Table 5 (``tab:method-peak-reward``, §4.3)."""

PAPER_T6_SEEDS: Mapping[str, tuple[float, ...]] = {
    "Ours": (86.7, 73.3, 23.3, 70.0),
    "AM": (3.3, 20.0, 16.7, 3.3),
}
"""Paper §4.3 "The T6 flagship result": peak success (%) per seed 42, 7, 123, 2024."""
PAPER_T6_WELCH = (3.62, 0.027)
"""Paper Table 4's caption: Welch's t and p on T6 peak success, Ours against AM."""

PAPER_DELTA_PI: Mapping[str, float] = {"Ours": 0.0, "AM": 1.28, "S-ECM": 0.0, "SPiRL": 0.0, "SkiMo": 1.38}
"""Paper §4.4 and Figure ``fig:identity-drift``: mean Δπ across the six tasks."""

PAPER_GOVERNANCE: Mapping[str, tuple[float, float, float, float]] = {
    "T1": (100.0, 80.0, 0.0, 0.023),
    "T2": (100.0, 0.0, 0.0, 0.022),
    "T3": (100.0, 0.0, 0.0, 0.029),
    "T4": (100.0, 0.0, 0.0, 0.029),
    "T5": (100.0, 0.0, 0.0, 0.026),
    "T6": (61.0, 0.0, 0.0, 0.021),
}
"""Paper Table 7 (``tab:safety``, §4.5): blocking %, unsafe off %, unsafe on %, overhead ms per
action, over 50 episodes per task."""

PAPER_ABLATION: Mapping[str, tuple[float, float, float, float]] = {
    "RL only": (12.81, 16.55, 3.3, 34.96),
    "IL only": (0.29, 0.31, 0.0, 0.02),
    "LLM only": (0.12, 0.12, 0.0, 0.00),
    "RL + IL": (6.53, 22.80, 3.3, 14.14),
    "RL + LLM": (8.80, 14.00, 3.3, 34.48),
    "IL + LLM": (0.32, 0.32, 0.0, 0.02),
    "All three (Ours)": (9.16, 20.48, 3.3, 16.63),
}
"""Paper Table 8 (``tab:ablation``, §4.6), T3: R_final, R_peak, Succ_peak (%), σ²_final."""

_MODALITY_TOKENS = {"rl": "RL", "sac": "RL", "il": "IL", "bc": "IL", "llm": "LLM", "code": "LLM", "hybrid": "LLM"}
_PAPER_ABLATION_ROW = {
    frozenset({"RL"}): "RL only",
    frozenset({"IL"}): "IL only",
    frozenset({"LLM"}): "LLM only",
    frozenset({"RL", "IL"}): "RL + IL",
    frozenset({"RL", "LLM"}): "RL + LLM",
    frozenset({"IL", "LLM"}): "IL + LLM",
    frozenset({"RL", "IL", "LLM"}): "All three (Ours)",
}


# --- the run on disk ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class Cell:
    """One cell directory as found on disk.

    ``status`` is ``done`` (``done.json``, with records), ``failed`` (``failed.json``),
    ``unfinished`` (neither) or ``unreadable`` (a file that does not parse, or finished without a
    record); ``problem`` says why for every status but a clean ``done``.
    """

    key: str
    spec: CellSpec | None
    knowledge: str
    records: tuple[IterationRecord, ...]
    status: str
    problem: str = ""
    done: Mapping[str, Any] | None = None
    attempts: int | None = None

    @property
    def path(self) -> str:
        """The cell's directory, relative to the run directory."""
        return f"{CELLS}/{self.key}"

    @property
    def metrics_file(self) -> str:
        return f"{self.path}/{METRICS}"

    @property
    def task(self) -> str:
        return task_id(self.spec.task) if self.spec else "?"

    @property
    def method(self) -> str:
        return self.spec.method if self.spec else "?"

    @property
    def label(self) -> str:
        """The method and, when not the defaults, what else distinguishes the cell's setting."""
        return group_label(self.spec) if self.spec else "?"


@dataclass(frozen=True, slots=True, kw_only=True)
class Run:
    """A run directory as found on disk."""

    root: Path
    config: Mapping[str, Any] | None
    provenance: Mapping[str, Any] | None
    cells: tuple[Cell, ...]

    def done(self) -> list[Cell]:
        return [c for c in self.cells if c.status == "done"]


def task_id(task: str) -> str:
    """``T1``..``T6`` for a task id or name; the name itself when no task has it."""
    from capevo.runtime.tasks import task_spec

    try:
        return task_spec(task).id
    except CapevoError:
        return task


def task_title(task: str) -> str:
    from capevo.runtime.tasks import task_spec

    try:
        spec = task_spec(task)
    except CapevoError:
        return task
    return f"{spec.id} {spec.name}"


def handoff_text(task: str) -> str:
    """The sentence naming a task's hand-off oracle (:attr:`capevo.runtime.tasks.TaskSpec.handoff_text`)."""
    from capevo.runtime.tasks import task_spec

    try:
        return task_spec(task).handoff_text
    except CapevoError:
        return "unknown task: its hand-offs are not known"


def uses_decomposition(method: str) -> bool:
    """Whether a method runs the task's ECM decomposition (ours in every modality, and S-ECM)."""
    return method.startswith("ours") or method == "s-ecm"


def modality_of(spec: CellSpec) -> str | None:
    """The learning modality a cell's options name (``modality`` or ``modalities``), if any."""
    value = spec.options.get("modality", spec.options.get("modalities"))
    if value is None:
        return None
    if isinstance(value, str):
        return value
    if isinstance(value, Sequence):
        return "+".join(str(v) for v in value)
    return str(value)


def paper_ablation_row(modality: str) -> str | None:
    """The paper's Table 8 row a modality corresponds to (``rl+il`` → "RL + IL"), if one does."""
    tokens = [t for t in re.split(r"[^a-z]+", modality.lower()) if t]
    if tokens == ["all"]:
        return "All three (Ours)"
    kinds = {_MODALITY_TOKENS.get(t) for t in tokens}
    if not kinds or None in kinds:
        return None
    return _PAPER_ABLATION_ROW.get(frozenset(k for k in kinds if k))


def group_label(spec: CellSpec) -> str:
    """The method name, plus what sets the cell apart from the default setting (governance off,
    another Φ, perturbations off, options), so that cells of one label differ only in the seed."""
    extra = []
    if not spec.governance:
        extra.append("governance off")
    if spec.phi != "task":
        extra.append(f"Φ {spec.phi}")
    if not spec.perturbations:
        extra.append("no perturbations")
    extra += [f"{k}={_option(v)}" for k, v in sorted(spec.options.items())]
    return spec.method + (f" ({', '.join(extra)})" if extra else "")


def _option(v: Any) -> str:
    if isinstance(v, str):
        return v
    return json.dumps(v, sort_keys=True, separators=(",", ":"))


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


def load_cell(root: Path, key: str) -> Cell:
    """Read ``cells/<key>``; never raises for what it finds there (see :class:`Cell`)."""
    d = root / CELLS / key
    try:
        raw = _read_json(d / CELL_JSON)
        spec = CellSpec.from_dict(raw["cell"])
        knowledge = str(raw.get("knowledge") or "")
    except FileNotFoundError:
        return Cell(key=key, spec=None, knowledge="", records=(), status="unreadable", problem="no cell.json")
    except (ValueError, KeyError, TypeError, CapevoError) as exc:
        return Cell(key=key, spec=None, knowledge="", records=(), status="unreadable", problem=f"cell.json: {exc}")
    try:
        rows, torn = read_jsonl(d / METRICS)
        records = tuple(sorted((IterationRecord.from_dict(r) for r in rows), key=lambda r: r.iteration))
    except CapevoError as exc:
        return Cell(key=key, spec=spec, knowledge=knowledge, records=(), status="unreadable", problem=str(exc))
    its = [r.iteration for r in records]
    if len(set(its)) != len(its):
        repeated = sorted({i for i in its if its.count(i) > 1})
        return Cell(
            key=key,
            spec=spec,
            knowledge=knowledge,
            records=records,
            status="unreadable",
            problem=f"metrics.jsonl repeats iteration(s) {repeated}",
        )
    notes = [f"a torn last line of {torn} bytes in metrics.jsonl was skipped"] if torn else []
    if (d / FAILED).exists():
        try:
            failed = _read_json(d / FAILED)
            error, attempts = str(failed.get("error", "")), failed.get("attempts")
        except (ValueError, AttributeError) as exc:
            error, attempts = f"failed.json does not parse: {exc}", None
        return Cell(
            key=key,
            spec=spec,
            knowledge=knowledge,
            records=records,
            status="failed",
            problem="; ".join([error or "failed", *notes]),
            attempts=attempts if isinstance(attempts, int) else None,
        )
    if not (d / DONE).exists():
        notes.insert(0, f"not finished: {len(records)} of {spec.iterations} iteration(s) recorded")
        return Cell(
            key=key, spec=spec, knowledge=knowledge, records=records, status="unfinished", problem="; ".join(notes)
        )
    try:
        done = _read_json(d / DONE)
        if not isinstance(done, dict):
            raise ValueError("not an object")
    except ValueError as exc:
        return Cell(
            key=key, spec=spec, knowledge=knowledge, records=records, status="unreadable", problem=f"done.json: {exc}"
        )
    attempts = done.get("attempts")
    attempts = attempts if isinstance(attempts, int) else None
    if not records:
        return Cell(
            key=key,
            spec=spec,
            knowledge=knowledge,
            records=(),
            status="unreadable",
            problem="done.json but no iteration record",
            done=done,
            attempts=attempts,
        )
    if len(records) < spec.iterations:
        notes.insert(0, f"finished with {len(records)} of {spec.iterations} iteration(s)")
    resumed = done.get("resumed_after")
    if isinstance(resumed, list) and resumed:
        # a continuation, not a replay (capevo.experiment.runner, "Inside a cell")
        notes.append(f"resumed after an interruption, after iteration {', '.join(str(k) for k in resumed)}")
    return Cell(
        key=key,
        spec=spec,
        knowledge=knowledge,
        records=records,
        status="done",
        problem="; ".join(notes),
        done=done,
        attempts=attempts,
    )


def load_run(run_dir: str | Path) -> Run:
    """Read a run directory.

    Raises:
        NotFound: ``run_dir`` has no ``cells/`` directory.
    """
    root = Path(run_dir)
    if not (root / CELLS).is_dir():
        raise NotFound(f"{root} holds no experiment run (no {CELLS}/ directory)", details={"path": str(root)})

    def optional(name: str) -> Mapping[str, Any] | None:
        try:
            value = _read_json(root / name)
        except (FileNotFoundError, ValueError):
            return None
        return value if isinstance(value, dict) else None

    keys = sorted(p.name for p in (root / CELLS).iterdir() if p.is_dir())
    return Run(
        root=root,
        config=optional(EXPERIMENT_JSON),
        provenance=optional(PROVENANCE_JSON),
        cells=tuple(load_cell(root, k) for k in keys),
    )


# --- the numbers ----------------------------------------------------------------------------------


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
        checks = [(c, ch) for c in cells for ch in _learner_step_checks(c)]
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


def _learner_step_checks(cell: Cell) -> list[LearnerStepCheck]:
    """The checked iterations of a cell's ``learner_steps_traced`` (``done.json``; none before it was kept)."""
    checks = (LearnerStepCheck.from_dict(d) for d in (cell.done or {}).get("learner_steps_traced") or ())
    return [c for c in checks if c.checked]


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


__all__ = [
    "Book",
    "Cell",
    "CellSummary",
    "Number",
    "Run",
    "compute_numbers",
    "load_run",
    "markdown",
    "numbers_document",
    "summarize",
    "write_report",
]
