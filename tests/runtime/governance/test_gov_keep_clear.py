"""keep_clear: a wrist link, or the hand near the fixed scene, steered back out of a thin band.

The rule on synthetic proximity pairs (worked examples, invariants by hypothesis); inside the
per-task Φ, where ``contact_approach`` after it must still hold; and one learned policy's forearm
strike replayed open loop in robosuite, unsafe without the rule and safe with it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from govcheck import violations
from hypothesis import given, settings
from hypothesis import strategies as st
from replay import unsafe_reasons

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import ArmScene, ContactApproach, KeepClear, Phi, StoppingDistance, load_phi, make
from capevo.runtime.governance.keep_clear import MIN_ROW2
from capevo.runtime.governance.pose import DOWN
from capevo.runtime.governance.proximity import FIXED, LOOSE
from capevo.runtime.state import SINGLE_PANDA, RobotState
from capevo.runtime.tasks import task_spec

DATA = Path(__file__).parent / "data"
RULE = KeepClear(within=0.003, restore=0.01)


def pair(dist: float, n: tuple[float, float, float], owner: int = FIXED) -> tuple[float, ...]:
    norm = math.sqrt(sum(x * x for x in n))
    return (dist, *(x / norm for x in n), 0.0, 0.0, 0.0, owner)


def arm(*pairs: tuple[float, ...], rows: tuple[tuple[int, tuple[float, ...]], ...] = ()) -> ArmScene:
    return ArmScene(eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=pairs, link_rows=rows)


def govern(rule: Any, scene: ArmScene, action: list[float]) -> Any:
    """The governed action (a list, or the very input when untouched) and the interventions."""
    out, records = Phi((rule,)).governor(SINGLE_PANDA)(RobotState(arms=(scene,)), action)
    return (list(out) if out is not None and out is not action else out), records


def dot(g: tuple[float, ...], a: list[float]) -> float:
    return sum(g[j] * a[j] for j in range(6))


def test_config_round_trips_and_bad_values_name_their_field() -> None:
    phi = Phi((KeepClear(within=0.002, restore=0.02),))
    assert load_phi(phi.to_yaml()) == phi
    assert make("keep_clear", within=0.002) == KeepClear(within=0.002)
    for field, value in (("within", 0.0), ("within", 0.06), ("restore", 0.0), ("restore", 0.7), ("within", math.nan)):
        with pytest.raises(Invalid) as err:
            KeepClear(**{field: value})
        assert err.value.code is ErrorCode.INVALID and err.value.details["field"] == field


def test_a_fingertip_at_the_floor_is_lifted_and_keeps_its_sideways_motion() -> None:
    """The dragged fingertip: a fixed pair straight below, the command sideways with z at 0."""
    out, records = govern(RULE, arm(pair(0.0001, (0.0, 0.0, -1.0))), [0.0, -0.2, 0.0, 0.1, 0.0, 0.0, -0.05])
    assert records
    assert out[2] == pytest.approx(RULE.target(0.0001)) and out[2] > 0.0
    assert out[:2] == [0.0, -0.2] and out[3:] == [0.1, 0.0, 0.0, -0.05]


def test_a_link_creeping_in_at_the_touch_speed_is_turned_back_along_its_row() -> None:
    """The forearm case: a link pair 1 mm off, its row closing at about the touch speed."""
    g = (0.5, -0.12, -0.88, 0.9, -1.0, 0.4)
    a = [0.0, 0.0, -0.01, 0.0, 0.0, 0.06, 0.3]
    assert dot(g, a) > 0.0
    out, _ = govern(RULE, arm(pair(0.001, (0.37, 0.0, -0.93)), rows=((0, g),)), a)
    assert dot(g, out) == pytest.approx(-RULE.target(0.001))
    assert out[6] == 0.3  # the gripper is not the rule's


def test_what_needs_contact_and_what_is_outside_the_band_is_left_alone() -> None:
    """Loose objects (grasping, pushing), another arm's hand (T6's insertion), and pairs beyond ``within``."""
    a = [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 1.0]
    for scene in (
        arm(pair(0.0, (0.0, 0.0, -1.0), LOOSE)),
        arm(pair(0.0, (0.0, 1.0, 0.0), 0)),
        arm(pair(0.003, (0.0, 0.0, -1.0))),
        arm(),
    ):
        out, records = govern(RULE, scene, a)
        assert out is a and not records


def test_a_link_the_action_barely_moves_is_not_steered() -> None:
    g = (0.05, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert sum(v * v for v in g) < MIN_ROW2
    a = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    out, _ = govern(RULE, arm(pair(0.0, (1.0, 0.0, 0.0)), rows=((0, g),)), a)
    assert out is a


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_pair_or_row_in_the_band_is_rejected(bad: float) -> None:
    a = [0.0] * 7
    out, records = govern(RULE, arm((0.0, bad, 0.0, -1.0, 0.0, 0.0, 0.0, FIXED)), a)
    assert out is None and records[0].result is None
    out, records = govern(RULE, arm((math.nan, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, FIXED)), a)
    assert out is None
    row = (0.0, 0.0, bad, 0.0, 0.0, 0.0)
    out, records = govern(RULE, arm(pair(0.0, (0.0, 0.0, -1.0)), rows=((0, row),)), a)
    assert out is None and "link row" in records[0].reason


DIST = st.floats(-0.002, 0.004)
UNIT = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda n: sum(x * x for x in n) > 0.01)
ROW = st.tuples(*[st.floats(-3.0, 3.0)] * 6)
ACTION = st.lists(st.floats(-1.0, 1.0), min_size=7, max_size=7)


@settings(max_examples=300, deadline=None)
@given(dist=DIST, n=UNIT, row=st.one_of(st.none(), ROW), owner=st.sampled_from([FIXED, LOOSE, 0]), a=ACTION)
def test_one_pair_in_the_band_gets_its_speed_away(
    dist: float, n: tuple[float, float, float], row: tuple[float, ...] | None, owner: int, a: list[float]
) -> None:
    """Invariants 1-3 for a single pair: the target is met unless a component hit ±1, only the
    pose components (a hand pair: the translation) change, and each stays within [−1, 1]."""
    p = pair(dist, n, owner)
    rows = ((0, row),) if row is not None else ()
    out, _ = govern(RULE, arm(p, rows=rows), a)
    target = RULE.target(dist)
    g = row if row is not None else (*p[1:4], 0.0, 0.0, 0.0)
    in_scope = sum(v * v for v in row) >= MIN_ROW2 if row is not None else owner == FIXED
    steered = target > 0.0 and in_scope
    if not steered:
        assert out is a
        return
    assert out[6] == a[6]
    if row is None:
        assert out[3:6] == a[3:6]
    assert all(-1.0 <= v <= 1.0 for v in out)
    stuck = all(out[j] == (-1.0 if g[j] > 0 else 1.0) for j in range(6) if g[j] != 0.0)
    if not stuck:
        assert dot(g, out) <= -target * (1 - 1e-9) + 1e-12


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_inside_the_task_phi_contact_approach_still_holds_after_the_steering(data: st.DataObject) -> None:
    """keep_clear runs before contact_approach, so every pair's closing bound still holds after both."""
    phi = Phi.for_task(task_spec("T1"))
    rules = tuple(c for c in phi.constraints if isinstance(c, (KeepClear, ContactApproach)))
    assert [type(c) for c in rules] == [KeepClear, ContactApproach]
    pairs = data.draw(st.lists(st.builds(pair, DIST, UNIT, st.sampled_from([FIXED, LOOSE])), min_size=1, max_size=3))
    rows = tuple((k, data.draw(ROW)) for k in sorted(data.draw(st.sets(st.integers(0, len(pairs) - 1)))))
    state = RobotState(arms=(arm(*pairs, rows=rows),))
    action = data.draw(ACTION)
    out, _ = Phi(rules).governor(SINGLE_PANDA)(state, action)
    assert violations(Phi(rules[1:]), SINGLE_PANDA, state, out, tol=1e-9) == []


FOREARM_CREEP = DATA / "am_t1_forearm_creep_actions.json"


@pytest.mark.slow
def test_the_forearm_a_learned_policy_crept_into_the_bin_at_the_touch_speed_is_kept_off() -> None:
    """The AM baseline's T1 policy (a cpu-small cell, iteration 3, seed 2000042049): its forearm
    (link 5) closed on the bin's rim at contact_approach's touch speed and struck it at 82 N.
    Its proposed actions, replayed open loop under the default Φ without keep_clear, strike the
    bin again; with the rule (the default Φ) no step is unsafe. ``stopping_distance`` prevents this
    strike too, so it is left out of the Φ without the rule as well."""
    record = json.loads(FOREARM_CREEP.read_text())
    full = Phi.for_task(task_spec("T1"))
    without = Phi(tuple(c for c in full.constraints if not isinstance(c, (KeepClear, StoppingDistance))))
    struck = unsafe_reasons(record["actions"], record["seed"], phi=without)
    assert any("link5" in r for r in struck), struck
    assert unsafe_reasons(record["actions"], record["seed"], phi=full) == []
