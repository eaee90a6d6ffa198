"""The fused kernel as a whole: it is built, it takes every built-in Φ, it can be switched off,
and governors that use it give what the Python checks give, for whole envelopes, on drawn states
and on states from real robosuite episodes (fused.py invariants 1 and 2)."""

from __future__ import annotations

import dataclasses
import functools
import random
from typing import Any

import numpy as np
import pytest
from fused_support import SIGNED_PERMUTATIONS, Pair, actions, robot_states
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.runtime.governance import CONSTRAINTS, Governor, Phi, WorkspaceBox, fused
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.state import SINGLE_PANDA, ActionLayout, ArmState, RobotState

TASKS = ("T1", "T2", "T3", "T4", "T5", "T6")


def layout_of(task: str) -> tuple[ActionLayout, Any]:
    return (TWO_ARM_NO_GRIPPER, SIGNED_PERMUTATIONS[2:4]) if task == "T6" else (SINGLE_PANDA, None)


def test_inv1_the_kernel_is_built_and_has_a_check_for_every_registered_kind() -> None:
    assert fused.kernel_available()
    assert set(CONSTRAINTS) <= set(fused.kernel_kinds())
    for kind, cls in CONSTRAINTS.items():
        assert callable(getattr(cls, "kernel_spec", None)), kind


@pytest.mark.parametrize("task", ["paper", *TASKS])
def test_inv1_every_built_in_phi_runs_in_the_kernel(task: str) -> None:
    phi, (layout, frames) = (
        (Phi.default(), (SINGLE_PANDA, None)) if task == "paper" else (Phi.for_task(task), layout_of(task))
    )
    assert Governor(phi, layout, frames=frames)._program is not None
    assert Governor(phi, layout, frames=frames, kernel=False)._program is None


def test_inv1_switched_off_by_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(fused.ENV_SWITCH, "0")
    assert not fused.kernel_available()
    assert Governor(Phi.default(), SINGLE_PANDA)._program is None


def test_inv1_a_constraint_without_a_port_sends_the_whole_phi_to_python() -> None:
    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class Unported(WorkspaceBox):
        def kernel_spec(self, layout: ActionLayout) -> None:
            return None

    phi = Phi((*Phi.default().constraints, Unported(name="unported")))
    governor = Governor(phi, SINGLE_PANDA)
    assert governor._program is None
    state = RobotState(arms=(ArmState(eef_pos=(0.55, 0.0, 1.0), eef_force=(0.0, 0.0, 25.0)),))
    assert governor(state, [0.1] * 7) == Governor(phi, SINGLE_PANDA, kernel=False)(state, [0.1] * 7)


@functools.cache
def pair_for(task: str, enforce: bool = True) -> Pair:
    layout, frames = layout_of(task)
    return Pair(Phi.for_task(task), layout, frames=frames, enforce=enforce)


@pytest.mark.parametrize("task", TASKS)
@settings(max_examples=125, deadline=None)
@given(data=st.data())
def test_inv2_per_task_phi_matches_the_python_checks(task: str, data: st.DataObject) -> None:
    pair = pair_for(task)
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


@pytest.mark.parametrize("task", ["T1", "T6"])
@settings(max_examples=50, deadline=None)
@given(data=st.data())
def test_inv2_governance_off_matches_too(task: str, data: st.DataObject) -> None:
    pair = pair_for(task, enforce=False)
    layout = pair.kernel.layout
    pair.check(data.draw(robot_states(len(layout.arms))), data.draw(actions(layout.dim)))


JUNK = st.one_of(
    st.none(),
    st.integers(),
    st.text(max_size=3),
    st.lists(st.one_of(st.floats(), st.integers(), st.none(), st.text(max_size=2)), max_size=13),
    st.tuples(st.floats(), st.floats()),
)


@settings(max_examples=150, deadline=None)
@given(arms=JUNK, action=JUNK)
def test_inv2_the_program_takes_any_input_without_raising_and_declines_what_it_cannot_read(
    arms: Any, action: Any
) -> None:
    program = pair_for("T6").kernel._program
    assert program(arms, action) is None or isinstance(arms, tuple)


@settings(max_examples=100, deadline=None)
@given(state=robot_states(1), action=actions(7), kind=st.sampled_from(["f64", "f32", "tuple", "ints", "2d", "nan"]))
def test_inv2_other_action_types_match(state: Any, action: list[float], kind: str) -> None:
    pair = pair_for("T1")
    value: Any = {
        "f64": lambda: np.array(action),
        "f32": lambda: np.array(action, dtype=np.float32),
        "tuple": lambda: tuple(action),
        "ints": lambda: [int(max(-5.0, min(5.0, x))) for x in action],
        "2d": lambda: np.array([action]),
        "nan": lambda: [*action[:-1], float("nan")],
    }[kind]()
    pair.check(state, value)


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_inv2_matches_on_states_from_real_episodes(task: str) -> None:
    """Real scenes (contacts, held objects, both arms of T6) under an aggressive random policy."""
    from capevo.runtime.episode import make_governor
    from capevo.runtime.tasks import make_task
    from capevo.runtime.tasks.base import quiet_robosuite

    with quiet_robosuite():
        env = make_task(task, horizon=60, terminate_on_success=False)
    try:
        phi = Phi.for_task(task)
        governor = make_governor(env, phi)
        pair = Pair(phi, env.task_spec.action_layout, frames=governor.frames)
        rng = random.Random(task)
        env.reset(seed=11)
        for _ in range(60):
            state = env.robot_state()
            proposed = [rng.uniform(-1.5, 1.5) for _ in range(pair.kernel.layout.dim)]
            pair.check(state, proposed)
            for _ in range(5):
                pair.check(state, [rng.uniform(-0.3, 0.3) for _ in proposed])
            governed, _ = governor(state, proposed)
            env.step(np.asarray(governed if governed is not None else [0.0] * len(proposed)))
        assert pair.handled == pair.calls
    finally:
        env.close()
