"""Learner env steps per iteration against the learner's own MCAP traces (issue 20, parity).

Every metrics row records ``learner_steps``: the env steps the iteration's learners reported. The
loop sums them from the proposals, and a fault in that sum once let chains overrun the budget
unseen (``results/h1/README.md``). The code learners (CEM, the LLM's attempts, hybrid) run every
episode through an evaluator that traces it to ``traces/learner/`` of the report directory, so
those files give a second count that does not go through the loop.

A resumed run (:mod:`capevo.evolve.loop`, "Resuming") redoes an interrupted iteration from its
start, so an interrupted attempt's learner traces lie between the previous row's end and the
redo's ``started_at``. They are counted apart, as ``interrupted``: the redo either learned again
(its row records only its own steps) or gated the candidate the interrupted attempt published
(its row records that attempt's steps).

Invariants:
1. An iteration's traced steps are the steps of the episodes in the learner traces last written
   within its row's span, ``started_at`` to ``started_at + wall_s`` (the learner writes only
   between the live and the gate episodes of its iteration); its ``interrupted`` steps are those
   of the traces last written after the previous row's span and before its own.
2. A row is checked only when its learner is a code learner (:data:`TRACED_LEARNERS`): SAC and BC
   run their episodes in their own environments, which trace nothing.
3. :func:`learner_step_checks` of a directory without ``metrics.jsonl`` is ``()``.
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capevo.evolve.metrics import MetricsLog, read_metrics

LEARNER_TRACES = Path("traces") / "learner"
"""Where, under a report directory, the code learners' evaluator writes its traces."""

SPAN_SLACK_S = 1.0
"""Allowance on a row's end for a file system's timestamps (its span is measured by the clock)."""

TRACED_LEARNERS = ("cem", "hybrid", "llm")
"""Learner ids (the last ``/`` part, by prefix) whose episodes are traced; see invariant 2."""


@dataclass(frozen=True, slots=True, kw_only=True)
class LearnerStepCheck:
    """One iteration's recorded learner steps next to those its learner traces hold."""

    iteration: int
    learner: str
    recorded: int
    traced: int
    interrupted: int = 0
    """Steps of the learner traces of an interrupted attempt of this iteration (see the module docstring)."""

    @property
    def checked(self) -> bool:
        """Whether the learner traces its episodes, so the two counts must agree."""
        last = self.learner.rsplit("/", 1)[-1]
        return last.startswith(TRACED_LEARNERS)

    @property
    def ok(self) -> bool:
        """Unchecked, or the recorded steps are the finished attempt's traced ones, alone or with
        the interrupted attempt's (whose candidate the redo gated)."""
        return not self.checked or self.recorded in (self.traced, self.traced + self.interrupted)

    @property
    def discarded(self) -> int:
        """Learner steps an interrupted attempt spent that the row does not record (the redo learned
        again): spent, but they shaped nothing the run kept."""
        return 0 if self.recorded == self.traced + self.interrupted else self.interrupted

    def to_dict(self) -> dict[str, object]:
        return {
            "iteration": self.iteration,
            "learner": self.learner,
            "recorded": self.recorded,
            "traced": self.traced,
            "interrupted": self.interrupted,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LearnerStepCheck:
        """Read :meth:`to_dict`'s form back.

        Raises:
            KeyError, TypeError, ValueError: not that form.
        """
        return cls(
            iteration=int(d["iteration"]),
            learner=str(d.get("learner") or ""),
            recorded=int(d["recorded"]),
            traced=int(d["traced"]),
            interrupted=int(d.get("interrupted", 0)),
        )


def learner_step_checks(report_dir: str | Path) -> tuple[LearnerStepCheck, ...]:
    """Per finished iteration of the evolve run in ``report_dir``, its recorded and traced learner steps."""
    from capevo.runtime.traces.summary import summarize

    report = Path(report_dir)
    if not (report / MetricsLog.JSONL).is_file():
        return ()
    rows = read_metrics(report)
    starts = [row.started_at for row in rows]
    traced = [0] * len(rows)
    interrupted = [0] * len(rows)
    for path in sorted((report / LEARNER_TRACES).rglob("*.mcap")):
        written = path.stat().st_mtime
        k = bisect.bisect_right(starts, written) - 1
        steps = sum(e.steps for e in summarize(path).episodes)
        if k >= 0 and written <= rows[k].started_at + rows[k].wall_s + SPAN_SLACK_S:
            traced[k] += steps
        elif k + 1 < len(rows):
            interrupted[k + 1] += steps
        # else: an attempt of an iteration that has no row yet
    return tuple(
        LearnerStepCheck(
            iteration=row.iteration, learner=row.learner or "", recorded=row.learner_steps, traced=t, interrupted=x
        )
        for row, t, x in zip(rows, traced, interrupted, strict=True)
    )


__all__ = ["LEARNER_TRACES", "TRACED_LEARNERS", "LearnerStepCheck", "learner_step_checks"]
