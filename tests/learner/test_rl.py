"""RL for neural ECMs: reward shaping arithmetic, the ECM training environment, SAC warm start.

Real parts: robosuite T1 episodes in :class:`EcmEnv`, real SB3 SAC models, a real
:class:`LocalRegistry` on disk. Budgets are tiny (tens of steps).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from neural_support import write_scripted_trace

from capevo.errors import ErrorCode, Invalid
from capevo.learner.base import LearnRequest
from capevo.learner.bc import torch_threads
from capevo.learner.ecm_env import (
    EcmEnv,
    EcmEnvConfig,
    ecm_observation,
    make_ecm_env,
    step_of,
    target_for,
)
from capevo.learner.neural_seed import (
    SpacesEnv,
    ecm_spaces,
    model_bytes,
    policy_state,
    seed_policy,
    warm_start,
)
from capevo.learner.presets import make_preset, preset_names
from capevo.learner.reward import RewardShaping, ShapedReward
from capevo.learner.rl import SacConfig, SacLearner, build_sac, train_sac
from capevo.records import Kind, Origin, Predicate, State
from capevo.registry.local import LocalRegistry
from capevo.registry.predicates import predicate_holds
from capevo.runtime.ecm import NeuralPolicy
from capevo.runtime.ecm.neural import load_sb3_policy
from capevo.runtime.tasks import Perturbations
from capevo.runtime.tasks.scripted import REFERENCES

ECM = "pick.reach"
ENV_CONFIG = EcmEnvConfig(max_steps=60, prefix_budget=60, perturbations=Perturbations.none(), seed_base=500_000)
SAC = SacConfig(total_steps=60, buffer_size=1_000, batch_size=16, learning_starts=20, net_arch=(32, 32))


class CallableDriver:
    """A :class:`Driver` from a function of the raw observation dict (e.g. a scripted reference).

    Args:
        name: The ECM it stands in for.
        termination: When its step is done.
        act: ``obs_dict -> action`` (None ends it).
    """

    def __init__(
        self, name: str, termination: Predicate, act: Callable[[Mapping[str, np.ndarray]], np.ndarray | None]
    ) -> None:
        self.name = name
        self.termination = termination
        self._act = act

    def start(self) -> None:
        """Nothing to reset."""

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray | None:
        out = self._act(obs)
        return None if out is None else np.asarray(out, dtype=np.float64)

    def close(self) -> None:
        """Nothing to release."""


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread() -> Iterator[None]:
    # tiny networks on shared cores: one thread is several times faster
    with torch_threads(1):
        yield


# --- reward shaping (no simulator) -------------------------------------------------------------


class Playback(gym.Env[np.ndarray, np.ndarray]):
    """A real gymnasium env that replays scripted (reward, success, retries) steps."""

    def __init__(self, steps: list[tuple[float, bool, int]], *, control_dt: float | None = None) -> None:
        self.steps = steps
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        if control_dt is not None:
            self.control_dt = control_dt
        self._t = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        self._t = 0
        return np.zeros(1, np.float32), {"is_success": False, "retries": 0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        reward, success, retries = self.steps[self._t]
        self._t += 1
        done = self._t == len(self.steps)
        return np.zeros(1, np.float32), reward, False, done, {"is_success": success, "retries": retries}


step_lists = st.lists(st.tuples(st.floats(-2, 2), st.booleans(), st.integers(0, 2)), min_size=1, max_size=30).map(
    # the env latches success and counts retries cumulatively, as EcmEnv does
    lambda raw: [
        (r, any(s for _, s, _ in raw[: i + 1]), sum(k for _, _, k in raw[: i + 1])) for i, (r, _, _) in enumerate(raw)
    ]
)


@settings(max_examples=60, deadline=None)
@given(
    steps=step_lists,
    alpha=st.floats(0, 10),
    beta=st.floats(0, 10),
    gamma=st.floats(0, 10),
    dt=st.floats(0.001, 1.0),
)
def test_shaping_adds_the_paper_formula_per_episode(
    steps: list[tuple[float, bool, int]], alpha: float, beta: float, gamma: float, dt: float
) -> None:
    shaping = RewardShaping(success_bonus=alpha, time_penalty=beta, retry_penalty=gamma)
    env = ShapedReward(Playback(steps), shaping, dt=dt)
    env.reset()
    total = 0.0
    for reward, _, _ in steps:
        _, shaped, _, _, info = env.step(np.zeros(1, np.float32))
        assert info["reward_task"] == reward
        assert shaped == pytest.approx(reward + info["reward_shaping"])
        total += shaped
    success, retries = steps[-1][1], steps[-1][2]
    expected = sum(r for r, _, _ in steps) + alpha * success - beta * dt * len(steps) - gamma * retries
    assert total == pytest.approx(expected, abs=1e-9)


def test_zero_coefficients_leave_the_reward_unchanged() -> None:
    steps = [(0.5, False, 0), (-0.25, True, 1), (1.0, True, 3)]
    env = ShapedReward(Playback(steps), RewardShaping(success_bonus=0, time_penalty=0, retry_penalty=0), dt=0.05)
    env.reset()
    assert [env.step(np.zeros(1, np.float32))[1] for _ in steps] == [0.5, -0.25, 1.0]


def test_dt_is_read_from_the_environment() -> None:
    assert ShapedReward(Playback([(0.0, False, 0)], control_dt=0.25), RewardShaping()).dt == 0.25


@pytest.mark.parametrize(
    ("make", "field", "text"),
    [
        (
            lambda: RewardShaping(success_bonus=-1.0),
            "success_bonus",
            "success_bonus must be a finite number >= 0, got -1.0",
        ),
        (
            lambda: RewardShaping(time_penalty=math.inf),
            "time_penalty",
            "time_penalty must be a finite number >= 0, got inf",
        ),
        (
            lambda: ShapedReward(Playback([(0.0, False, 0)]), RewardShaping()),
            "dt",
            "cannot tell the environment's control period; pass dt=",
        ),
        (
            lambda: ShapedReward(Playback([(0.0, False, 0)]), RewardShaping(), dt=0.0),
            "dt",
            "dt must be a positive number of seconds, got 0.0",
        ),
        (lambda: SacConfig(gamma=1.5), "gamma", "gamma must be a number in (0, 1], got 1.5"),
        (lambda: SacConfig(batch_size=0), "batch_size", "batch_size must be an integer >= 1, got 0"),
        (lambda: EcmEnvConfig(max_steps=0), "max_steps", "max_steps must be a positive integer, got 0"),
    ],
)
def test_bad_settings_are_refused(make: Any, field: str, text: str) -> None:
    with pytest.raises(Invalid) as info:
        make()
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == text
    assert info.value.details["field"] == field


def test_warm_start_refuses_a_parent_that_is_not_sac() -> None:
    from stable_baselines3 import TD3

    interface = target_for("T1", ECM).interface
    obs, act = ecm_spaces(interface, 7)
    td3 = model_bytes(
        TD3("MlpPolicy", SpacesEnv(obs, act), buffer_size=1, policy_kwargs={"net_arch": [8]}, device="cpu")
    )
    with pytest.raises(Invalid) as info:
        build_sac(SpacesEnv(obs, act), SAC, parent_artifact=td3)
    assert info.value.code is ErrorCode.INVALID
    assert (
        info.value.message == "warm start needs a SAC parent; the parent is a stable_baselines3.td3.policies.TD3Policy"
    )


# --- the ECM environment (robosuite) -----------------------------------------------------------


@pytest.fixture(scope="module")
def reach_env() -> Iterator[EcmEnv]:
    env = make_ecm_env("T1", target_for("T1", ECM), config=ENV_CONFIG)
    yield env
    env.close()


@pytest.mark.slow
def test_observation_is_the_interface_inputs_and_seeds_are_training_seeds(reach_env: EcmEnv) -> None:
    obs, info = reach_env.reset(seed=3)
    inputs = reach_env.target.interface.inputs
    assert obs.dtype == np.float32 and obs.shape == reach_env.observation_space.shape == (15,)
    np.testing.assert_array_equal(obs, ecm_observation(reach_env.obs_dict, inputs))
    np.testing.assert_array_equal(obs[:3], reach_env.obs_dict["robot0_eef_pos"])
    assert info["task_seed"] == 500_003 and info["prefix_steps"] == 0
    _, info = reach_env.reset()
    assert info["task_seed"] == 500_004
    assert reach_env.control_dt == pytest.approx(0.05)


@pytest.mark.slow
def test_scripted_reach_terminates_with_success_and_idling_truncates(reach_env: EcmEnv) -> None:
    termination = reach_env.target.descriptor.termination
    reach_env.reset(seed=0)
    for _ in range(ENV_CONFIG.max_steps):
        _, _, terminated, truncated, info = reach_env.step(REFERENCES["pick"](reach_env.obs_dict))
        assert not (terminated and truncated)
        if terminated or truncated:
            break
    assert terminated and info["is_success"]
    assert predicate_holds(termination, reach_env.signals())
    reach_env.reset(seed=0)
    for i in range(ENV_CONFIG.max_steps):
        _, _, terminated, truncated, info = reach_env.step(np.zeros(7, np.float32))
        assert not terminated
        assert truncated == (i == ENV_CONFIG.max_steps - 1)
    assert not info["is_success"] and info["ecm_steps"] == ENV_CONFIG.max_steps


@pytest.mark.slow
def test_a_later_ecm_starts_where_its_predecessor_ended() -> None:
    reach = step_of("T1", "pick.reach")
    driver = CallableDriver("pick.reach", reach.termination, REFERENCES["pick"])
    env = make_ecm_env("T1", target_for("T1", "pick.grasp"), predecessors=[driver], config=ENV_CONFIG)
    try:
        _, info = env.reset(seed=0)
        assert 0 < info["prefix_steps"] < ENV_CONFIG.prefix_budget
        assert predicate_holds(reach.termination, env.signals())
        assert env.observation_space.shape == (15,)
    finally:
        env.close()
    env.close()  # idempotent
    with pytest.raises(Invalid) as info:
        env.reset()
    assert info.value.message == "this ECM environment is closed"


@pytest.mark.slow
def test_predecessors_come_from_the_registrys_active_versions(tmp_path: Path) -> None:
    from capevo.learner.skills import seed_registry

    reg = LocalRegistry(tmp_path / "registry", actor="tests")
    try:
        seed_registry(reg, "pick")
        env = make_ecm_env(
            "T1", target_for("T1", "pick.grasp", reg.get_version("pick.grasp")), registry=reg, config=ENV_CONFIG
        )
        try:
            (driver,) = env.predecessors
            assert (
                driver.name == "pick.reach"
                and driver.termination == reg.get_version("pick.reach").descriptor.termination
            )
            _, info = env.reset(seed=0)
            # the code v0 reach ran until its termination held or its budget ran out
            assert info["prefix_steps"] > 0
            done = predicate_holds(driver.termination, env.signals())
            assert done or info["prefix_steps"] == ENV_CONFIG.prefix_budget
        finally:
            env.close()
        with pytest.raises(Invalid) as info:
            make_ecm_env("T1", target_for("T1", "pick.grasp"), config=ENV_CONFIG)
        assert info.value.message == "pick.grasp runs after pick.reach; give a registry to load them from"
    finally:
        reg.close()


@pytest.mark.slow
def test_actions_are_clipped_to_the_unit_box(reach_env: EcmEnv) -> None:
    reach_env.reset(seed=9)
    big = reach_env.step(np.array([5.0, -5.0, 3.0, 0.0, 0.0, 0.0, 9.0], np.float32))[0]
    reach_env.reset(seed=9)
    unit = reach_env.step(np.array([1.0, -1.0, 1.0, 0.0, 0.0, 0.0, 1.0], np.float32))[0]
    np.testing.assert_array_equal(big, unit)


# --- SAC ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def registry(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalRegistry]:
    reg = LocalRegistry(tmp_path_factory.mktemp("rl") / "registry", actor="tests")
    artifact, spec = seed_policy("T1", ECM, net_arch=(32, 32), seed=7)
    record = reg.publish(ECM, artifact, spec)
    reg.promote(ECM, record.version)
    yield reg
    reg.close()


def _request(reg: LocalRegistry) -> LearnRequest:
    return LearnRequest(task="pick", ecm=ECM, parent=reg.get_version(ECM), source="")


@pytest.fixture(scope="module")
def trace_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Any]]:
    path = tmp_path_factory.mktemp("rl-traces") / "pick.mcap"
    inputs = target_for("T1", ECM).interface.inputs
    episodes = write_scripted_trace(path, seeds=[0, 1], horizons=[80, 10], versions={ECM: 0}, inputs={ECM: inputs})
    return path, episodes


@pytest.fixture(scope="module")
def trained(registry: LocalRegistry, trace_file: tuple[Path, list[Any]]) -> tuple[SacLearner, Any]:
    learner = SacLearner(
        config=SAC,
        env_config=ENV_CONFIG,
        registry=registry,
        traces=[str(trace_file[0])],
        torch_threads=1,
        learner_id="rl-test-a",
    )
    return learner, learner.learn(_request(registry))


@pytest.mark.slow
def test_sac_candidate_is_a_loadable_rl_version_with_provenance(
    registry: LocalRegistry, trained: tuple[SacLearner, Any], trace_file: tuple[Path, list[Any]]
) -> None:
    learner, cand = trained
    # every traced step of this ECM went into the replay buffer first (successful or not)
    path, episodes = trace_file
    assert cand.notes["train"]["prefilled"] == sum(len(e.ecm_obs[ECM]) for e in episodes) > 0
    assert cand.spec.provenance.traces == (str(path.resolve()),)
    parent = registry.get_version(ECM)
    assert cand.spec.kind is Kind.NEURAL and cand.spec.origin is Origin.RL and cand.spec.parent == parent.version
    assert cand.spec.interface == parent.interface and cand.spec.descriptor == parent.descriptor
    assert cand.spec.provenance.learner_id == "rl-test-a"
    assert cand.spec.provenance.config_hash == learner.provenance(_request(registry), []).config_hash
    assert cand.notes["warm_start"] == "weights" and cand.notes["train"]["steps"] == SAC.total_steps
    # same settings, same hash; another budget, another hash
    twin = SacLearner(config=SAC, env_config=ENV_CONFIG, learner_id="rl-test-b")
    other = SacLearner(config=dataclasses.replace(SAC, total_steps=61), env_config=ENV_CONFIG)
    assert twin.provenance(_request(registry), []).config_hash == cand.spec.provenance.config_hash
    assert other.provenance(_request(registry), []).config_hash != cand.spec.provenance.config_hash
    policy = NeuralPolicy(cand.artifact, inputs=parent.interface.inputs, outputs=parent.interface.outputs)
    assert policy.loaded.policy_class.endswith("SACPolicy")
    record = cand.publish(registry)
    assert record.state is State.CANDIDATE and record.origin is Origin.RL
    assert record.provenance.learner_id == "rl-test-a"


@pytest.mark.slow
def test_warm_start_starts_from_the_active_weights_and_training_moves_them(
    registry: LocalRegistry, trained: tuple[SacLearner, Any], reach_env: EcmEnv
) -> None:
    learner, cand = trained
    parent = registry.get_artifact(ECM)
    # the first run started from the active version's weights and moved them
    before = policy_state(load_sb3_policy(parent).policy)
    after = policy_state(load_sb3_policy(cand.artifact).policy)
    assert before.keys() == after.keys()
    assert any(not np.array_equal(before[k], after[k]) for k in before)
    # warm-starting from that candidate restores everything it saved, exactly
    env = ShapedReward(reach_env, RewardShaping())
    model = build_sac(env, dataclasses.replace(SAC, seed=11), parent_artifact=cand.artifact)
    start = policy_state(model)
    assert all(np.array_equal(start[k], after[k]) for k in after)
    trained_ent = float(learner.last_model.log_ent_coef.detach())
    assert trained_ent != 0.0
    assert float(model.log_ent_coef.detach()) == pytest.approx(trained_ent)
    assert model.actor.optimizer.state_dict()["state"]  # Adam moments came along
    calls: list[tuple[int, int]] = []
    report = train_sac(model, 40, progress=lambda done, total: calls.append((done, total)))
    assert report.steps == 40
    assert calls == [(10, 40), (20, 40), (30, 40), (40, 40)]
    moved = policy_state(model)
    assert any(not np.array_equal(moved[k], start[k]) for k in start)
    # a stop request ends training after the step it was seen on
    assert train_sac(model, 40, should_stop=lambda: True).steps == 1


@pytest.mark.slow
def test_warm_start_refuses_weights_of_another_shape(reach_env: EcmEnv) -> None:
    env = ShapedReward(reach_env, RewardShaping())
    small = seed_policy("T1", ECM, net_arch=(8,))[0]
    model = build_sac(env, SAC)
    with pytest.raises(Invalid) as info:
        warm_start(model, small)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message.startswith("warm start: the parent's policy does not match the model:")


def test_seed_policy_is_reproducible_and_loadable(tmp_path: Path) -> None:
    a, spec = seed_policy("T1", ECM, net_arch=(16, 16), seed=3)
    b, _ = seed_policy("T1", ECM, net_arch=(16, 16), seed=3)
    c, _ = seed_policy("T1", ECM, net_arch=(16, 16), seed=4)
    sa, sb, sc = (policy_state(load_sb3_policy(x).policy) for x in (a, b, c))
    assert all(np.array_equal(sa[k], sb[k]) for k in sa)
    assert any(not np.array_equal(sa[k], sc[k]) for k in sa)
    assert spec.kind is Kind.NEURAL and spec.media_type == "application/zip"
    policy = NeuralPolicy(a, inputs=spec.interface.inputs, outputs=spec.interface.outputs)
    assert (policy.loaded.observation_dim, policy.loaded.action_dim) == (15, 7)


def test_presets_are_found_by_name_and_unknown_ones_listed() -> None:
    assert preset_names() == ("tiny", "cpu-small", "paper")
    paper = make_preset("paper")
    assert (paper.sac.gamma, paper.sac.tau, paper.sac.buffer_size, paper.sac.batch_size) == (0.99, 0.005, 10**6, 4096)
    assert make_preset("tiny").sac.total_steps == 200
    with pytest.raises(Invalid) as info:
        make_preset("huge")
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "unknown preset 'huge'; valid: tiny, cpu-small, paper"


def test_training_leaves_no_sb3_log_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SB3 makes an empty ``SB3-<time>`` directory in the temp dir on every ``learn`` unless the
    model has a logger of its own; capevo's runs made hundreds."""
    import tempfile

    import gymnasium as gym

    from capevo.learner.neural_seed import new_sac
    from capevo.learner.rl import train_sac

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    model = new_sac(gym.make("Pendulum-v1"), net_arch=(8,), seed=0, learning_starts=2, batch_size=2)
    report = train_sac(model, 4)
    assert report.steps == 4
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("SB3-")] == []
