"""A run directory of ``capevo experiment run`` as found on disk: its file names, its cells and
what names a cell in the report (issue 20 "Harness" and "Report").

The runner (:mod:`capevo.experiment.runner`) writes ``RUN_DIR/experiment.json``,
``provenance.json`` and ``cells/<key>/{cell.json, metrics.jsonl, done.json | failed.json}``;
:func:`load_run` reads them back for the report and verify, and needs no simulator.

Invariants:
1. :func:`load_cell` never raises for what it finds: a cell is ``done`` (``done.json`` and at
   least one record), ``failed``, ``unfinished`` or ``unreadable``, with the reason.
2. Only ``done`` cells enter the report's statistics; the others are listed with their reason,
   never dropped.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.baselines.base import CellSpec, IterationRecord
from capevo.errors import CapevoError, NotFound
from capevo.evolve.metrics import read_jsonl

CELLS = "cells"
CELL_JSON = "cell.json"
METRICS = "metrics.jsonl"
DONE = "done.json"
FAILED = "failed.json"
RESUMES = "resumes.jsonl"
EXPERIMENT_JSON = "experiment.json"
PROVENANCE_JSON = "provenance.json"


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


__all__ = [
    "CELLS",
    "CELL_JSON",
    "DONE",
    "EXPERIMENT_JSON",
    "FAILED",
    "METRICS",
    "PROVENANCE_JSON",
    "RESUMES",
    "Cell",
    "Run",
    "group_label",
    "handoff_text",
    "load_cell",
    "load_run",
    "modality_of",
    "task_id",
    "task_title",
    "uses_decomposition",
]
