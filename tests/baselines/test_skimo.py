"""The SkiMo baseline (capevo.baselines.skimo): world model, planner, and one real iteration.

The dynamics model is checked on held-out offline play against a constant predictor, the
planner under a model whose best skill is known, the run on its accounting (steps spent equal
the budget, held-out seeds, Δπ over the skill and model tensors recomputed from the
checkpoints). No budget here can show the task being learned.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from capevo.agent import policy_drift
from capevo.baselines import Budget, CellSpec, IterationRecord, Method
from capevo.baselines.offline_data import OfflineData, collect, offline_settings
from capevo.baselines.skills import SkillVAE, segments
from capevo.baselines.skimo import DELTA_TENSORS, KNOWLEDGE, SkillWorldModel, Skimo, cem_plan, fit_joint
from capevo.errors import ErrorCode, Invalid
from capevo.learner.bc import torch_threads


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def play() -> OfflineData:
    return collect(
        offline_settings(
            "T1", episodes=8, seed=12, noise=0.3, phi="task", governance=True, perturbations=True, horizon=40
        )
    )


@pytest.mark.slow
def test_the_dynamics_model_beats_a_constant_predictor_on_held_out_play(play: OfflineData) -> None:
    train, held = segments(play).split(0.25, seed=1)
    torch.manual_seed(0)
    vae = SkillVAE(play.obs.shape[1], play.action.shape[1])
    vae.set_normaliser(train.obs)
    model = SkillWorldModel(vae)
    fit_joint(vae, model, train, steps=400)
    with torch.no_grad():
        z = vae.encode(torch.as_tensor(held.actions)).loc  # the held-out windows' own skills
        target = vae.normalise(torch.as_tensor(held.next_obs))
        constant = vae.normalise(torch.as_tensor(train.next_obs).mean(0))  # the best constant on training data
        constant_error = float(((constant - target) ** 2).mean())
    assert model.dynamics_error(held, z) < 0.75 * constant_error


def _known_model(best: torch.Tensor):
    """Dynamics: the state does not change; reward: -|z - best|²; so ``best`` is the best skill at every step."""

    def dynamics(s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return s

    def reward(s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return -((z - best) ** 2).sum(-1)

    return dynamics, reward


def test_the_planner_picks_a_better_skill_than_a_random_one_under_a_known_model() -> None:
    g = torch.Generator().manual_seed(0)
    obs = torch.zeros(4)
    planned_rewards, random_rewards = [], []
    for _ in range(10):
        best = torch.randn(6, generator=g)
        dynamics, reward = _known_model(best)
        mean, std = cem_plan(
            obs, dynamics=dynamics, reward=reward, value=None, z_dim=6, horizon=2, samples=64, iterations=5, generator=g
        )
        planned_rewards.append(float(reward(obs[None], mean[None])))
        random_rewards.append(float(reward(obs[None], torch.randn(1, 6, generator=g))))
        assert mean.shape == std.shape == (6,)
    # every planned skill beats every random one's average, and the plan lands near the optimum
    assert min(planned_rewards) > sum(random_rewards) / len(random_rewards)
    assert sum(planned_rewards) / len(planned_rewards) > -0.5


def test_the_planner_uses_the_value_and_policy_and_is_deterministic_for_a_generator_state() -> None:
    best = torch.tensor([0.5, -1.0])
    dynamics = lambda s, z: s + z  # noqa: E731 - a tiny known model
    reward = lambda s, z: torch.zeros(len(z))  # noqa: E731
    value = lambda s: -((s - best) ** 2).sum(-1)  # noqa: E731 - only the value says where to go

    def policy(s: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        return best.expand(len(s), -1) + 0.01 * torch.randn(len(s), 2, generator=g)

    def plan(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        return cem_plan(
            torch.zeros(2),
            dynamics=dynamics,
            reward=reward,
            value=value,
            z_dim=2,
            horizon=1,
            samples=32,
            iterations=3,
            generator=torch.Generator().manual_seed(seed),
            policy=policy,
        )

    mean, _ = plan(1)
    assert torch.allclose(mean, best, atol=0.1)  # the policy's proposals reach the value's optimum
    assert all(torch.equal(a, b) for a, b in zip(plan(7), plan(7), strict=True))  # invariant 4
    with pytest.raises(Invalid):
        cem_plan(
            torch.zeros(2),
            dynamics=dynamics,
            reward=reward,
            value=None,
            z_dim=2,
            horizon=0,
            samples=8,
            iterations=1,
            generator=torch.Generator(),
        )


@pytest.mark.slow
def test_one_iteration_spends_the_budget_and_counts_skill_and_model_tensors(tmp_path: Path) -> None:
    cell = CellSpec(
        task="T1",
        method="skimo",
        seed=3,
        iterations=1,
        budget=Budget(env_steps_per_iteration=25, eval_episodes=2, horizon=20),
        options={"offline_episodes": 4, "pretrain_steps": 30, "learning_starts": 1, "batch_size": 4},
    )
    records: list[IterationRecord] = []
    method = Skimo()
    assert isinstance(method, Method) and method.name == "skimo" and method.knowledge == KNOWLEDGE
    method.run(cell, tmp_path, emit=records.append)
    (rec,) = records
    assert rec.iteration == 1 and rec.env_steps_train == 25  # invariant 1
    assert tuple(e.seed for e in rec.episodes) == cell.eval_seeds()  # invariant 2
    assert rec.env_steps_eval == sum(e.steps for e in rec.episodes)
    assert "offline play data" in rec.notes and "model and" in rec.notes
    before = torch.load(tmp_path / "pretrained.pt")
    after = torch.load(tmp_path / "iteration-001.pt")
    names = [k for k in before if k.startswith(DELTA_TENSORS)]
    for prefix in ("vae.decoder.", "vae.prior.", "model.dynamics.", "model.reward.", "sac.actor."):
        assert any(k.startswith(prefix) for k in names), prefix
    assert not any(k.startswith(("sac.q1", "sac.q2", "vae.encoder.")) for k in names)  # critics, encoder: not counted
    theta = [torch.cat([d[k].flatten() for k in names]).tolist() for d in (before, after)]
    assert rec.delta_pi == policy_drift(*theta) > 0.0  # 2 skills, 2 model and SAC updates moved it
    # the skills stay frozen downstream; the model and the policy move
    assert all(torch.equal(before[k], after[k]) for k in names if k.startswith("vae."))


def test_skimo_options_are_checked_before_any_simulator(tmp_path: Path) -> None:
    cell = CellSpec(
        task="T1",
        method="skimo",
        seed=0,
        iterations=1,
        budget=Budget(env_steps_per_iteration=10, eval_episodes=1),
        options={"plan_samples": 1},
    )
    with pytest.raises(Invalid) as err:
        Skimo().run(cell, tmp_path, emit=lambda r: None)
    assert err.value.code == ErrorCode.INVALID and err.value.details["field"] == "options.plan_samples"
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_without_an_update_nothing_drifts(tmp_path: Path) -> None:
    cell = CellSpec(
        task="T1",
        method="skimo",
        seed=4,
        iterations=1,
        budget=Budget(env_steps_per_iteration=20, eval_episodes=1, horizon=20),
        options={"offline_episodes": 2, "pretrain_steps": 10, "learning_starts": 1000},
    )
    records: list[IterationRecord] = []
    Skimo().run(cell, tmp_path, emit=records.append)
    (rec,) = records
    assert rec.env_steps_train == 20 and rec.delta_pi == 0.0  # invariant 3
    assert "0 model and 0 SAC updates so far, 2 skills stored" in rec.notes


@pytest.mark.slow
def test_the_evaluation_is_deterministic_and_cells_share_offline_data_through_offline_dir(tmp_path: Path) -> None:
    from capevo.baselines.governed_env import evaluate_policy
    from capevo.baselines.skills import SkillActor, cell_offline_data, decoder_of

    options = {"offline_episodes": 2, "pretrain_steps": 20, "offline_dir": str(tmp_path / "shared")}
    budget = Budget(env_steps_per_iteration=10, eval_episodes=2, horizon=15)
    cells = [
        CellSpec(task="T1", method=m, seed=6, iterations=1, budget=budget, options=options) for m in ("spirl", "skimo")
    ]
    first = cell_offline_data(cells[0], tmp_path / "a", Skimo().options(cells[0]), horizon=15)
    data = cell_offline_data(cells[1], tmp_path / "b", Skimo().options(cells[1]), horizon=15)
    assert not first.reused and data.reused and np.array_equal(first.obs, data.obs)
    assert len(list((tmp_path / "shared").iterdir())) == 1

    method = Skimo()
    agent = method._pretrain(cells[1], data, segments(data), method.options(cells[1]))
    actor = SkillActor(agent.exploit, decoder_of(agent.modules["vae"]))

    def new_episode() -> None:
        actor.reset()
        agent.new_episode()

    runs = [evaluate_policy("T1", actor, cells[1].eval_seeds(), horizon=15, on_reset=new_episode) for _ in range(2)]
    assert runs[0] == runs[1]
