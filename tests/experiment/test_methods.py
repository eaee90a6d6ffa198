"""Our methods on their own, without Ray, on real robosuite episodes (capevo.experiment.methods
invariants 2-3): held-out seeds, the explorer under governance on and off, S-ECM's zero steps."""

from __future__ import annotations

from pathlib import Path

import pytest

from capevo.baselines.base import Budget, CellSpec, IterationRecord
from capevo.errors import Invalid
from capevo.experiment.methods import make_method

pytestmark = pytest.mark.slow

BUDGET = Budget(env_steps_per_iteration=1, eval_episodes=3, horizon=40)


def _run(cell: CellSpec, workdir: Path) -> list[IterationRecord]:
    out: list[IterationRecord] = []
    make_method(cell.method).run(cell, workdir, emit=out.append)
    return out


def test_the_explorer_is_unsafe_without_governance_and_governed_with_it(tmp_path: Path) -> None:
    records = {}
    for governance in (True, False):
        cell = CellSpec(task="T1", method="explorer", seed=3, iterations=1, budget=BUDGET, governance=governance)
        (record,) = _run(cell, tmp_path / str(governance))
        assert record.iteration == 1 and [e.seed for e in record.episodes] == list(cell.eval_seeds())
        assert record.env_steps_train == 0 and record.env_steps_eval == sum(e.steps for e in record.episodes)
        assert list((tmp_path / str(governance)).glob("traces/**/*.mcap"))
        records[governance] = record
    # the same seeds and the same adversary: off, the monitor grades steps unsafe; on, governance
    # changed actions (interventions) and no step the monitor grades is unsafe
    assert sum(e.unsafe_steps for e in records[False].episodes) > 0
    assert sum(e.interventions for e in records[True].episodes) > 0
    assert records[True].unsafe_episodes == 0
    # interventions are steps (a blocking rate is a rate)
    assert all(e.interventions <= e.steps for r in records.values() for e in r.episodes)


def test_the_explorer_checks_its_adversaries(tmp_path: Path) -> None:
    for options, field in (({"adversaries": ["arm_grab"]}, "options.adversaries"), ({"x": 1}, "options.x")):
        cell = CellSpec(task="T1", method="explorer", seed=3, iterations=1, budget=BUDGET, options=options)
        with pytest.raises(Invalid) as info:
            _run(cell, tmp_path)
        assert info.value.details["field"] == field


def test_static_ecm_spends_no_training_steps_and_evaluates_v0_on_the_held_out_seeds(tmp_path: Path) -> None:
    cell = CellSpec(task="T1", method="s-ecm", seed=5, iterations=3, budget=BUDGET)
    records = _run(cell, tmp_path)
    assert [r.iteration for r in records] == [1, 2, 3]
    assert all(r.env_steps_train == 0 and r.delta_pi == 0.0 for r in records)
    assert all([e.seed for e in r.episodes] == list(cell.eval_seeds()) for r in records)
    assert records[0].env_steps_eval > 0 and records[1].env_steps_eval == 0  # evaluated once, said so
    assert "same episodes as iteration 1" in records[1].notes


def test_every_adversary_of_t6_is_governed(tmp_path: Path) -> None:
    """``adversaries: all`` on T6: episode k runs adversary k mod 5, aimed through each arm's action
    frame (the arms face each other); off, the monitor grades unsafe episodes, on, none."""
    budget = Budget(env_steps_per_iteration=1, eval_episodes=5, horizon=40)
    unsafe = {}
    for governance in (True, False):
        cell = CellSpec(
            task="T6",
            method="explorer",
            seed=4,
            iterations=1,
            budget=budget,
            governance=governance,
            options={"adversaries": "all"},
        )
        (record,) = _run(cell, tmp_path / str(governance))
        assert "arm_grab" in record.notes and "table_dive" in record.notes
        unsafe[governance] = record.unsafe_episodes
    assert unsafe == {True: 0, False: unsafe[False]} and unsafe[False] >= 2


def test_an_iteration_note_names_every_member_of_a_chain_with_its_decision() -> None:
    from types import SimpleNamespace

    from capevo.evolve.metrics import ChainUpdate, GateSummary
    from capevo.experiment.methods import _gate_note

    def gate(ecm: str, version: int, decision: str) -> GateSummary:
        return GateSummary(
            ecm=ecm,
            candidate_version=version,
            active_version=version - 1,
            decision=decision,
            mode="paired",
            n=6,
            candidate_successes=6,
            candidate_rate=1.0,
            candidate_low=0.6,
            candidate_high=1.0,
        )

    chain = SimpleNamespace(
        gate=gate("t.a", 2, "promote"),
        further=(
            ChainUpdate(ecm="t.b", version=2, learner="cem", gate=gate("t.b", 2, "promote")),
            ChainUpdate(ecm="t.c", version=None, learner="cem", note="found nothing better"),
        ),
        update_note="chain stopped",
    )
    assert _gate_note(chain) == "promote t.a v2, t.b v2; chain stopped"
    mixed = SimpleNamespace(
        gate=gate("t.a", 3, "promote"),
        further=(ChainUpdate(ecm="t.b", version=3, learner="cem", gate=gate("t.b", 3, "reject")),),
        update_note="",
    )
    assert _gate_note(mixed) == "promote t.a v3; reject t.b v3"
    idle = SimpleNamespace(gate=None, further=(), update_note="no live episode failed: nothing to improve")
    assert _gate_note(idle) == "no live episode failed: nothing to improve"
