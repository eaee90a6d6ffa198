"""Learner steps against the learner's own traces (capevo.evolve.audit), with real metrics rows and
real MCAP files whose last-write times place them in, between or after the rows' spans."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from capevo.evolve.audit import LEARNER_TRACES, LearnerStepCheck, learner_step_checks
from capevo.evolve.metrics import IterationMetrics, MetricsLog, outcome_stats
from capevo.records import CapabilitySet
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.traces import EpisodeSummary, TraceMetadata, TraceWriter

T0 = 1_700_000_000.0


def _row(i: int, *, started_at: float, wall_s: float, learner_steps: int) -> IterationMetrics:
    outcomes = [
        EpisodeOutcome(
            seed=100 + i,
            success=False,
            reward=0.0,
            steps=10,
            duration_s=0.1,
            interventions=0,
            unsafe_steps=0,
            ecm_failures=0,
            capability_set={"pick.reach": 0},
        )
    ]
    return IterationMetrics(
        iteration=i,
        started_at=started_at,
        live=outcome_stats(outcomes),
        live_seeds=(100 + i,),
        episodes=tuple(o.to_dict() for o in outcomes),
        delta_pi=0.0,
        identity_hash="ab" * 32,
        active_versions={"pick.reach": 0},
        active_after={"pick.reach": 0},
        learner="cem",
        learner_steps=learner_steps,
        wall_s=wall_s,
    )


def _trace(report: Path, name: str, steps: list[int], written: float) -> None:
    path = report / LEARNER_TRACES / f"{name}.mcap"
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = TraceMetadata.collect(
        run_id=name,
        task="T1",
        capability_set=CapabilitySet(revision=1, active={"pick.reach": 0}),
        phi_hash="f" * 64,
        agent_identity_hash="a" * 64,
    )
    with TraceWriter(path, meta) as w:
        for k, n in enumerate(steps):
            w.write_episode_summary(
                EpisodeSummary(
                    episode=k,
                    seed=k,
                    success=False,
                    total_reward=0.0,
                    steps=n,
                    interventions=0,
                    unsafe_steps=0,
                    capability_set={"pick.reach": 0},
                    duration_s=0.1,
                )
            )
    os.utime(path, (written, written))


def test_an_interrupted_attempts_traces_are_counted_apart(tmp_path: Path) -> None:
    # iteration 0 ran from T0 for 100 s; iteration 1 was interrupted after learning (traces at
    # T0+150) and redone from T0+300 for 100 s; iteration 2's first attempt is running (T0+500)
    log = MetricsLog(tmp_path)
    log.append(_row(0, started_at=T0, wall_s=100.0, learner_steps=70))
    log.append(_row(1, started_at=T0 + 300, wall_s=100.0, learner_steps=40))
    _trace(tmp_path, "it0-a", [30, 20], T0 + 40)
    _trace(tmp_path, "it0-b", [20], T0 + 99)
    _trace(tmp_path, "it1-interrupted", [25, 25], T0 + 150)
    _trace(tmp_path, "it1-redo", [40], T0 + 350)
    _trace(tmp_path, "it2-running", [10], T0 + 500)
    first, second = learner_step_checks(tmp_path)
    assert (first.traced, first.interrupted, first.ok, first.discarded) == (70, 0, True, 0)
    # the redo learned again: its row records its own 40 steps; the interrupted 50 were discarded
    assert (second.traced, second.interrupted, second.ok, second.discarded) == (40, 50, True, 50)

    # had the redo gated the interrupted attempt's candidate, its row records those 50 as well
    gated = dataclasses.replace(second, recorded=90)
    assert gated.ok and gated.discarded == 0
    # anything else is a mismatch
    assert not dataclasses.replace(second, recorded=60).ok
    assert LearnerStepCheck.from_dict(second.to_dict()) == second
    # a check kept before ``interrupted`` existed reads as none
    old = {"iteration": 1, "learner": "cem", "recorded": 40, "traced": 40}
    assert LearnerStepCheck.from_dict(old).interrupted == 0


def test_a_trace_inside_a_rows_span_is_that_iterations(tmp_path: Path) -> None:
    log = MetricsLog(tmp_path)
    log.append(_row(0, started_at=T0, wall_s=100.0, learner_steps=30))
    _trace(tmp_path, "before-any-row", [7], T0 - 50)  # an interrupted first attempt of iteration 0
    _trace(tmp_path, "in-span", [30], T0 + 60)
    (check,) = learner_step_checks(tmp_path)
    assert (check.traced, check.interrupted, check.ok) == (30, 7, True)
