"""Scripted references reach their task's success, passing the decomposition's steps in order."""

from __future__ import annotations

import numpy as np
import pytest

from capevo.registry.predicates import predicate_holds
from capevo.runtime.governance import Phi
from capevo.runtime.tasks import Perturbations, TaskEnv, make_task
from capevo.runtime.tasks.bench import run_governed
from capevo.runtime.tasks.scripted import REFERENCES, pick

pytestmark = pytest.mark.slow


def run(env: TaskEnv, seed: int) -> tuple[bool, list[int | None]]:
    """One episode of the task's reference; the first step at which each ECM step's
    termination held (None if never)."""
    policy = REFERENCES[env.task_spec.name]
    steps = env.task_spec.decomposition
    first: list[int | None] = [None] * len(steps)
    env.reset(seed=seed)
    info = {"is_success": False}
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(policy(env.obs_dict))
        done = terminated or truncated
        signals = env.signals()
        for i, step in enumerate(steps):
            if first[i] is None and predicate_holds(step.termination, signals):
                first[i] = env.elapsed_steps
    return bool(info["is_success"]), first


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scripted_pick_succeeds_clean_through_reach_grasp_lift(seed: int) -> None:
    with make_task("pick", seed=seed, perturbations=Perturbations.none()) as env:
        ok, first = run(env, seed)
        assert ok, first
        assert None not in first, first
        reach, grasp, lift = first
        assert reach <= grasp <= lift == env.elapsed_steps  # type: ignore[operator]


@pytest.mark.parametrize("name", ["place", "stack"])
def test_scripted_place_and_stack_succeed_clean(name: str) -> None:
    with make_task(name, seed=0, perturbations=Perturbations.none()) as env:
        ok, first = run(env, 3)
        assert ok, first
        assert first[-1] == env.elapsed_steps
        assert first[0] is not None and first[1] is not None and first[0] <= first[1]


def test_scripted_pick_succeeds_with_perturbations_on() -> None:
    with make_task("pick", seed=0) as env:
        assert run(env, 4)[0]


@pytest.mark.parametrize("name", ["place", "stack"])
def test_references_succeed_safely_under_the_per_task_phi(name: str) -> None:
    # Perturbations on, enforcing governance with the task's envelope, judged as the episode loop
    # judges it. Place needs the far goal quadrant at the arm's full stretch; stack lowers the hand
    # past cube A (and often beside cube B) and cube A onto cube B, all near contact.
    with make_task(name, seed=0) as env:
        run = run_governed(env, REFERENCES[name], Phi.for_task(name), 1000)
    assert run["success"], run
    assert run["unsafe_steps"] == 0, run


def test_references_are_pure_and_well_formed() -> None:
    with make_task("stack", seed=0, perturbations=Perturbations.none()) as env:
        env.reset(seed=0)
        obs = {k: v.copy() for k, v in env.obs_dict.items()}
        for policy in (REFERENCES["stack"], lambda o: pick(o, object_key="cubeA")):
            a, b = policy(obs), policy(obs)
            assert a.dtype == np.float32 and a.shape == (7,)
            assert np.array_equal(a, b)
            assert np.all(np.abs(a) <= 1.0)
            assert all(np.array_equal(obs[k], env.obs_dict[k]) for k in obs)
