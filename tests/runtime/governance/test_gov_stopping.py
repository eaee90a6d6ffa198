"""stopping_distance: a hand or wrist link closing on the fixed scene too fast to stop is pushed back.

The rule on synthetic proximity pairs (worked examples, invariants by hypothesis); the closing
speeds the live sensor measures, against a finite difference of the gaps; and two learned
policies' strikes replayed open loop in robosuite, unsafe without the rule and safe with it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from replay import unsafe_reasons

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import ArmScene, Phi, StoppingDistance, load_phi, make
from capevo.runtime.governance.keep_clear import MIN_ROW2
from capevo.runtime.governance.pose import DOWN
from capevo.runtime.governance.proximity import FIXED, LOOSE
from capevo.runtime.state import SINGLE_PANDA, RobotState
from capevo.runtime.tasks import task_spec

DATA = Path(__file__).parent / "data"
RULE = StoppingDistance(decel=0.2, clearance=0.003, gain=3.0, touch=0.04)


def pair(dist: float, n: tuple[float, float, float], owner: int = FIXED) -> tuple[float, ...]:
    norm = math.sqrt(sum(x * x for x in n))
    return (dist, *(x / norm for x in n), 0.0, 0.0, 0.0, owner)


def arm(
    *pairs: tuple[float, ...], closing: tuple[float, ...] = (), rows: tuple[tuple[int, tuple[float, ...]], ...] = ()
) -> ArmScene:
    return ArmScene(
        eef_pos=(0.0, 0.0, 1.0), eef_force=(0.0, 0.0, 0.0), eef_rot=DOWN, near=pairs, link_rows=rows, closing=closing
    )


def govern(scene: ArmScene, action: list[float], rule: Any = RULE) -> Any:
    """The governed action (a list, or the very input when untouched) and the interventions."""
    out, records = Phi((rule,)).governor(SINGLE_PANDA)(RobotState(arms=(scene,)), action)
    return (list(out) if out is not None and out is not action else out), records


def dot(g: tuple[float, ...], a: list[float]) -> float:
    return sum(g[j] * a[j] for j in range(6))


def test_config_round_trips_and_bad_values_name_their_field() -> None:
    phi = Phi((StoppingDistance(decel=0.3, clearance=0.0, gain=2.0),))
    assert load_phi(phi.to_yaml()) == phi
    assert make("stopping_distance", decel=0.3) == StoppingDistance(decel=0.3)
    bad = (("decel", 0.0), ("decel", math.inf), ("clearance", -0.001), ("clearance", 0.06), ("gain", 0.0))
    bad += (("gain", 11.0), ("decel", math.nan), ("turn", -1.0), ("turn", 101.0), ("touch", -0.1), ("touch", 0.6))
    for field, value in bad:
        with pytest.raises(Invalid) as err:
            StoppingDistance(**{field: value})
        assert err.value.code is ErrorCode.INVALID and err.value.details["field"] == field


def test_the_stopping_speed_and_the_push_follow_the_formula() -> None:
    assert RULE.stopping_speed(0.003) == RULE.touch == RULE.stopping_speed(-0.01) == 0.04  # a touch is allowed
    assert RULE.stopping_speed(0.053) == pytest.approx(math.sqrt(2 * 0.2 * 0.05))
    assert RULE.push(0.053, 0.1) == 0.0  # slower than it can stop from
    assert RULE.push(0.001, 0.04) == 0.0  # the touch speed, however close
    assert RULE.push(0.003, 0.1) == pytest.approx(3 * (0.1 - 0.04))
    assert RULE.push(0.0, 5.0) == 1.0  # never more than a full action unit


def test_a_link_swinging_in_faster_than_it_can_stop_is_pushed_back_by_translation() -> None:
    """The h2-t1 forearm at 15.8 mm closing at 0.236 m/s (11.8 mm a step) with the action moving it away
    a little: not enough, so the translation part of its row gets ``g_t · a_t = −p``, p = gain · (v −
    v_stop); the turn is left as it was (later rules limit turning near a pair)."""
    g = (0.0, -1.2, 1.5, 0.9, 0.0, 0.6)
    action = [0.2, -0.2, -0.08, 0.0, 0.08, 0.08, 0.3]
    out, records = govern(arm(pair(0.0158, (0.0, 0.5, -1.0)), closing=(0.236,), rows=((0, g),)), action)
    p = RULE.push(0.0158, 0.236)
    assert p > 0.3 and dot((*g[:3], 0.0, 0.0, 0.0), out) == pytest.approx(-p, abs=1e-9)
    assert out[3:] == action[3:] and [r.constraint for r in records] == ["stopping_distance"]


def test_a_hand_drifting_onto_a_wall_with_a_zero_command_is_moved_off_it() -> None:
    """The h2-t1 hand at 6.6 mm from bin 1's wall, closing at 3.6 mm a step with nothing commanded."""
    out, _ = govern(arm(pair(0.0066, (0.0, -1.0, 0.0)), closing=(0.072,)), [0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.4])
    assert out[1] == pytest.approx(RULE.push(0.0066, 0.072)) and out[0] == 0.2 and out[2:] == [0.0] * 4 + [0.4]


def test_a_hand_point_off_the_site_is_steered_along_its_rigid_motion() -> None:
    """A fingertip 0.1 m from the site along x, closing down onto the floor: its row is
    ``(n, (r × n) · turn)``, so turning the hand helps lift it."""
    scene = arm((0.004, 0.0, 0.0, -1.0, 0.1, 0.0, 0.0, FIXED), closing=(0.2,))
    out, _ = govern(scene, [0.0] * 6 + [0.0])
    row = (0.0, 0.0, -1.0, 0.0, 0.1 * RULE.turn, 0.0)  # r × n = (0.1, 0, 0) × (0, 0, −1) = (0, 0.1, 0)
    assert dot(row, out) == pytest.approx(-RULE.push(0.004, 0.2)) and out[4] < 0.0 < out[2]


def test_what_is_slow_enough_moving_or_unmeasured_is_left_alone() -> None:
    action = [0.3, 0.0, -0.5, 0.0, 0.0, 0.0, 0.0]
    down = (0.0, 0.0, -1.0)
    for scene in (
        arm(pair(0.05, down), closing=(0.1,)),  # can still stop: v_stop(0.05) = 0.137
        arm(pair(0.01, down), closing=(-0.2,)),  # receding
        arm(pair(0.01, down, owner=LOOSE), closing=(0.5,)),  # a can: it moves too
        arm(pair(0.01, down, owner=0), closing=(0.5,)),  # another arm
        arm(pair(0.01, down)),  # no speeds measured
        arm(pair(0.01, down), closing=(0.5,), rows=((0, (0.05, 0.0, 0.0, 1.0, 0.0, 0.0)),)),  # translation too weak
    ):
        out, records = govern(scene, action)
        assert out is action and records == ()


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_speed_or_row_of_a_fixed_pair_is_rejected(bad: float) -> None:
    action = [0.0] * 7
    out, records = govern(arm(pair(0.01, (0.0, 0.0, -1.0)), closing=(bad,)), action)
    assert out is None and "not finite" in records[-1].reason
    row = ((0, (bad, 0.0, 1.0, 0.0, 0.0, 0.0)),)
    out, records = govern(arm(pair(0.01, (0.0, 0.0, -1.0)), closing=(0.5,), rows=row), action)
    assert out is None and "not finite" in records[-1].reason


UNIT = st.floats(-1.0, 1.0, allow_nan=False)
ACTION = st.lists(UNIT, min_size=7, max_size=7)


@settings(max_examples=300, deadline=None)
@given(
    dist=st.floats(-0.005, 0.11),
    speed=st.floats(-1.0, 2.0),
    n=st.tuples(UNIT, UNIT, UNIT).filter(lambda v: sum(x * x for x in v) > 0.01),
    g=st.none() | st.tuples(*[st.floats(-4.0, 4.0)] * 6),
    action=ACTION,
)
def test_one_pair_meets_its_target_and_only_what_its_row_moves_changes_within_bounds(
    dist: float, speed: float, n: tuple[float, float, float], g: tuple[float, ...] | None, action: list[float]
) -> None:
    rows = () if g is None else ((0, g),)
    out, _ = govern(arm(pair(dist, n), closing=(speed,), rows=rows), action)
    p = RULE.push(dist, speed)
    row = (*(pair(dist, n)[1:4] if g is None else g[:3]), 0.0, 0.0, 0.0)
    if p == 0.0 or sum(v * v for v in row) < MIN_ROW2:
        assert out is action
        return
    if out is action:  # already meets it
        assert dot(row, action) <= -p * (1 - 1e-12)
        return
    assert out[3:] == action[3:] and all(-1.0 <= v <= 1.0 for v in out)
    met = dot(row, out) <= -p + 1e-9
    # a component whose g_k² underflows to 0 cannot move the point: it is not asked to
    at_bounds = all(out[k] == (-1.0 if row[k] > 0 else 1.0) for k in range(6) if row[k] * row[k] != 0.0)
    assert met or at_bounds


@pytest.mark.slow
def test_the_sensed_closing_speed_is_how_fast_the_gap_shrinks() -> None:
    """On a live T1 episode, each fixed-scene pair's ``closing`` against the gap a short integration
    of the joint velocities later, pair by pair where the nearest points did not jump."""
    import mujoco

    from capevo.baselines.governed_env import GovernedTaskEnv

    env = GovernedTaskEnv("T1", perturbations=False)
    try:
        env.reset(seed=3)
        te = env.task_env
        m, d, sensor = te._model, te._data, te._proximity
        agree: list[bool] = []
        for _ in range(40):  # down and sideways, into the bin: pairs with the floor and the walls
            env.step(np.array([0.3, -0.2, -0.6, 0.1, 0.0, 0.2, 0.0]))
            # After mj_step the positions MuJoCo derived lag qpos by one 2 ms substep: derive them again.
            mujoco.mj_forward(m, d)
            near, _, closing = sensor.sense(0)
            qpos = d.qpos.copy()
            eps = 1e-4
            mujoco.mj_integratePos(m, d.qpos, d.qvel, eps)
            mujoco.mj_forward(m, d)
            later, _, _ = sensor.sense(0)
            d.qpos[:] = qpos
            mujoco.mj_forward(m, d)
            if len(later) != len(near):
                continue
            for before, after, speed in zip(near, later, closing, strict=True):
                same = max(abs(x - y) for x, y in zip(before[1:7], after[1:7], strict=True)) < 1e-3
                if before[7] != FIXED or before[0] <= 0.0 or not same:
                    continue  # not a fixed-scene pair, or not the same pair (the nearest points jumped)
                agree.append(abs((before[0] - after[0]) / eps - speed) <= 0.02 + 0.1 * abs(speed))
        # Two boxes' gap is a lower bound (see proximity), which need not move with the points.
        assert len(agree) > 20 and sum(agree) >= 0.9 * len(agree), (sum(agree), len(agree))
    finally:
        env.close()


STRIKES = [
    ("am_t1_forearm_fast_actions.json", "link5"),
    ("am_t1_hand_drift_actions.json", "hand"),
]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "part"), STRIKES)
def test_a_learned_policys_strike_is_prevented(name: str, part: str) -> None:
    """The AM baseline's T1 policies of ``results/h2-t1`` (seed-42 cell, seed 2000042006): at
    iteration 2 the forearm swung onto bin 1's rim at 10-14 mm a step with the executed actions
    moving it away; at iteration 3 the hand drifted onto the bin's wall with nothing commanded
    towards it. Their proposed actions, replayed open loop under the default Φ without
    stopping_distance, strike the bin again; under the default Φ no step is unsafe."""
    record = json.loads((DATA / name).read_text())
    full = Phi.for_task(task_spec("T1"))
    without = Phi(tuple(c for c in full.constraints if not isinstance(c, StoppingDistance)))
    struck = unsafe_reasons(record["actions"], record["seed"], phi=without)
    assert any(part in r for r in struck), struck
    assert unsafe_reasons(record["actions"], record["seed"], phi=full) == []
