"""The Agent Modification baseline on real robosuite episodes with tiny budgets (capevo.baselines.am).

Budgets here are far too small to learn the task; the tests check the accounting (steps spent
equal the budget), the held-out evaluation seeds, Δπ recomputed from the saved checkpoints, the
option checks, and that cloning the v0 code ECMs' demonstrations fits held-out demonstrations
better than the untrained policy does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from capevo.agent import policy_drift
from capevo.baselines import Budget, CellSpec, IterationRecord, Method
from capevo.baselines.am import (
    KNOWLEDGE,
    KNOWLEDGE_BC,
    AgentModification,
    AgentModificationBC,
    bc_view,
    decision_names,
    decision_vector,
    minibatch_size,
    rollout_length,
)
from capevo.baselines.demos import v0_demos
from capevo.baselines.governed_env import GovernedTaskEnv
from capevo.errors import ErrorCode, Invalid
from capevo.learner.bc import BcConfig, behaviour_clone, imitation_loss
from capevo.runtime.traces import TraceReader

HORIZON = 20


def _cell(method: str = "am", *, budget: int = 64, iterations: int = 2, **options: object) -> CellSpec:
    return CellSpec(
        task="T1",
        method=method,
        seed=3,
        iterations=iterations,
        budget=Budget(env_steps_per_iteration=budget, eval_episodes=2, horizon=HORIZON),
        options=options,
    )


def _run(method: AgentModification, cell: CellSpec, workdir: Path) -> list[IterationRecord]:
    records: list[IterationRecord] = []
    method.run(cell, workdir, emit=records.append)
    return records


@pytest.mark.slow
def test_ppo_spends_the_budget_moves_the_policy_and_evaluates_on_the_held_out_seeds(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    cell = _cell()
    records = _run(AgentModification(), cell, tmp_path)
    assert [r.iteration for r in records] == [1, 2]
    for r in records:
        assert r.env_steps_train == cell.budget.env_steps_per_iteration
        assert tuple(e.seed for e in r.episodes) == cell.eval_seeds()
        assert r.env_steps_eval == sum(e.steps for e in r.episodes)
        assert all(e.steps <= HORIZON for e in r.episodes)
    assert records[0].delta_pi > 0.0
    for r in records:
        summaries = list(TraceReader(tmp_path / "traces" / f"eval-{r.iteration:03d}.mcap").episode_summaries())
        assert [(s.seed, s.steps, s.success) for s in summaries] == [(e.seed, e.steps, e.success) for e in r.episodes]
    # Δπ is what the checkpoints say: θ_0 the initial weights, θ_i the iteration's.
    first = PPO.load(tmp_path / "checkpoints" / "iteration-000.zip", device="cpu")
    for r in records:
        now = PPO.load(tmp_path / "checkpoints" / f"iteration-{r.iteration:03d}.zip", device="cpu")
        expected = policy_drift(decision_vector(first, "ppo"), decision_vector(now, "ppo"))
        assert r.delta_pi == pytest.approx(expected, rel=1e-9)
    # The critic is not part of θ.
    names = decision_names(first, "ppo")
    assert names and not any("value" in n or n == "log_std" for n in names)


@pytest.mark.slow
def test_sac_spends_the_budget(tmp_path: Path) -> None:
    # 120 steps: past SAC's 100 random warm-up steps, so it trains and the actor moves.
    cell = _cell(budget=120, iterations=1, algo="sac")
    (record,) = _run(AgentModification(), cell, tmp_path)
    assert record.env_steps_train == 120
    assert record.delta_pi > 0.0
    assert "actor.mu.*" in record.notes


@pytest.mark.slow
def test_sac_within_its_warm_up_does_not_move_the_policy(tmp_path: Path) -> None:
    # 50 steps: all inside SAC's 100 random warm-up steps, so no gradient step is taken.
    (record,) = _run(AgentModification(), _cell(budget=50, iterations=1, algo="sac"), tmp_path)
    assert record.env_steps_train == 50
    assert record.delta_pi == 0.0


@pytest.mark.slow
def test_t6_twelve_dimensional_actions(tmp_path: Path) -> None:
    cell = CellSpec(
        task="T6",
        method="am",
        seed=0,
        iterations=1,
        budget=Budget(env_steps_per_iteration=32, eval_episodes=1, horizon=10),
    )
    (record,) = _run(AgentModification(), cell, tmp_path)
    assert record.env_steps_train == 32 and record.env_steps_eval == 10
    assert record.delta_pi > 0.0


@pytest.mark.slow
def test_bc_warm_start_charges_its_demonstrations_to_iteration_one(tmp_path: Path) -> None:
    cell = _cell("am-bc", budget=50, iterations=1, bc_episodes=2, bc_epochs=5)
    (record,) = _run(AgentModificationBC(), cell, tmp_path)
    # Two 20-step v0 episodes fit in 50 steps; PPO spends the other 10 (a partial rollout).
    assert record.env_steps_train == 50
    assert "40 demonstration steps" in record.notes
    assert "10 steps of a partial rollout" in record.notes
    assert list((tmp_path / "demos").glob("*.mcap"))
    assert record.delta_pi > 0.0


CRITIC = {"ppo": ("mlp_extractor.value_net.", "value_net."), "sac": ("critic.", "critic_target.")}


@pytest.mark.slow
@pytest.mark.parametrize(("algo", "loss"), [("ppo", "mse"), ("ppo", "nll"), ("sac", "mse")])
def test_cloning_the_v0_skills_fits_held_out_demonstrations(tmp_path: Path, algo: str, loss: str) -> None:
    from stable_baselines3 import PPO, SAC

    demos = v0_demos("T1", tmp_path, seeds=[1_500_000_000 + j for j in range(4)], horizon=30)
    assert len(demos.demos) == demos.env_steps == sum(o.steps for o in demos.outcomes)
    assert demos.demos.obs.dtype == demos.demos.action.dtype == np.float32
    assert demos.demos.obs.shape[1] == 46 and demos.demos.action.shape[1] == 7
    assert np.abs(demos.demos.action).max() <= 1.0
    assert sorted(set(demos.episode.tolist())) == [0, 1, 2, 3]
    train, held_out = demos.split([0, 1, 2])
    assert len(held_out) and len(train) + len(held_out) == len(demos.demos)
    env = GovernedTaskEnv("T1", horizon=30)
    try:
        if algo == "ppo":
            model = PPO("MlpPolicy", env, seed=0, device="cpu")
        else:
            model = SAC("MlpPolicy", env, seed=0, device="cpu", buffer_size=100)
    finally:
        env.close()
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    view = bc_view(model, algo)
    untrained = imitation_loss(view, held_out, loss=loss)
    behaviour_clone(view, train, BcConfig(epochs=30, loss=loss, seed=0))
    assert imitation_loss(view, held_out, loss=loss) < untrained
    after = model.policy.state_dict()
    changed = {k for k, v in before.items() if not bool((after[k] == v).all())}
    # The critic is never touched; mse moves exactly the decision tensors, nll PPO's log_std too.
    assert not any(k.startswith(CRITIC[algo]) for k in changed)
    assert set(decision_names(model, algo)) <= changed
    if algo == "ppo":
        assert ("log_std" in changed) == (loss == "nll")


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"algorithm": "ppo"}, "options.algorithm"),
        ({"algo": "dqn"}, "options.algo"),
        ({"warm_start": "dagger"}, "options.warm_start"),
        ({"net_arch": [64, 0]}, "options.net_arch"),
        ({"bc_episodes": 0}, "options.bc_episodes"),
        ({"bc_loss": "l1"}, "options.bc_loss"),
        ({"handoff_signals": "yes"}, "options.handoff_signals"),
        ({"handoff_signals": True, "warm_start": "bc"}, "options.handoff_signals"),
    ],
)
def test_a_bad_option_is_invalid_and_named(tmp_path: Path, options: dict, field: str) -> None:
    with pytest.raises(Invalid) as exc:
        AgentModification().run(_cell(**options), tmp_path, emit=lambda r: None)
    assert exc.value.code is ErrorCode.INVALID
    assert exc.value.details["field"] == field
    assert field.removeprefix("options.") in str(exc.value)


def test_budgets_too_small_are_invalid_before_a_simulator_is_built(tmp_path: Path) -> None:
    with pytest.raises(Invalid, match="warm_start bc needs one demonstration episode"):
        AgentModificationBC().run(_cell("am-bc", budget=HORIZON - 1), tmp_path, emit=lambda r: None)
    with pytest.raises(Invalid, match="warm_start is always bc"):
        AgentModificationBC().run(_cell("am-bc", warm_start="none"), tmp_path, emit=lambda r: None)
    with pytest.raises(Invalid, match="too small for PPO"):
        AgentModification().run(_cell(budget=1), tmp_path, emit=lambda r: None)
    assert not (tmp_path / "checkpoints").exists()


def test_rollout_length_divides_the_budget() -> None:
    assert rollout_length(50_000, 2048) == 2000
    assert rollout_length(64, 2048) == 64
    assert rollout_length(50_021, 2048) == 50_021  # a prime: one rollout per iteration
    for budget in (2, 3, 1000, 4096, 99_991, 120_000):
        n = rollout_length(budget, 2048)
        assert n >= 2 and budget % n == 0
    assert minibatch_size(2000) == 80 and 2000 % 80 == 0
    assert minibatch_size(64) == 64
    assert minibatch_size(50_021) == 64  # no divisor from 16 to 256: SB3's default
    assert minibatch_size(7) == 7


def test_methods_and_their_knowledge() -> None:
    assert isinstance(AgentModification(), Method) and isinstance(AgentModificationBC(), Method)
    assert (AgentModification.name, AgentModification.knowledge) == ("am", KNOWLEDGE)
    assert (AgentModificationBC.name, AgentModificationBC.knowledge) == ("am-bc", KNOWLEDGE_BC)
    assert AgentModification.knowledge_of({"warm_start": "bc"}) == KNOWLEDGE_BC
    assert AgentModification.knowledge_of({}) == KNOWLEDGE
    assert np.isclose(policy_drift([1.0, 0.0], [1.0, 0.0]), 0.0)


@pytest.mark.slow
def test_am_with_handoff_signals_observes_them_in_training_and_evaluation(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    from capevo.runtime.tasks import task_spec

    records = _run(AgentModification(), _cell(budget=32, iterations=1, handoff_signals=True), tmp_path)
    assert records[0].env_steps_train == 32 and len(records[0].episodes) == 2
    model = PPO.load(tmp_path / "checkpoints" / "iteration-001.zip", device="cpu")
    plain = GovernedTaskEnv("T1", horizon=HORIZON)
    try:
        want = plain.observation_space.shape[0] + len(task_spec("T1").handoff_signals)
    finally:
        plain.close()
    assert model.observation_space.shape == (want,)
