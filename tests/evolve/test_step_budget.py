"""Budget parity for ours (issue 20, config invariant 5): with ``env_steps_per_iteration`` an
iteration's live, learner and gate episodes take at most that many env steps, each counted from
the episodes actually run; a budget that cannot cover one update is refused before anything runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from capevo.errors import Invalid
from capevo.evolve.audit import learner_step_checks
from capevo.evolve.config import make_config
from capevo.evolve.run import EvolveOptions, run_evolution


def test_a_budget_below_live_gate_and_one_candidate_is_refused(tmp_path: Path) -> None:
    # tiny on T1: 3 live + 2 x 4 gate episodes of 40 steps = 440 reserved, one candidate 40 more
    config = make_config("tiny", env_steps_per_iteration=470)
    with pytest.raises(Invalid) as info:
        config.check_budget("T1", modality="code")
    assert info.value.details["field"] == "env_steps_per_iteration"
    assert "440" in info.value.message
    config.replace(env_steps_per_iteration=480).check_budget("T1", modality="code")
    with pytest.raises(Invalid):
        run_evolution(EvolveOptions(task="T1", config=config, root=tmp_path / "data", report_dir=tmp_path / "report"))
    # refused before the registry or the report directory's manifest was touched
    assert not (tmp_path / "data").exists() and not (tmp_path / "report" / "run.json").exists()


@pytest.mark.slow
def test_an_iteration_spends_at_most_its_env_step_budget(tmp_path: Path) -> None:
    budget = 600  # 440 reserved: the learners get 160 steps, 4 CEM episodes of up to 40
    config = make_config("tiny", iterations=1, env_steps_per_iteration=budget)
    report = tmp_path / "report"
    result = run_evolution(EvolveOptions(task="T1", config=config, root=tmp_path / "data", report_dir=report, seed=0))
    (row,) = result.rows
    assert row.env_steps_live == sum(int(e["steps"]) for e in row.episodes) > 0
    assert row.learner_steps > 0, row.update_note
    if row.gate is not None:
        assert row.env_steps_gate > 0
    assert row.env_steps == row.env_steps_live + row.learner_steps + row.env_steps_gate <= budget
    # the learner's own traces agree: every episode it ran is counted, kept or not (the chain's
    # re-learned updates: tests/evolve/test_chain.py)
    (check,) = learner_step_checks(report)
    assert check.checked and check.ok and check.traced == row.learner_steps


@pytest.mark.slow
def test_sac_spends_what_the_iteration_leaves_it(tmp_path: Path) -> None:
    """Parity (issue 20): with a budget, ``rl`` trains SAC for the iteration's remaining env steps,
    here more than the tiny preset's own 200, not the preset's figure."""
    config = make_config("tiny", iterations=1, env_steps_per_iteration=1000, updates_per_iteration=1)
    reserve = config.step_reserve("T1")
    result = run_evolution(
        EvolveOptions(
            task="T1", config=config, modality="rl", root=tmp_path / "data", report_dir=tmp_path / "report", seed=0
        )
    )
    (row,) = result.rows
    assert row.learner_steps == 1000 - row.env_steps_live - 2 * config.gate_episodes * config.episode_steps_max("T1")
    assert row.learner_steps > 200 and reserve < 1000
    assert row.env_steps <= 1000
