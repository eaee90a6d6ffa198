"""Neural learning accumulates across iterations (issue 19): the learners continue from their own
latest candidate, SAC keeps its replay buffer, BC keeps every demonstration row, and SAC on a
randomly initialised v0 starts from a behaviour-cloned actor. Real robosuite episodes, real files."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from capevo.errors import Invalid
from capevo.learner.base import LearnRequest
from capevo.learner.bc import BcConfig, BcLearner, torch_threads
from capevo.learner.continuation import DEMOS, LATEST, REPLAY, LearnerState
from capevo.learner.ecm_env import EcmEnvConfig
from capevo.learner.neural_seed import seed_policy
from capevo.learner.rl import SacConfig, SacLearner
from capevo.registry.local import LocalRegistry
from capevo.runtime.tasks import Perturbations

ECM = "pick.reach"
ENV_CONFIG = EcmEnvConfig(max_steps=60, prefix_budget=60, perturbations=Perturbations.none(), seed_base=700_000)
SAC = SacConfig(total_steps=60, buffer_size=1_000, batch_size=16, learning_starts=20, net_arch=(32, 32))
BC = BcConfig(epochs=5, batch_size=32, net_arch=(32, 32), seed=0)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread() -> Iterator[None]:
    with torch_threads(1):
        yield


@pytest.fixture()
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    """T1's reach as a randomly initialised neural v0 (what ``capevo evolve --modality rl`` seeds)."""
    reg = LocalRegistry(tmp_path / "registry", actor="tests")
    artifact, spec = seed_policy("T1", ECM, net_arch=(32, 32), seed=7)
    reg.promote(ECM, reg.publish(ECM, artifact, spec).version)
    yield reg
    reg.close()


def _request(reg: LocalRegistry) -> LearnRequest:
    return LearnRequest(task="pick", ecm=ECM, parent=reg.get_version(ECM), source="")


def test_state_files_round_trip_and_demos_accumulate(tmp_path: Path) -> None:
    state = LearnerState(tmp_path, ECM)
    assert state.latest() is None and state.demos() is None and not any(tmp_path.rglob(REPLAY))
    state.save_latest(b"zip-1")
    assert LearnerState(tmp_path, ECM).latest() == b"zip-1"  # invariant 1: another instance reads it
    a = (np.ones((3, 4), np.float32), np.zeros((3, 2), np.float32))
    b = (np.full((2, 4), 2.0, np.float32), np.ones((2, 2), np.float32))
    state.add_demos(*a)
    obs, act = state.add_demos(*b)
    np.testing.assert_array_equal(act, np.concatenate([a[1], b[1]]))
    np.testing.assert_array_equal(obs, np.concatenate([a[0], b[0]]))  # invariant 2: stored rows first
    np.testing.assert_array_equal(LearnerState(tmp_path, ECM).demos()[1], np.concatenate([a[1], b[1]]))
    with pytest.raises(Invalid) as info:
        state.add_demos(np.ones((1, 5), np.float32), np.ones((1, 2), np.float32))
    assert info.value.details["field"] == "demos"
    assert sorted(p.name for p in state.directory.iterdir()) == [DEMOS, LATEST]  # no temporary left


def test_a_writer_killed_mid_write_leaves_the_previous_state(tmp_path: Path) -> None:
    """Invariant 3: SIGKILL while a large state file is written; the old file stays whole."""
    state = LearnerState(tmp_path, ECM)
    state.save_latest(b"old")
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(
                f"""
                import sys
                from capevo.learner.continuation import LearnerState
                s = LearnerState({str(tmp_path)!r}, {ECM!r})
                sys.stdout.write("ready\\n"); sys.stdout.flush()
                while True:
                    s.save_latest(b"x" * 50_000_000)
                """
            ),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert child.stdout is not None and child.stdout.readline() == "ready\n"
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    assert LearnerState(tmp_path, ECM).latest() in (b"old", b"x" * 50_000_000)


@pytest.mark.slow
def test_sac_continues_from_its_rejected_candidate_and_keeps_its_buffer(
    registry: LocalRegistry, tmp_path: Path
) -> None:
    state_dir = tmp_path / "state"
    first = SacLearner(config=SAC, env_config=ENV_CONFIG, registry=registry, state_dir=state_dir, torch_threads=1)
    a = first.learn(_request(registry))
    assert a.notes["warm_start"] == "weights" and a.notes["replay_kept"] == 0
    assert LearnerState(state_dir, ECM).latest() == a.artifact
    # the gate rejected `a` (nothing was promoted): the next update still starts from it
    second = SacLearner(config=SAC, env_config=ENV_CONFIG, registry=registry, state_dir=state_dir, torch_threads=1)
    b = second.learn(_request(registry))
    assert b.notes["warm_start"] == "latest candidate"
    assert b.notes["replay_kept"] == SAC.total_steps  # every transition of the first update
    assert second.last_model.replay_buffer.pos == 2 * SAC.total_steps
    # without a state directory, the same request starts from the active v0 again
    fresh = SacLearner(config=SAC, env_config=ENV_CONFIG, registry=registry, torch_threads=1)
    assert fresh.learn(_request(registry)).notes["warm_start"] == "weights"


@pytest.mark.slow
def test_sac_on_a_random_v0_starts_from_a_cloned_actor(registry: LocalRegistry) -> None:
    bc = BcLearner(config=BC, env_config=ENV_CONFIG, registry=registry, scripted_episodes=2)
    cloned = SacLearner(config=SAC, env_config=ENV_CONFIG, registry=registry, bc=bc, distill=BC, torch_threads=1).learn(
        _request(registry)
    )
    assert cloned.notes["warm_start"] == "cloned"
    distill = cloned.notes["train"]["distill"]
    assert distill["samples"] > 0 and distill["loss_after"] < distill["loss_before"]


@pytest.mark.slow
def test_sac_clones_with_dagger_and_its_check_keeps_the_better_actor(registry: LocalRegistry) -> None:
    """The clone runs DAgger rounds, and the candidate's actor is the one its check (before and
    after SAC, on the same seeds) did not see do worse: re-running the check on the candidate
    gives the kept side's figure."""
    from capevo.learner.ecm_env import make_ecm_env, target_for
    from capevo.learner.rl import CHECK_SEED_OFFSET, check_actor

    bc_config = BcConfig(epochs=5, batch_size=32, net_arch=(32, 32), seed=0, dagger_rounds=1, dagger_episodes=1)
    sac_config = SacConfig(
        total_steps=60, buffer_size=1_000, batch_size=16, learning_starts=20, net_arch=(32, 32), check_episodes=2
    )
    bc = BcLearner(config=bc_config, env_config=ENV_CONFIG, registry=registry, scripted_episodes=2)
    learner = SacLearner(
        config=sac_config, env_config=ENV_CONFIG, registry=registry, bc=bc, distill=bc_config, torch_threads=1
    )
    cand = learner.learn(_request(registry))
    assert cand.notes["warm_start"] == "cloned"
    (round_1,) = cand.notes["dagger"]["rounds"]
    assert round_1["episodes"] == 1 and round_1["env_steps"] == cand.notes["dagger"]["env_steps"] >= round_1["rows"] > 0
    check = cand.notes["check"]
    for side in ("before", "after"):
        assert check[side]["episodes"] == 2 and check[side]["env_steps"] >= 2
    kept = "sac" if check["after"]["successes"] >= check["before"]["successes"] else "start"
    assert check["actor"] == kept
    env = make_ecm_env("T1", target_for("T1", ECM), registry=registry, config=ENV_CONFIG)
    try:
        again = check_actor(learner.last_model, env, episodes=2, first_seed=ENV_CONFIG.seed + CHECK_SEED_OFFSET)
    finally:
        env.close()
    assert again.to_dict() == check["after" if kept == "sac" else "before"]
    spent = cand.notes["env_steps"]
    assert spent["dagger"] == round_1["env_steps"] and spent["check"] == sum(
        check[s]["env_steps"] for s in check if s != "actor"
    )
    assert spent["sac"] >= sac_config.total_steps  # SAC's own steps (a reach ECM has no predecessors to drive)
    assert spent["total"] == spent["clone"] + spent["dagger"] + spent["check"] + spent["sac"] + spent["distill"]
    # a random-init v0 with nothing cloned has no learned start to check against
    bare = SacLearner(config=sac_config, env_config=ENV_CONFIG, registry=registry, torch_threads=1)
    assert bare.learn(_request(registry)).notes["check"] is None


@pytest.mark.slow
@pytest.mark.parametrize("ecm", ["pick.reach", "pick.grasp"])
def test_under_a_budget_the_clone_and_sac_together_spend_no_more_than_it(tmp_path: Path, ecm: str) -> None:
    """Issue 20's parity: the clone's scripted rollouts come out of the budget and SAC trains on the
    rest. A reach has no predecessors, so it spends the budget exactly; a grasp's resets drive the
    reach first, and SAC stops while one more reset still fits."""
    from capevo.learner.skills import seed_registry

    reg = LocalRegistry(tmp_path / "registry", actor="tests")
    try:
        seed_registry(reg, "pick")  # code predecessors drive the grasp's resets
        artifact, spec = seed_policy("T1", ecm, net_arch=(32, 32), seed=7)
        reg.promote(ecm, reg.publish(ecm, artifact, spec).version)
        bc = BcLearner(config=BC, env_config=ENV_CONFIG, registry=reg, scripted_episodes=2)
        budget = 400
        checked = dataclasses.replace(SAC, check_episodes=2)
        learner = SacLearner(
            config=checked,
            env_config=ENV_CONFIG,
            registry=reg,
            bc=bc,
            distill=BC,
            torch_threads=1,
            env_step_budget=budget,
        )
        cand = learner.learn(LearnRequest(task="pick", ecm=ecm, parent=reg.get_version(ecm), source=""))
    finally:
        reg.close()
    spent = cand.notes["env_steps"]
    assert cand.notes["warm_start"] == "cloned" and spent["clone"] > 0
    assert spent["total"] == spent["clone"] + spent["sac"]
    # the check's episodes after SAC could not be cut short to fit: none runs under a budget
    assert cand.notes["check"] is None and spent["check"] == 0
    reserve = 0 if ecm == "pick.reach" else ENV_CONFIG.prefix_budget
    assert budget - reserve <= spent["total"] <= budget


@pytest.mark.slow
def test_bc_keeps_every_demonstration_and_continues_from_its_latest(registry: LocalRegistry, tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    learner = BcLearner(config=BC, env_config=ENV_CONFIG, registry=registry, scripted_episodes=1, state_dir=state_dir)
    a = learner.learn(_request(registry))
    assert a.notes["continued"] is False and a.notes["demos"]["source"] == "scripted"
    rows_a = a.notes["demos"]["samples"]
    b = learner.learn(_request(registry))
    assert b.notes["continued"] is True and b.notes["demos"]["source"] == "scripted+earlier"
    assert b.notes["demos"]["samples"] == rows_a + b.notes["demos"]["new_samples"]
    assert LearnerState(state_dir, ECM).latest() == b.artifact
    # b started from a's weights: its loss before cloning is a's loss after, on a's rows
    assert b.notes["bc"]["loss_before"] < a.notes["bc"]["loss_before"]


@pytest.mark.slow
def test_sac_from_a_random_v0_clones_again_on_every_row_before_each_later_update(
    registry: LocalRegistry, tmp_path: Path
) -> None:
    """A lineage that began at a random v0 re-clones before SAC on every update, on the rows of
    all its updates so far: a SAC that loses every check must not hand the gate its first clone
    again and again (a 12-iteration T1 run did, results/evolution/T1-rl)."""
    state_dir = tmp_path / "state"
    bc = BcLearner(config=BC, env_config=ENV_CONFIG, registry=registry, scripted_episodes=1)

    def update() -> Any:
        learner = SacLearner(
            config=SAC,
            env_config=ENV_CONFIG,
            registry=registry,
            bc=bc,
            distill=BC,
            state_dir=state_dir,
            torch_threads=1,
        )
        return learner.learn(_request(registry))

    a = update()
    rows_a = a.notes["train"]["distill"]["samples"]
    assert a.notes["warm_start"] == "cloned" and rows_a > 0
    b = update()
    assert b.notes["warm_start"] == "latest candidate, cloned again"
    assert b.notes["replay_kept"] == SAC.total_steps
    stored = LearnerState(state_dir, ECM).demos()
    assert stored is not None
    rows_b = b.notes["train"]["distill"]["samples"]
    assert rows_b == len(stored[0]) > rows_a  # the second clone fitted the first update's rows too
    assert b.notes["env_steps"]["clone"] > 0


@pytest.mark.slow
def test_sac_on_a_random_v0_without_anything_to_clone_starts_from_its_weights(registry: LocalRegistry) -> None:
    """No scripted rollouts and no successful traces (T4-T6 have no scripted reference): SAC
    trains from the random v0 instead of failing the update."""
    bc = BcLearner(config=BC, env_config=ENV_CONFIG, registry=registry, scripted_episodes=0)
    cand = SacLearner(config=SAC, env_config=ENV_CONFIG, registry=registry, bc=bc, torch_threads=1).learn(
        _request(registry)
    )
    assert cand.notes["warm_start"] == "weights" and cand.notes["train"]["steps"] == SAC.total_steps


@pytest.mark.parametrize("budget", [0, -1, 1.5, True])
def test_sac_refuses_a_bad_env_step_budget(budget: object) -> None:
    with pytest.raises(Invalid) as info:
        SacLearner(env_step_budget=budget)  # type: ignore[arg-type]
    assert info.value.details["field"] == "env_step_budget"
    assert info.value.message == f"env_step_budget must be an integer >= 1, got {budget!r}"
