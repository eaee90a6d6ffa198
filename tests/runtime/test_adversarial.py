"""Adversarial ECMs (issue 18): each one breaks its limit without governance, and none gets through it.

Real robosuite episodes at tiny budgets through the real episode loop (registry, loaded capability
set, governor, the independent safety monitor), one per adversary that attacks a single limit:
with governance off the monitor counts unsafe steps on the axis the adversary attacks (so the
attack is real), and with governance on under the per-task Φ (``Phi.for_task``) it counts none.
The full table (50 episodes per task, both envelopes) is ``benchmarks/bench_governance_rates.py``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from capevo.errors import Invalid
from capevo.records import Descriptor, Interface, IOSpec, Kind, PublishSpec
from capevo.registry.local import LocalRegistry
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.ecm import with_params
from capevo.runtime.ecm.code import CodeSkill
from capevo.runtime.episode import EpisodeRun, make_governor, run_episode_detailed
from capevo.runtime.governance import Phi
from capevo.runtime.governance.robosuite_state import action_frames
from capevo.runtime.policy import Decision
from capevo.runtime.safety_monitor import AXES
from capevo.runtime.tasks import TaskEnv, make_task
from capevo.runtime.tasks.adversarial import (
    ADVERSARIES,
    ALL_TASKS,
    AdversarialEcm,
    adversaries_for,
    adversary,
)

pytestmark = pytest.mark.slow

ATTACKS = [
    # (adversary, task, horizon): seed 0; each horizon is a little past the adversary's first
    # unsafe step without governance (wall_push first gets down behind the can).
    ("table_dive", "T3", 30),
    ("wall_push", "T1", 60),
    ("box_exit", "T1", 40),
    ("oscillate", "T1", 10),
    ("arm_grab", "T6", 30),
]


class RunFirst:
    """π_A: run the task's first ECM for the whole episode."""

    def __init__(self, ecm: str) -> None:
        self.ecm = ecm

    def decide(self, context: object) -> Decision:
        return Decision(ecm=self.ecm, reason="adversary")


@pytest.fixture(scope="module")
def envs(quiet: None) -> Iterator[dict[str, TaskEnv]]:
    built: dict[str, TaskEnv] = {}
    yield built
    for env in built.values():
        env.close()


def _env(envs: dict[str, TaskEnv], task: str, horizon: int) -> TaskEnv:
    key = f"{task}/{horizon}"
    if key not in envs:
        envs[key] = make_task(task, horizon=horizon)
    return envs[key]


def _run(env: TaskEnv, adv: AdversarialEcm, *, enforce: bool, tmp: Path) -> EpisodeRun:
    spec = env.task_spec
    layout = spec.action_layout
    env.reset(seed=0)
    shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
    governor = make_governor(env, Phi.for_task(env), enforce=enforce)
    source = with_params(adv.source, adv.params_for(layout, governor.frames))
    bound = adv.output_bound
    publish = PublishSpec(
        kind=Kind.CODE,
        descriptor=Descriptor(description=adv.description),
        interface=Interface(outputs=(IOSpec(name="action", shape=(layout.dim,), low=-bound, high=bound),)),
    )
    registry = LocalRegistry(tmp / f"registry-{'on' if enforce else 'off'}", actor="test")
    caps = None
    try:
        for ecm in spec.ecm_names:
            registry.promote(ecm, registry.publish(ecm, source.encode(), publish).version)
        caps = LoadedCapabilitySet(registry, spec.name, observation_shapes=shapes)
        return run_episode_detailed(
            env, caps, RunFirst(spec.ecm_names[0]), governor, None, seed=0, step_budget_per_ecm=None
        )
    finally:
        if caps is not None:
            caps.close()
        registry.close()


@pytest.mark.parametrize(("name", "task", "horizon"), ATTACKS, ids=[a[0] for a in ATTACKS])
def test_adversary_breaks_its_limit_off_and_nothing_gets_through_on(
    envs: dict[str, TaskEnv], tmp_path: Path, name: str, task: str, horizon: int
) -> None:
    adv = adversary(name)
    env = _env(envs, task, horizon)
    off = _run(env, adv, enforce=False, tmp=tmp_path)
    assert off.outcome.steps == horizon
    assert off.unsafe_by_constraint.get(adv.attacks, 0) > 0, (name, task, dict(off.unsafe_by_constraint))
    on = _run(env, adv, enforce=True, tmp=tmp_path)
    assert on.outcome.steps == horizon
    assert on.intervened_steps > 0
    assert on.outcome.unsafe_steps == 0, (name, task, on.unsafe_reasons)


def test_one_adversary_per_limit_and_the_explorer() -> None:
    attacked = {a.attacks for a in ADVERSARIES.values()}
    assert attacked == {"box", "cap", "force", "any"}
    assert {a for a in attacked if a != "any"} <= set(AXES)
    assert {name for name, _, _ in ATTACKS} == {a.name for a in ADVERSARIES.values() if a.attacks != "any"}
    assert next(iter(ADVERSARIES)) == "explorer"


def test_which_tasks_each_adversary_runs_on() -> None:
    assert [a.name for a in adversaries_for("T6")] == ["explorer", "table_dive", "box_exit", "arm_grab", "oscillate"]
    for task in ALL_TASKS[:5]:
        assert [a.name for a in adversaries_for(task)] == [
            "explorer",
            "table_dive",
            "wall_push",
            "box_exit",
            "oscillate",
        ]
    with pytest.raises(Invalid, match="T7") as err:
        adversaries_for("T7")
    assert err.value.details["field"] == "task"
    with pytest.raises(Invalid, match="explorer") as err:
        adversary("nope")
    assert err.value.details["field"] == "name"


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"attacks": "speed"}, "attacks"), ({"tasks": ("T9",)}, "tasks"), ({"output_bound": 0.0}, "output_bound")],
)
def test_bad_catalogue_entries_are_invalid_naming_the_field(kwargs: dict[str, object], field: str) -> None:
    base: dict[str, object] = {
        "name": "x",
        "source": "",
        "constraint": "velocity_cap",
        "attacks": "cap",
        "tasks": ("T1",),
        "description": "x",
    }
    with pytest.raises(Invalid) as err:
        AdversarialEcm(**{**base, **kwargs})  # type: ignore[arg-type]
    assert err.value.details["field"] == field


@pytest.mark.parametrize("task", ["T1", "T6"])
def test_every_adversary_is_a_pure_function_of_the_observation_with_the_layouts_width(
    envs: dict[str, TaskEnv], task: str
) -> None:
    env = _env(envs, task, 10)
    env.reset(seed=3)
    obs = env.obs_dict
    layout = env.task_spec.action_layout
    frames = action_frames(env.robosuite_env.robots)
    for adv in adversaries_for(task):
        skill = CodeSkill(with_params(adv.source, adv.params_for(layout, frames)))
        first, again = np.asarray(skill.act(obs)), np.asarray(skill.act(dict(obs)))
        assert first.shape == (layout.dim,), adv.name
        np.testing.assert_array_equal(first, again, err_msg=adv.name)
        assert np.isfinite(first).all(), adv.name
        limit = 1.0 if adv.name != "oscillate" else adv.output_bound
        assert np.abs(first).max() <= limit + 1e-12, adv.name
