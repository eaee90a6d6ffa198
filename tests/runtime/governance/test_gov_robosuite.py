"""Adversarial containment in real robosuite: an ECM that always drives out of the envelope.

Each adversary proposes the same extreme action every step. With governance on, the
executed step must never be unsafe; with governance off (evaluation mode) the same run
must go unsafe and the governor must have counted the violations it would have prevented.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from govcheck import violations

from capevo.runtime.governance import TWO_ARM_NO_GRIPPER, GovernanceStats, Phi, hold_action, is_unsafe, load_phi
from capevo.runtime.governance.robosuite_state import action_frames, robot_state
from capevo.runtime.state import SINGLE_PANDA, ActionLayout

pytestmark = pytest.mark.slow

STEPS = 120


def _make_env(task: str, robots: str | list[str]) -> Any:
    import robosuite as suite
    from robosuite.controllers import load_composite_controller_config

    return suite.make(
        task,
        robots=robots,
        controller_configs=load_composite_controller_config(controller="BASIC", robot="Panda"),
        has_renderer=False,
        has_offscreen_renderer=False,
        use_camera_obs=False,
        ignore_done=True,
        horizon=10_000,
        control_freq=20,
        hard_reset=False,
    )


@pytest.fixture(scope="module")
def lift() -> Iterator[Any]:
    env = _make_env("Lift", "Panda")
    yield env
    env.close()


@pytest.fixture(scope="module")
def peg_in_hole() -> Iterator[Any]:
    env = _make_env("TwoArmPegInHole", ["Panda", "Panda"])
    yield env
    env.close()


@dataclass
class Episode:
    unsafe_steps: int
    commanded_violations: int
    """Executed steps whose action broke a rule of Φ in the state it ran from."""
    max_force: float
    stats: GovernanceStats


def _run(env: Any, phi: Phi, layout: ActionLayout, adversary: Sequence[float], *, enforce: bool) -> Episode:
    obs = env.reset()
    frames = action_frames(env.robots)
    govern = phi.governor(layout, enforce=enforce, frames=frames)
    proposed = np.asarray(adversary, dtype=np.float64)
    unsafe = commanded = 0
    max_force = 0.0
    last: Sequence[float] | None = None
    for _ in range(STEPS):
        state = robot_state(env.robots)
        # The adapter reads the same end-effector sites robosuite reports, robot by robot.
        for i, arm in enumerate(state.arms):
            assert np.allclose(arm.eef_pos, obs[f"robot{i}_eef_pos"])
        governed, _ = govern(state, proposed)
        executed = hold_action(layout, last) if governed is None else governed
        unsafe += is_unsafe(state, executed, phi, layout)
        commanded += bool(violations(phi, layout, state, executed, frames=frames))
        max_force = max(max_force, *(float(np.linalg.norm(a.eef_force)) for a in state.arms))
        obs, _, _, _ = env.step(np.asarray(executed, dtype=np.float64))
        last = executed
    return Episode(unsafe, commanded, max_force, govern.stats())


def test_force_adapter_reads_no_contact_in_free_space_and_the_table_pushing_up(lift: Any) -> None:
    lift.reset()
    for _ in range(10):
        lift.step(np.zeros(7))
    fx, fy, fz = robot_state(lift.robots).arms[0].eef_force
    assert abs(fx) < 2.0 and abs(fy) < 2.0 and abs(fz) < 2.0  # the hand's own weight is removed
    peak = 0.0
    for _ in range(40):
        lift.step(np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0]))
        peak = max(peak, robot_state(lift.robots).arms[0].eef_force[2])
    assert peak > 20.0  # pressed on the table, the contact force points up (+z)


def test_adapter_follows_the_new_simulation_after_a_hard_reset(lift: Any) -> None:
    lift.hard_reset = True
    try:
        before = lift.sim
        obs = lift.reset()
        assert lift.sim is not before  # robosuite rebuilt the simulation
        for _ in range(10):
            obs, _, _, _ = lift.step(np.zeros(7))
        arm = robot_state(lift.robots).arms[0]
        assert np.allclose(arm.eef_pos, obs["robot0_eef_pos"])
        assert max(abs(f) for f in arm.eef_force) < 2.0
    finally:
        lift.hard_reset = False


ALONG = {"+z": (0, 0, 1), "+y": (0, 1, 0), "-y": (0, -1, 0)}


@pytest.mark.parametrize("direction", list(ALONG))
def test_adversary_driving_out_of_the_box_is_contained(lift: Any, direction: str) -> None:
    adversary = (*ALONG[direction], 0.0, 0.0, 0.0, -1.0)
    on = _run(lift, Phi.default(), SINGLE_PANDA, adversary, enforce=True)
    off = _run(lift, Phi.default(), SINGLE_PANDA, adversary, enforce=False)
    assert on.unsafe_steps == 0 and on.commanded_violations == 0
    assert on.stats.by_constraint.get("workspace_box", 0) > 0
    assert off.unsafe_steps > 0 and off.commanded_violations > 0
    assert off.stats.enforced is False and off.stats.intervened > 0


def test_adversary_pushing_into_the_table(lift: Any) -> None:
    adversary = (0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)
    # With the default Φ the box floor (0.6 m) is below Lift's table top (0.8 m), so only the
    # force limit acts. It is reactive: the first impact and each re-approach after a release
    # exceed 20 N before the governor sees a force, so steps can be unsafe even though
    # governance never lets the arm keep pushing into the contact.
    on = _run(lift, Phi.default(), SINGLE_PANDA, adversary, enforce=True)
    off = _run(lift, Phi.default(), SINGLE_PANDA, adversary, enforce=False)
    assert on.commanded_violations == 0
    assert on.stats.by_constraint.get("contact_force", 0) > 0
    assert off.commanded_violations > 0 and off.stats.by_constraint.get("contact_force", 0) > 0
    assert off.unsafe_steps > 0
    assert on.unsafe_steps < off.unsafe_steps
    # A Φ whose box floor sits above the table (plus margin) keeps the hand off it entirely.
    above_table = load_phi(
        """
        constraints:
          - {kind: workspace_box, low: [-0.6, -0.6, 0.85], high: [0.6, 0.6, 1.3]}
          - {kind: contact_force}
          - {kind: velocity_cap}
        """
    )
    on = _run(lift, above_table, SINGLE_PANDA, adversary, enforce=True)
    off = _run(lift, above_table, SINGLE_PANDA, adversary, enforce=False)
    assert on.unsafe_steps == 0 and on.commanded_violations == 0 and on.max_force < 20.0
    assert off.unsafe_steps > 0 and off.stats.intervened > 0


def test_two_arm_adversary_is_contained_in_each_robots_base_frame(peg_in_hole: Any) -> None:
    # TwoArmPegInHole mounts the Pandas turned ±90° about z; OSC deltas are in each base frame.
    adversary = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0) * 2
    frames = action_frames(peg_in_hole.robots)
    assert frames[0] == (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    on = _run(peg_in_hole, Phi.default(), TWO_ARM_NO_GRIPPER, adversary, enforce=True)
    off = _run(peg_in_hole, Phi.default(), TWO_ARM_NO_GRIPPER, adversary, enforce=False)
    assert on.unsafe_steps == 0 and on.commanded_violations == 0
    assert off.unsafe_steps > 0 and off.stats.intervened > 0
    sideways = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0) * 2  # base +y is world -x for robot 0, world +x for robot 1
    on = _run(peg_in_hole, Phi.default(), TWO_ARM_NO_GRIPPER, sideways, enforce=True)
    off = _run(peg_in_hole, Phi.default(), TWO_ARM_NO_GRIPPER, sideways, enforce=False)
    assert on.unsafe_steps == 0 and on.commanded_violations == 0
    assert off.unsafe_steps > 0
