"""Behaviour cloning for neural ECMs on real demonstrations.

Demonstrations come from the scripted T1 reference rolled out in the ECM's environment
(robosuite) and from real MCAP traces of scripted episodes. The cloned policy must be a SAC
zip that capevo's neural loader accepts (no unpickling).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from neural_support import write_scripted_trace

from capevo.errors import ErrorCode, Invalid
from capevo.learner.base import request_for
from capevo.learner.bc import (
    BcConfig,
    BcLearner,
    Demos,
    _later_steps,
    behaviour_clone,
    collect_demos,
    demos_from_traces,
    imitation_loss,
    input_columns,
    torch_threads,
)
from capevo.learner.ecm_env import EcmEnv, EcmEnvConfig, make_ecm_env, target_for
from capevo.learner.neural_seed import model_bytes, offline_sac, policy_state
from capevo.learner.skills import seed_registry
from capevo.records import Kind, Origin
from capevo.registry.local import LocalRegistry
from capevo.runtime.ecm import NeuralPolicy
from capevo.runtime.tasks import Perturbations, task_spec
from capevo.runtime.tasks.scripted import REFERENCES

ECM = "pick.reach"
TARGET = target_for("T1", ECM)
INPUTS = TARGET.interface.inputs
ENV_CONFIG = EcmEnvConfig(max_steps=60, prefix_budget=60, perturbations=Perturbations.none(), seed_base=600_000)
BC = BcConfig(epochs=60, batch_size=32, net_arch=(64, 64), seed=0)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread() -> Iterator[None]:
    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def reach_env() -> Iterator[EcmEnv]:
    env = make_ecm_env("T1", TARGET, config=ENV_CONFIG)
    yield env
    env.close()


@pytest.fixture(scope="module")
def demos(reach_env: EcmEnv) -> Demos:
    return collect_demos(reach_env, REFERENCES["pick"], episodes=3, seed=0, source="scripted")


@pytest.fixture(scope="module")
def trace_dir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Any]]:
    """One real trace: seed 0 runs to success, seed 1 is cut after 10 steps (a failure)."""
    d = tmp_path_factory.mktemp("traces")
    episodes = write_scripted_trace(
        d / "pick-run.mcap",
        seeds=[0, 1],
        horizons=[80, 10],
        versions={"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0},
        inputs={ECM: INPUTS},
    )
    return d, episodes


@pytest.mark.slow
def test_scripted_demos_are_the_ecm_observations_of_successful_episodes(demos: Demos) -> None:
    assert demos.episodes == demos.episodes_seen == 3
    assert demos.obs.dtype == np.float32 and demos.obs.shape == (len(demos), 15)
    assert demos.action.shape == (len(demos), 7)
    assert np.all(np.abs(demos.action) <= 1.0)
    assert 3 <= len(demos) <= 3 * ENV_CONFIG.max_steps


@pytest.mark.slow
def test_failed_episodes_are_dropped_unless_asked_for(reach_env: EcmEnv) -> None:
    def idle(obs: Any) -> np.ndarray:
        return np.zeros(7)

    kept = collect_demos(reach_env, idle, episodes=1, seed=0)
    assert (len(kept), kept.episodes, kept.episodes_seen) == (0, 0, 1)
    # the dropped episode's steps were simulated all the same, and a budget counts them
    assert kept.env_steps == ENV_CONFIG.max_steps
    everything = collect_demos(reach_env, idle, episodes=1, seed=0, only_successful=False)
    assert (len(everything), everything.episodes, everything.env_steps) == (ENV_CONFIG.max_steps, 1, 60)


@pytest.mark.slow
def test_a_step_cap_ends_the_collection_exactly_there(reach_env: EcmEnv) -> None:
    def idle(obs: Any) -> np.ndarray:
        return np.zeros(7)

    # a reach has no predecessors: the first episode runs its 60 steps, the second is cut at 40
    capped = collect_demos(reach_env, idle, episodes=3, seed=0, only_successful=False, max_env_steps=100)
    assert (capped.env_steps, len(capped), capped.episodes_seen) == (100, 100, 2)
    assert collect_demos(reach_env, idle, episodes=3, seed=0, max_env_steps=0).env_steps == 0


@pytest.mark.slow
def test_under_a_budget_demonstrations_and_dagger_together_spend_no_more_than_it(tmp_path: Path) -> None:
    """Issue 20's parity for ``il``: a grasp's episodes start by driving the reach, so each episode
    starts only while its reset's predecessors and one step still fit."""
    reg = LocalRegistry(tmp_path / "registry", actor="tests")
    try:
        seed_registry(reg, "pick")
        request = request_for(reg, "pick", "pick.grasp", train_seeds=[1])
        config = BcConfig(epochs=5, batch_size=32, net_arch=(32, 32), seed=0, dagger_rounds=3, dagger_episodes=2)
        budget = 400
        learner = BcLearner(
            config=config, env_config=ENV_CONFIG, registry=reg, scripted_episodes=3, env_step_budget=budget
        )
        cand = learner.learn(request)
    finally:
        reg.close()
    spent = cand.notes["env_steps"]
    assert spent["demos"] > 0 and spent["total"] == spent["demos"] + spent["dagger"] <= budget
    # the cap binds: the weak clone's DAgger episodes run their 60 steps behind a reach prefix, so
    # not all 6 of them fit after the scripted ones
    assert sum(r["episodes"] for r in cand.notes["dagger"]["rounds"]) < 6


@pytest.mark.slow
def test_a_driver_acts_while_the_controller_only_labels(reach_env: EcmEnv) -> None:
    """DAgger's data: the states the driver visits, each labelled with the controller's action."""
    labels: list[np.ndarray] = []

    def expert(obs: Any) -> np.ndarray:
        labels.append(np.clip(np.asarray(REFERENCES["pick"](obs), dtype=np.float32), -1, 1))
        return labels[-1]

    def idle(obs: np.ndarray) -> np.ndarray:
        return np.zeros(7, dtype=np.float32)

    driven = collect_demos(reach_env, expert, episodes=1, seed=0, only_successful=False, driver=idle)
    # the idle driver never reaches the can: the episode runs the ECM's whole budget, every step kept
    assert (len(driven), driven.episodes, driven.episodes_seen) == (ENV_CONFIG.max_steps, 1, 1)
    np.testing.assert_array_equal(driven.action, np.stack(labels))
    # the expert would have moved the hand towards the can; the driver kept it where it started
    assert np.linalg.norm(driven.action[-1, :3]) > 0.1
    np.testing.assert_allclose(driven.obs[-1], driven.obs[0], atol=0.05)
    alone = collect_demos(reach_env, expert, episodes=1, seed=0, only_successful=False)
    assert len(alone) < ENV_CONFIG.max_steps  # the expert alone finishes the step


@pytest.mark.slow
def test_dagger_rounds_add_the_clones_own_states_labelled_by_the_expert(tmp_path: Path) -> None:
    reg = LocalRegistry(tmp_path / "registry", actor="tests")
    try:
        seed_registry(reg, "pick")
        request = request_for(reg, "pick", ECM, train_seeds=[1])
        config = BcConfig(epochs=20, batch_size=32, net_arch=(64, 64), seed=0, dagger_rounds=2, dagger_episodes=2)
        epochs: list[tuple[int, int]] = []
        learner = BcLearner(
            config=config,
            env_config=ENV_CONFIG,
            registry=reg,
            scripted_episodes=2,
            progress=lambda epoch, total, _loss: epochs.append((epoch, total)),
        )
        cand = learner.learn(request)
        dagger = cand.notes["dagger"]
        assert dagger["expert"] == "scripted" and [r["round"] for r in dagger["rounds"]] == [1, 2]
        assert [r["episodes"] for r in dagger["rounds"]] == [2, 2]
        assert all(1 <= r["rows"] <= r["env_steps"] <= 2 * ENV_CONFIG.max_steps for r in dagger["rounds"])
        assert dagger["env_steps"] == sum(r["env_steps"] for r in dagger["rounds"])
        # the last clone is fitted on the scripted rows and every round's rows
        rows = sum(r["rows"] for r in dagger["rounds"])
        assert cand.notes["bc"]["samples"] == cand.notes["demos"]["new_samples"] + rows
        spent = cand.notes["env_steps"]
        assert spent["demos"] >= cand.notes["demos"]["new_samples"] and spent["dagger"] == dagger["env_steps"]
        assert spent["total"] == spent["demos"] + spent["dagger"]
        assert epochs == [(e, 60) for e in range(1, 61)]
        plain = BcLearner(
            config=BcConfig(epochs=20, batch_size=32, net_arch=(64, 64), seed=0),
            env_config=ENV_CONFIG,
            registry=reg,
            scripted_episodes=2,
        ).learn(request)
        assert plain.notes["dagger"] == {"rounds": [], "expert": None, "env_steps": 0}
        assert plain.notes["env_steps"]["total"] == plain.notes["env_steps"]["demos"] > 0
    finally:
        reg.close()


@pytest.mark.slow
def test_cloning_reduces_the_imitation_loss_and_yields_a_loadable_sac_zip(demos: Demos) -> None:
    model = offline_sac(TARGET.interface, 7, net_arch=BC.net_arch, seed=1)
    critics = {k: v for k, v in policy_state(model).items() if not k.startswith("actor.")}
    report = behaviour_clone(model, demos, BC)
    assert report.samples == len(demos) and report.epochs == BC.epochs
    assert report.loss_after < 0.5 * report.loss_before, report
    assert imitation_loss(model, demos) == pytest.approx(report.loss_after, rel=1e-5)
    # only the actor learned (invariant 1)
    after = policy_state(model)
    assert all(np.array_equal(after[k], v) for k, v in critics.items())
    # the runtime's loader (no unpickling) accepts it and acts exactly like the trained actor
    policy = NeuralPolicy(model_bytes(model), inputs=INPUTS, outputs=TARGET.interface.outputs)
    for row in demos.obs[:5]:
        want, _ = model.predict(row, deterministic=True)
        np.testing.assert_allclose(policy.predict(row), want, rtol=1e-6, atol=1e-6)
    loaded_mse = np.mean([(policy.predict(o) - a) ** 2 for o, a in zip(demos.obs, demos.action, strict=True)])
    assert loaded_mse == pytest.approx(report.loss_after, rel=1e-4)


@pytest.mark.slow
def test_likelihood_loss_fits_too_and_cloning_is_deterministic(demos: Demos) -> None:
    config = BcConfig(epochs=20, batch_size=32, net_arch=(32, 32), loss="nll", seed=2)
    a = offline_sac(TARGET.interface, 7, net_arch=(32, 32), seed=5)
    b = offline_sac(TARGET.interface, 7, net_arch=(32, 32), seed=5)
    ra = behaviour_clone(a, demos, config)
    rb = behaviour_clone(b, demos, config)
    assert ra.loss_after < ra.loss_before
    assert (ra.loss_before, ra.loss_after) == (rb.loss_before, rb.loss_after)
    sa, sb = policy_state(a), policy_state(b)
    assert all(np.array_equal(sa[k], sb[k]) for k in sa)


@pytest.mark.slow
def test_trace_demos_keep_this_ecms_steps_of_successful_episodes(trace_dir: tuple[Path, list[Any]]) -> None:
    directory, episodes = trace_dir
    assert episodes[0].success and not episodes[1].success
    demos = demos_from_traces([directory], task="T1", target=TARGET)
    want_obs = np.stack(episodes[0].ecm_obs[ECM])
    want_act = np.clip(np.stack(episodes[0].ecm_actions[ECM]), -1, 1)
    np.testing.assert_allclose(demos.obs, want_obs, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(demos.action, want_act, rtol=1e-6, atol=1e-7)
    assert (demos.episodes, demos.episodes_seen, demos.source) == (1, 2, "traces")
    assert demos.traces == (str((directory / "pick-run.mcap").resolve()),)
    both = demos_from_traces([directory / "pick-run.mcap"], task="pick", target=TARGET, only_successful=False)
    assert len(both) == len(episodes[0].ecm_obs[ECM]) + len(episodes[1].ecm_obs[ECM])
    # a trace of another task is not read
    assert len(demos_from_traces([directory], task="T2", target=target_for("T2", "place.reach"))) == 0


def test_a_flat_observation_of_another_length_is_refused() -> None:
    with pytest.raises(Invalid) as info:
        input_columns(task_spec("T1"), INPUTS, 40)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "task 'pick': its observation keys add up to 46 values, the traces hold 40"
    cols = input_columns(task_spec("T1"), INPUTS, 46)
    assert cols.tolist() == [*range(21, 30), 32, 33, 34, 39, 40, 41]


@pytest.mark.slow
def test_bc_learner_turns_a_code_parent_into_an_il_neural_candidate(
    tmp_path: Path, trace_dir: tuple[Path, list[Any]]
) -> None:
    reg = LocalRegistry(tmp_path / "registry", actor="tests")
    try:
        seed_registry(reg, "pick")
        request = request_for(reg, "pick", ECM, train_seeds=[1])
        learner = BcLearner(config=BC, env_config=ENV_CONFIG, registry=reg, traces=[trace_dir[0]], learner_id="il-t")
        cand = learner.learn(request)
        assert cand.spec.kind is Kind.NEURAL and cand.spec.origin is Origin.IL
        assert cand.spec.parent == request.parent.version == 0
        assert cand.spec.provenance.learner_id == "il-t" and len(cand.spec.provenance.config_hash or "") == 64
        assert cand.spec.provenance.traces == (str((trace_dir[0] / "pick-run.mcap").resolve()),)
        # the current set's successful traces and the scripted reference's rollouts, both (issue 19)
        assert cand.notes["demos"]["source"] == "traces+scripted" and cand.notes["warm_start"] is False
        assert cand.notes["bc"]["loss_after"] < cand.notes["bc"]["loss_before"]
        record = cand.publish(reg)
        assert record.kind is Kind.NEURAL and record.origin is Origin.IL and record.parent == 0
        # with no traces and no scripted rollouts there is nothing to imitate
        empty = BcLearner(config=BC, env_config=ENV_CONFIG, registry=reg, scripted_episodes=0)
        with pytest.raises(Invalid) as info:
            empty.learn(request)
        assert info.value.code is ErrorCode.INVALID
        assert info.value.message.startswith("pick.reach: only 0 demonstration steps (need 1);")
    finally:
        reg.close()


@pytest.mark.parametrize(
    ("kwargs", "field", "text"),
    [
        ({"epochs": 0}, "epochs", "epochs must be a positive integer, got 0"),
        ({"loss": "l1"}, "loss", "unknown loss 'l1'; valid: mse, nll"),
        ({"learning_rate": 0.0}, "learning_rate", "learning_rate must be a finite number > 0, got 0.0"),
        ({"dagger_rounds": -1}, "dagger_rounds", "dagger_rounds must be a non-negative integer, got -1"),
        ({"dagger_episodes": 0}, "dagger_episodes", "dagger_episodes must be a positive integer, got 0"),
    ],
)
def test_bad_bc_settings_are_refused(kwargs: dict, field: str, text: str) -> None:
    with pytest.raises(Invalid) as info:
        BcConfig(**kwargs)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == text
    assert info.value.details["field"] == field


@pytest.mark.parametrize("budget", [0, -5, 2.5, True, "400"])
def test_a_bad_env_step_budget_is_refused(budget: object) -> None:
    with pytest.raises(Invalid) as info:
        BcLearner(env_step_budget=budget)  # type: ignore[arg-type]
    assert info.value.details["field"] == "env_step_budget"
    assert info.value.message == f"env_step_budget must be a positive integer, got {budget!r}"


@pytest.mark.slow
def test_an_ecm_that_finished_the_task_alone_gives_no_demonstrations(tmp_path: Path) -> None:
    """The successful episode's steps all came from pick.reach, which never handed over: cloning
    them would teach the first ECM the grasp and the lift too (results/evolution/T1-il)."""
    alone = write_scripted_trace(
        tmp_path / "pick-alone.mcap",
        seeds=[0],
        horizons=[80],
        versions={"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0},
        inputs={ECM: INPUTS},
        acting=ECM,
    )
    assert alone[0].success and set(alone[0].ecm_actions) == {ECM}
    assert len(demos_from_traces([tmp_path], task="T1", target=TARGET)) == 0
    everything = demos_from_traces([tmp_path], task="T1", target=TARGET, only_successful=False)
    assert len(everything) == len(alone[0].ecm_actions[ECM])  # asked for every row, it gets them
    # the decomposition's last step has no one to hand over to: its own successes still count
    lift = target_for("T1", "pick.lift")
    last = write_scripted_trace(
        tmp_path / "pick-lift.mcap",
        seeds=[0],
        horizons=[80],
        versions={"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0},
        inputs={},
        acting="pick.lift",
    )
    assert len(demos_from_traces([tmp_path / "pick-lift.mcap"], task="T1", target=lift)) == len(
        last[0].ecm_actions["pick.lift"]
    )


@pytest.mark.parametrize(
    ("task", "ecm", "later"),
    [
        ("T1", "pick.reach", ["pick.grasp", "pick.lift"]),
        ("T1", "pick.lift", []),
        # hold applies only once the peg is inside (success), and success ends the episode, so
        # insert, which makes it succeed, hands over to nothing and counts as the last step
        ("T6", "peg_in_hole.insert", []),
        ("T6", "peg_in_hole.pre_insert", ["peg_in_hole.insert"]),
        # the same for NutAssembly's release
        ("T4", "nut_assembly.insert", []),
        ("T4", "nut_assembly.align", ["nut_assembly.insert"]),
    ],
)
def test_a_step_that_only_applies_after_success_is_no_later_step(task: str, ecm: str, later: list[str]) -> None:
    """Before, T6's insert gave no demonstration row from any successful episode: it never handed
    over to hold (results/evolution/T6-distil)."""
    assert _later_steps(task_spec(task), ecm) == later
