"""closing_grip: while a gripper closes on a loose object between its fingers, the hand moves slowly.

The rule on synthetic proximity pairs (worked examples, its invariant by hypothesis), and the
hand-set T3 grasp that pressed the cube into the table replayed open loop in robosuite: unsafe
without the rule, safe with it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from replay import unsafe_reasons

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import ArmScene, ClosingGrip, Phi, load_phi, make
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER
from capevo.runtime.governance.pose import DOWN
from capevo.runtime.governance.proximity import FIXED, LOOSE
from capevo.runtime.state import SINGLE_PANDA, RobotState
from capevo.runtime.tasks import task_spec

DATA = Path(__file__).parent / "data"
RULE = ClosingGrip(within=0.01, speed=0.05)
LEFT, RIGHT = (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)


def pair(dist: float, n: tuple[float, float, float], owner: int = LOOSE) -> tuple[float, ...]:
    norm = math.sqrt(sum(x * x for x in n))
    return (dist, *(x / norm for x in n), 0.0, 0.0, 0.0, owner)


def arm(*pairs: tuple[float, ...]) -> ArmScene:
    return ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=pairs)


def govern(scene: ArmScene, action: list[float]) -> Any:
    """The governed action (a list, or the very input when untouched) and the interventions."""
    out, records = Phi((RULE,)).governor(SINGLE_PANDA)(RobotState(arms=(scene,)), action)
    return (list(out) if out is not None and out is not action else out), records


def test_config_round_trips_and_bad_values_name_their_field() -> None:
    phi = Phi((ClosingGrip(within=0.02, speed=0.1),))
    assert load_phi(phi.to_yaml()) == phi
    assert make("closing_grip", speed=0.1) == ClosingGrip(speed=0.1)
    for field, value in (("within", 0.0), ("within", 0.06), ("speed", -0.1), ("speed", 1.5), ("speed", math.nan)):
        with pytest.raises(Invalid) as err:
            ClosingGrip(**{field: value})
        assert err.value.code is ErrorCode.INVALID and err.value.details["field"] == field


def test_the_hand_descending_while_its_fingers_close_on_a_cube_is_slowed_in_its_own_direction() -> None:
    """The T3 case: the cube 2-3 mm from each finger, the hand still descending at -0.17."""
    a = [0.02, 0.07, -0.17, -0.001, -0.004, 0.0, 1.0]
    out, records = govern(arm(pair(0.0019, LEFT), pair(0.0031, RIGHT)), a)
    assert records and "gripper closing" in records[0].reason
    norm = math.sqrt(sum(x * x for x in a[:3]))
    assert math.sqrt(sum(x * x for x in out[:3])) == pytest.approx(RULE.speed)
    assert out[:3] == pytest.approx([x * RULE.speed / norm for x in a[:3]])
    assert out[3:] == a[3:]  # rotation and gripper are not the rule's


def test_an_open_gripper_one_sided_or_distant_object_fixed_scene_or_slow_hand_is_left_alone() -> None:
    between = arm(pair(0.002, LEFT), pair(0.002, RIGHT))
    for scene, action in (
        (between, [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0]),  # opening
        (between, [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 0.0]),  # holding the gripper still
        (arm(pair(0.002, LEFT), pair(0.003, LEFT)), [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0]),  # pushing one side
        (arm(pair(0.002, LEFT), pair(0.01, RIGHT)), [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0]),  # other side beyond
        (arm(pair(0.002, LEFT, FIXED), pair(0.002, RIGHT, FIXED)), [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0]),
        (arm(pair(0.002, LEFT, 1), pair(0.002, RIGHT, 1)), [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0]),  # another arm
        (between, [0.03, 0.0, -0.04, 0.3, 0.0, 0.0, 1.0]),  # already slow (norm 0.05)
        (arm(), [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0]),
    ):
        out, records = govern(scene, action)
        assert out is action and not records, (scene.near, action)


def test_arms_without_a_gripper_are_never_slowed() -> None:
    """T6's arms hold a peg and a plate: no gripper command, nothing for the rule to read."""
    scene = arm(pair(0.002, LEFT), pair(0.002, RIGHT))
    action = [0.0, 0.0, -0.5, 0.0, 0.0, 0.0] * 2
    out, records = Phi((RULE,)).governor(TWO_ARM_NO_GRIPPER)(RobotState(arms=(scene, scene)), action)
    assert out is action and not records


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_loose_pair_in_the_band_is_rejected(bad: float) -> None:
    out, records = govern(arm(pair(0.002, LEFT), (0.002, bad, 0.0, 0.0, 0.0, 0.0, 0.0, LOOSE)), [0.0] * 6 + [1.0])
    assert out is None and records and "not finite" in records[0].reason


DIST = st.floats(-0.01, 0.03)
UNIT = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: sum(x * x for x in v) > 0.01)
ACTION = st.lists(st.floats(-1, 1), min_size=7, max_size=7)


@settings(max_examples=300, deadline=None)
@given(pairs=st.lists(st.builds(pair, DIST, UNIT, st.sampled_from([FIXED, LOOSE, 0])), max_size=4), action=ACTION)
def test_the_translation_is_bounded_exactly_when_closing_on_something_between_the_fingers(
    pairs: list[tuple[float, ...]], action: list[float]
) -> None:
    """Invariant 1: closing with two opposite loose pairs in the band bounds the translation's norm,
    keeping its direction; anything else leaves the arm as it was."""
    out, _ = govern(arm(*pairs), action)
    out = action if out is action else out
    loose = [p[1:4] for p in pairs if p[7] == LOOSE and p[0] < RULE.within]
    between = any(sum(m[k] * n[k] for k in range(3)) < 0 for i, m in enumerate(loose) for n in loose[i + 1 :])
    norm = math.sqrt(sum(x * x for x in action[:3]))
    if action[6] > 0 and between and norm > RULE.speed:
        assert math.sqrt(sum(x * x for x in out[:3])) == pytest.approx(RULE.speed)
        assert out[:3] == pytest.approx([x * RULE.speed / norm for x in action[:3]])
    else:
        assert out[:3] == action[:3]
    assert out[3:] == action[3:]


GRASP_PRESS = DATA / "t3_hand_set_grasp_press_actions.json"


@pytest.mark.slow
def test_the_hand_set_stack_grasp_no_longer_presses_the_cube_into_the_table() -> None:
    """The hand-set T3 set on held-out seed 250028: ``stack.grasp`` closed the gripper while still
    descending, and the cube, caught during that step, was pressed into the table at 21.2 N. Its
    proposed actions replayed open loop under the default Φ without closing_grip press it again;
    with the rule (the default Φ) no step is unsafe."""
    record = json.loads(GRASP_PRESS.read_text())
    full = Phi.for_task(task_spec(record["task"]))
    without = Phi(tuple(c for c in full.constraints if not isinstance(c, ClosingGrip)))
    pressed = unsafe_reasons(record["actions"], record["seed"], task=record["task"], phi=without)
    assert any("cubeA" in r and "table" in r for r in pressed), pressed
    assert unsafe_reasons(record["actions"], record["seed"], task=record["task"], phi=full) == []
