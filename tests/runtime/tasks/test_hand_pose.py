"""The hand's orientation helpers shared by the scripted references and the built-in skills."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from capevo.learner.skills import seed_source
from capevo.runtime.tasks.hand_pose import (
    DOWN,
    HAND_HALF_LENGTH,
    clear_of_walls,
    down_at,
    held_down,
    rot_error,
    yaw_of,
)

BIN = (-0.09, 0.29, -0.49, -0.01)
yaws = st.floats(-math.pi / 2, math.pi / 2, allow_nan=False)


def same_rotation(a, b) -> bool:
    return bool(np.linalg.norm(rot_error(a, b)) < 1e-9)


@given(yaws)
def test_a_held_yaw_is_kept(yaw: float) -> None:
    assert same_rotation(held_down(down_at(yaw)), down_at(yaw))
    assert math.isclose(math.cos(yaw_of(down_at(yaw)) - yaw), 1.0, abs_tol=1e-12)


def test_rot_error_is_zero_on_target_and_a_quarter_turn_about_z_otherwise() -> None:
    assert not np.any(rot_error(DOWN, DOWN))
    turn = rot_error(DOWN, down_at(math.pi / 2))
    assert np.allclose(np.abs(turn), [0.0, 0.0, math.pi / 2])


def test_no_walls_points_straight_down() -> None:
    assert clear_of_walls((0.1, -0.25, 0.86), down_at(0.7), None) == DOWN


def test_near_a_wall_running_along_x_the_hand_turns_parallel_to_it() -> None:
    # 8 cm from the wall at y = -0.01, in the middle of the bin in x: the 0.21 m hand must lie along x.
    target = clear_of_walls((0.1, -0.09, 0.86), DOWN, BIN)
    assert same_rotation(target, down_at(math.pi / 2))
    # ...and near a wall running along y it stays (fingers along y, long side parallel to that wall).
    assert same_rotation(clear_of_walls((-0.01, -0.25, 0.86), DOWN, BIN), DOWN)


@given(st.floats(-0.05, 0.25), st.floats(-0.45, -0.05), yaws)
def test_the_chosen_yaw_clears_the_walls_at_least_as_well_as_the_current_one(x: float, y: float, yaw: float) -> None:
    def clearance(q) -> float:
        t = yaw_of(q)
        ax, ay = abs(math.sin(t)), abs(math.cos(t))
        to_x = min(x - BIN[0], BIN[1] - x)
        to_y = min(y - BIN[2], BIN[3] - y)
        return min(to_x - (HAND_HALF_LENGTH * ax + 0.035 * ay), to_y - (HAND_HALF_LENGTH * ay + 0.035 * ax))

    current = down_at(yaw)
    assert clearance(clear_of_walls((x, y, 0.86), current, BIN)) >= clearance(current) - 1e-12


def test_the_skills_carry_this_module_verbatim() -> None:
    import inspect

    from capevo.runtime.tasks import hand_pose

    body = inspect.getsource(hand_pose).split("import numpy as np\n", 1)[1]
    assert body in seed_source("pick", "pick.reach")
