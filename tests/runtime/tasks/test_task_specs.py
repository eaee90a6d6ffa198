"""Task specs, registration and perturbation settings: no simulator is built here."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from capevo.errors import Conflict, ErrorCode, Invalid
from capevo.records import COMPARISON_OPS, Predicate
from capevo.records.names import validate_name
from capevo.registry.descriptor import spec_from_document
from capevo.registry.predicates import predicate_holds
from capevo.runtime.state import SINGLE_PANDA
from capevo.runtime.tasks import (
    RESERVED_ENV_KWARGS,
    Perturbations,
    TaskEnv,
    all_task_specs,
    make_task,
    register_task,
    task_class,
    task_ids,
    task_names,
    task_spec,
)
from capevo.runtime.tasks.perturbations import EpisodeRngs
from capevo.runtime.tasks.spec import EcmStep, TaskSpec, cond, pred, spec_problems

EXPECTED = {
    "T1": "pick",
    "T2": "place",
    "T3": "stack",
    "T4": "nut_assembly",
    "T5": "pick_place_multi",
    "T6": "peg_in_hole",
}
SIGNAL_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")


def test_six_tasks_registered_in_id_order() -> None:
    assert dict(task_ids()) == EXPECTED
    assert task_names() == tuple(EXPECTED.values())


@pytest.mark.parametrize("task_id", sorted(EXPECTED))
def test_id_and_name_find_the_same_task(task_id: str) -> None:
    assert task_class(task_id) is task_class(EXPECTED[task_id])
    spec = task_spec(task_id)
    assert (spec.id, spec.name) == (task_id, EXPECTED[task_id])


def test_unknown_task_lists_valid_names() -> None:
    with pytest.raises(Invalid) as e:
        make_task("T7")
    assert e.value.code is ErrorCode.INVALID
    for task_id, name in EXPECTED.items():
        assert f"{task_id} ({name})" in e.value.message
    assert "unknown task 'T7'" in e.value.message
    with pytest.raises(Invalid):
        task_spec(3)  # type: ignore[arg-type]


@pytest.mark.parametrize("spec", all_task_specs(), ids=lambda s: s.name)
def test_spec_is_consistent(spec: TaskSpec) -> None:
    assert spec_problems(spec) == []
    names = spec.signal_names
    assert len(set(names)) == len(names)
    assert all(SIGNAL_PATTERN.match(n) for n in names)
    assert "success" in names
    assert len(set(spec.observation_keys)) == len(spec.observation_keys)
    assert set(spec.position_keys) <= set(spec.observation_keys)
    assert spec.default_horizon > 0
    for step in spec.decomposition:
        assert validate_name(step.ecm) == step.ecm
        assert step.ecm.startswith(spec.name + ".")
        assert step.termination.all, f"{step.ecm} has no termination"
        assert all(c.op in COMPARISON_OPS and math.isfinite(c.value) for c in step.termination.all)
        assert step.observation_keys
    assert len({s.ecm for s in spec.decomposition}) == len(spec.decomposition)


@pytest.mark.parametrize("spec", all_task_specs(), ids=lambda s: s.name)
def test_step_descriptors_pass_the_registry_schema(spec: TaskSpec) -> None:
    for step in spec.decomposition:
        doc = {"kind": "code", **step.descriptor().to_dict()}
        assert spec_from_document(doc).descriptor == step.descriptor()


def test_action_layouts() -> None:
    for task_id in ("T1", "T2", "T3", "T4", "T5"):
        spec = task_spec(task_id)
        assert spec.action_layout == SINGLE_PANDA
        assert spec.n_arms == 1
    peg = task_spec("T6")
    assert peg.n_arms == 2
    assert peg.action_layout.dim == 12
    assert [(a.offset, a.gripper) for a in peg.action_layout.arms] == [(0, None), (6, None)]


def test_default_decompositions() -> None:
    steps = {n: [s.ecm.split(".", 1)[1] for s in task_spec(n).decomposition] for n in EXPECTED.values()}
    assert steps["pick"] == ["reach", "grasp", "lift"]
    assert steps["place"] == ["reach", "grasp", "lift", "move", "release"]
    assert steps["stack"] == ["reach", "grasp", "lift", "align", "lower", "release"]
    assert steps["nut_assembly"] == ["reach", "grasp", "lift", "align", "insert", "release"]
    assert steps["pick_place_multi"] == [
        f"{o}.{s}" for o in ("milk", "bread", "can") for s in ("reach", "grasp", "lift", "move", "release")
    ]
    assert len(steps["peg_in_hole"]) == 8


def test_pick_lift_termination_is_the_success_criterion() -> None:
    lift = task_spec("pick").decomposition[-1].termination
    assert predicate_holds(lift, {"object_height_above_start": 0.051})
    assert not predicate_holds(lift, {"object_height_above_start": 0.05})


def test_spec_problems_reports_unknown_names() -> None:
    good = task_spec("pick")
    bad_step = EcmStep(
        ecm="Pick.Reach",
        description="x",
        observation_keys=("nope",),
        termination=pred("t", cond("no_such_signal", "<", 1.0)),
    )
    spec = TaskSpec(
        id="T99",
        name="pick",
        env_name="PickPlace",
        n_arms=1,
        action_layout=SINGLE_PANDA,
        observation_keys=good.observation_keys,
        position_keys=("unlisted_pos",),
        signals=good.signals,
        decomposition=(bad_step,),
        success_text="",
        reward_text="",
        default_horizon=10,
    )
    problems = "\n".join(spec_problems(spec))
    assert "not a slug" in problems
    assert "does not start with 'pick.'" in problems
    assert "unknown signal 'no_such_signal'" in problems
    assert "unknown observation key 'nope'" in problems
    assert "position key 'unlisted_pos'" in problems


def test_cond_refuses_unknown_operator() -> None:
    with pytest.raises(Invalid) as e:
        cond("x", "=>", 1.0)
    assert e.value.code is ErrorCode.INVALID
    assert "unknown comparison '=>'" in e.value.message


def test_register_refuses_missing_and_conflicting_specs() -> None:
    class NoSpec(TaskEnv):
        pass

    with pytest.raises(Invalid) as e:
        register_task(NoSpec)
    assert "has no task_spec" in e.value.message

    class SameId(TaskEnv):
        task_spec = TaskSpec(
            **{
                **{f: getattr(task_spec("pick"), f) for f in TaskSpec.__dataclass_fields__},
                "name": "pick2",
                "decomposition": (),
            }
        )

    with pytest.raises(Conflict) as c:
        register_task(SameId)
    assert c.value.code is ErrorCode.CONFLICT
    assert "'T1' is already registered" in c.value.message
    assert "pick2" not in task_names()

    class Broken(TaskEnv):
        task_spec = TaskSpec(
            **{
                **{f: getattr(task_spec("pick"), f) for f in TaskSpec.__dataclass_fields__},
                "id": "T98",
                "name": "broken",
                "decomposition": (
                    EcmStep(ecm="broken.x", description="", observation_keys=(), termination=Predicate()),
                    EcmStep(
                        ecm="broken.y",
                        description="",
                        observation_keys=(),
                        termination=pred("", cond("nope", "<", 0)),
                    ),
                ),
            }
        )

    with pytest.raises(Invalid) as b:
        register_task(Broken)
    assert "broken.y: unknown signal 'nope'" in b.value.message
    assert "broken" not in task_names()


@pytest.mark.parametrize("key", sorted(RESERVED_ENV_KWARGS))
def test_reserved_robosuite_arguments_are_refused(key: str) -> None:
    with pytest.raises(Invalid) as e:
        make_task("T1", **{key: True})
    assert e.value.code is ErrorCode.INVALID
    assert key in e.value.message and "fixed by the task" in e.value.message


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"seed": True}, "seed"),
        ({"horizon": 0}, "horizon"),
        ({"horizon": 2.0}, "horizon"),
        ({"perturbations": {"actuation_failure_p": 0.1}}, "perturbations"),
    ],
)
def test_bad_arguments_are_refused_before_building(kwargs: dict, field: str) -> None:
    with pytest.raises(Invalid) as e:
        make_task("T3", **kwargs)
    assert e.value.details["field"] == field
    assert field in e.value.message


def test_perturbation_defaults_and_none() -> None:
    p = Perturbations()
    assert (p.object_position_jitter, p.obs_position_noise_std, p.actuation_failure_p) == (0.05, 0.01, 0.05)
    assert p.any
    n = Perturbations.none()
    assert (n.object_position_jitter, n.obs_position_noise_std, n.actuation_failure_p) == (0.0, 0.0, 0.0)
    assert not n.any


finite = st.floats(min_value=-2.0, max_value=2.0, allow_nan=False)


@given(jitter=finite, noise=finite, p=st.one_of(finite, st.just(math.nan), st.just(math.inf)))
def test_perturbations_accept_exactly_the_valid_settings(jitter: float, noise: float, p: float) -> None:
    valid = jitter >= 0 and noise >= 0 and math.isfinite(p) and 0 <= p <= 1
    if valid:
        Perturbations(object_position_jitter=jitter, obs_position_noise_std=noise, actuation_failure_p=p)
    else:
        with pytest.raises(Invalid) as e:
            Perturbations(object_position_jitter=jitter, obs_position_noise_std=noise, actuation_failure_p=p)
        assert e.value.details["field"] in {"object_position_jitter", "obs_position_noise_std", "actuation_failure_p"}


def test_episode_streams_are_seeded_and_independent() -> None:
    a, b, c = EpisodeRngs(7), EpisodeRngs(7), EpisodeRngs(8)
    for name in ("scene", "jitter", "obs_noise", "drop"):
        x, y, z = (getattr(r, name).random(5) for r in (a, b, c))
        assert np.array_equal(x, y)
        assert not np.array_equal(x, z)
    d = EpisodeRngs(7)
    assert not np.array_equal(d.drop.random(5), d.obs_noise.random(5))
