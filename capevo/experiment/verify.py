"""``capevo experiment verify DIR``: recompute every number of a run's report from its raw metrics.

The report (:mod:`capevo.experiment.report`) writes ``report/numbers.json``: every number of the
run it shows, with the run-relative files it came from. :func:`verify_run` reads the cells again
(``cells/*/metrics.jsonl``, ``cell.json``, ``done.json``), recomputes every number with the
report's one computation (:func:`capevo.experiment.numbers.compute_numbers`) and compares. It also
checks each metrics line on its own: the derived fields written for readers (``success_rate``,
``reward_mean``, ``unsafe_episodes``) must equal what that line's episodes give.

So a hand-edited number in ``numbers.json``, a metrics file edited after the report was written,
a cell added or lost since, and a derived field that disagrees with its episodes are each
reported. The paper's figures and BENCHMARKS.md's quoted overhead are constants and quotations,
not numbers of the run, and are not in ``numbers.json``.

Invariants:
1. :func:`verify_run` of a run just reported returns ``[]``.
2. A number whose recomputed value differs (floats beyond a relative 1e-9) is one mismatch naming
   the number, both values and its files; a number on one side only is a mismatch too.
3. Every metrics line whose derived field differs from its episodes is one mismatch naming the
   file, the line and the field.
4. Every iteration whose recorded learner steps differ from those its code learner's traces held
   (``learner_steps_traced`` in ``done.json``, counted where the cell ran) is one mismatch.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.baselines.base import IterationRecord
from capevo.errors import CapevoError, Corrupt, NotFound
from capevo.evolve.audit import LearnerStepCheck
from capevo.evolve.metrics import read_jsonl
from capevo.experiment.numbers import NUMBERS_JSON, compute_numbers
from capevo.experiment.report import REPORT_DIR
from capevo.experiment.run_files import CELLS, DONE, METRICS, load_run

REL_TOL = 1e-9
ABS_TOL = 1e-12
DERIVED = ("success_rate", "reward_mean", "unsafe_episodes")


@dataclass(frozen=True, slots=True, kw_only=True)
class Mismatch:
    """A number that does not recompute, with where it came from."""

    name: str
    reported: Any
    recomputed: Any
    sources: tuple[str, ...]

    def __str__(self) -> str:
        return (
            f"{self.name}: reported {self.reported!r}, recomputed {self.recomputed!r} "
            f"({', '.join(self.sources) or 'no source'})"
        )


_MISSING = "<absent>"


def same(a: Any, b: Any) -> bool:
    """Equal, with floats compared to a relative 1e-9 (JSON round trips keep 17 digits)."""
    if a is None or b is None or isinstance(a, str) or isinstance(b, str):
        return a == b
    if isinstance(a, bool) or isinstance(b, bool):
        return a == b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(float(a), float(b), rel_tol=REL_TOL, abs_tol=ABS_TOL)
    return a == b


def check_lines(run_dir: Path) -> list[Mismatch]:
    """Every metrics line whose derived fields disagree with its own episodes (Invariant 3)."""
    out: list[Mismatch] = []
    for path in sorted((run_dir / CELLS).glob(f"*/{METRICS}")):
        rel = path.relative_to(run_dir).as_posix()
        try:
            rows, _ = read_jsonl(path)
        except Corrupt as exc:
            out.append(Mismatch(name=f"{rel}", reported="unreadable", recomputed=str(exc), sources=(rel,)))
            continue
        for line, row in enumerate(rows, start=1):
            try:
                rec = IterationRecord.from_dict(row)
            except CapevoError as exc:
                out.append(Mismatch(name=f"{rel}:{line}", reported="unreadable", recomputed=str(exc), sources=(rel,)))
                continue
            for f in DERIVED:
                if f in row and not same(row[f], getattr(rec, f)):
                    out.append(
                        Mismatch(name=f"{rel}:{line}:{f}", reported=row[f], recomputed=getattr(rec, f), sources=(rel,))
                    )
    return out


def check_learner_steps(run_dir: Path) -> list[Mismatch]:
    """Every iteration whose learner steps disagree with its learner's traces (Invariant 4)."""
    out: list[Mismatch] = []
    for path in sorted((run_dir / CELLS).glob(f"*/{DONE}")):
        rel = path.relative_to(run_dir).as_posix()
        try:
            done = json.loads(path.read_text(encoding="utf-8"))
            checks = [LearnerStepCheck.from_dict(d) for d in done.get("learner_steps_traced") or ()]
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            out.append(Mismatch(name=rel, reported="unreadable", recomputed=str(exc), sources=(rel,)))
            continue
        for c in checks:
            if not c.ok:
                name = f"{rel}:iteration {c.iteration}:learner_steps"
                traced = f"{c.traced} traced"
                if c.interrupted:
                    traced += f" (+{c.interrupted} by an interrupted attempt)"
                out.append(Mismatch(name=name, reported=c.recorded, recomputed=traced, sources=(rel,)))
    return out


def check_run(run_dir: str | Path) -> list[Mismatch]:
    """Every mismatch between ``report/numbers.json`` and the run's files (see the module docstring).

    Raises:
        NotFound: no run at ``run_dir``, or no ``report/numbers.json`` (run the report first).
        Corrupt: ``numbers.json`` is not the report's format.
    """
    root = Path(run_dir)
    path = root / REPORT_DIR / NUMBERS_JSON
    run = load_run(root)
    if not path.is_file():
        raise NotFound(
            f"{path} does not exist: write the report first (capevo experiment report {root})",
            details={"path": str(path)},
        )
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        reported = {n["name"]: n for n in doc["numbers"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise Corrupt(f"{path} is not a report's numbers file: {exc}", details={"path": str(path)}) from None
    book = compute_numbers(run)
    out: list[Mismatch] = []
    for name, entry in reported.items():
        sources = tuple(entry.get("sources") or ())
        number = book.numbers.get(name)
        if number is None:
            out.append(Mismatch(name=name, reported=entry.get("value"), recomputed=_MISSING, sources=sources))
        elif not same(entry.get("value"), number.value):
            out.append(Mismatch(name=name, reported=entry.get("value"), recomputed=number.value, sources=sources))
    for name, number in book.numbers.items():
        if name not in reported:
            out.append(Mismatch(name=name, reported=_MISSING, recomputed=number.value, sources=number.sources))
    return out + check_lines(root) + check_learner_steps(root)


def verify_run(run_dir: Path) -> list[str]:
    """The mismatches of :func:`check_run` as lines of text; empty when every number recomputes.

    Raises:
        NotFound: no run, or no report, at ``run_dir``.
        Corrupt: ``numbers.json`` is not the report's format.
    """
    return [str(m) for m in check_run(run_dir)]


__all__ = ["Mismatch", "check_learner_steps", "check_lines", "check_run", "same", "verify_run"]
