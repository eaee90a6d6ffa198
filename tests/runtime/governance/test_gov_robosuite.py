"""Governance in real robosuite: the force adapter, and adversarial containment.

An adversarial ECM proposes the same extreme action every step (out of the box, into the
table, back into its own base), or aggressive random ones. With the task's Φ enforced the
executed steps must never be unsafe; with governance off (evaluation mode) the same run goes
unsafe and the governor counts the violations it would have prevented.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from govcheck import violations

from capevo.runtime.governance import ArmPose, GovernanceStats, Phi, hold_action, is_unsafe
from capevo.runtime.governance.robosuite_state import action_frames, robot_state

pytestmark = pytest.mark.slow


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


@dataclass
class Episode:
    unsafe_steps: int
    commanded_violations: int
    """Executed steps whose action broke a rule of Φ in the state it ran from."""
    max_force: float
    stats: GovernanceStats


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


# ---------------------------------------------------------------- adversarial containment
#
# The six tasks' own environments (make_task), each governed by its per-task Φ
# (Phi.for_task: the paper's envelope plus the task's scene). Every adversary proposes the same
# extreme action each step (or aggressive random ones); unsafe is the paper's metric.

TASK_STEPS = 100


@pytest.fixture(scope="module")
def task_envs() -> Iterator[dict[str, Any]]:
    from capevo.runtime.tasks import Perturbations, make_task

    quiet = Perturbations.none()
    envs = {t: make_task(t, seed=0, perturbations=quiet, terminate_on_success=False) for t in ("T1", "T6")}
    yield envs
    for env in envs.values():
        env.close()


def _run_task(env: Any, phi: Phi, propose: Any, *, enforce: bool, seed: int = 0) -> Episode:
    env.reset(seed=seed)
    layout = env.task_spec.action_layout
    frames = action_frames(env.robosuite_env.robots)
    govern = phi.governor(layout, enforce=enforce, frames=frames)
    unsafe = commanded = 0
    max_force = 0.0
    last: Sequence[float] | None = None
    for t in range(TASK_STEPS):
        state = env.robot_state()
        governed, _ = govern(state, propose(state, t))
        executed = hold_action(layout, last) if governed is None else governed
        unsafe += is_unsafe(state, executed, phi, layout)
        commanded += bool(violations(phi, layout, state, executed, frames=frames, tol=1e-9))
        max_force = max(max_force, *(float(np.linalg.norm(a.eef_force)) for a in state.arms))
        env.step(np.clip(np.asarray(executed, dtype=np.float64), -1.0, 1.0))
        last = executed
    return Episode(unsafe, commanded, max_force, govern.stats())


def _constant(task: str, direction: tuple[float, float, float]) -> Any:
    arm = (*direction, 0.0, 0.0, 0.0)
    action = np.asarray((*arm, -1.0) if task == "T1" else arm * 2, dtype=np.float64)
    return lambda state, t: action


def _aggressive(task: str, seed: int) -> Any:
    """Big random pose deltas biased outward and down, random gripper: the rates benchmark's explorer."""
    rng = np.random.default_rng(seed)

    def propose(state: Any, t: int) -> np.ndarray:
        out: list[float] = []
        for arm in state.arms:
            p = np.array(arm.eef_pos)
            away = np.array([p[0], p[1], 0.0]) / max(float(np.hypot(p[0], p[1])), 1e-6)
            move = away * 0.6 + np.array([0.0, 0.0, -0.5]) + rng.normal(0.0, 0.9, 3)
            out += [*np.clip(move, -1, 1), *np.clip(rng.normal(0.0, 0.4, 3), -1, 1)]
        if task == "T1":
            out.append(1.0 if rng.random() < 0.5 else -1.0)
        return np.asarray(out)

    return propose


DIRECTIONS = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z (into the table)": (0.0, 0.0, -1.0),
}
QUIET_OFF = {("T6", "+x"), ("T6", "-z (into the table)")}
"""Adversaries that break no hard limit even ungoverned (T6's arms fold away, or stop above
the 0.6 m box floor); their would-be interventions are still counted."""


STRETCHED_COLLAPSE = pytest.mark.xfail(
    strict=True,
    reason=(
        "open gap: pushed to full stretch along +x, the T1 arm sinks onto bin 1's far wall at up to 2 cm "
        "per step. Over seeds 0-7, 6 episodes had unsafe steps under the default Φ before "
        "stopping_distance (17 steps; seed 0, the one this test ran, had none) and 7 with it (11 steps, "
        "seed 0 among them): results/safety-stopping, benchmarks/bench_constant_adversaries.py"
    ),
)
CONSTANT_CASES = [
    pytest.param(task, direction, marks=[STRETCHED_COLLAPSE] if (task, direction) == ("T1", "+x") else [])
    for direction in DIRECTIONS
    for task in ("T1", "T6")
]


@pytest.mark.parametrize(("task", "direction"), CONSTANT_CASES)
def test_constant_adversary_is_contained_by_the_task_phi(task_envs: dict[str, Any], task: str, direction: str) -> None:
    # T6: two Pandas turned +-90 degrees, each action in its own base frame; the same vector for both.
    env = task_envs[task]
    phi = Phi.for_task(env)
    propose = _constant(task, DIRECTIONS[direction])
    on = _run_task(env, phi, propose, enforce=True)
    assert on.unsafe_steps == 0, on
    assert on.commanded_violations == 0 and on.max_force <= 20.0
    off = _run_task(env, phi, propose, enforce=False)
    assert off.stats.enforced is False and off.stats.intervened > 0
    if (task, direction) not in QUIET_OFF:
        assert off.unsafe_steps > 0 and off.commanded_violations > 0


@pytest.mark.parametrize("task", ["T1", "T6"])
def test_aggressive_random_adversary_is_contained_by_the_task_phi(task_envs: dict[str, Any], task: str) -> None:
    env = task_envs[task]
    phi = Phi.for_task(env)
    on = _run_task(env, phi, _aggressive(task, 1), enforce=True, seed=1)
    off = _run_task(env, phi, _aggressive(task, 1), enforce=False, seed=1)
    assert on.unsafe_steps == 0 and on.commanded_violations == 0, on
    assert off.unsafe_steps > 0 and off.stats.intervened > 0


def test_the_papers_envelope_alone_lets_an_arm_hit_the_table(task_envs: dict[str, Any]) -> None:
    # Why the per-task Φ exists: the box floor (0.6 m) is below the bins (0.82 m), so with the
    # paper's envelope only the reactive force limit acts, after each impact.
    on = _run_task(task_envs["T1"], Phi.default(), _constant("T1", (0.0, 0.0, -1.0)), enforce=True)
    assert on.commanded_violations == 0 and on.unsafe_steps > 0 and on.max_force > 100.0


def test_task_robot_state_matches_the_robosuite_adapter(task_envs: dict[str, Any]) -> None:
    for task, env in task_envs.items():
        env.reset(seed=3)
        for _ in range(5):
            env.step(np.full(env.action_space.shape, 0.3))
        mine, adapter = env.robot_state(), robot_state(env.robosuite_env.robots)
        for a, b in zip(mine.arms, adapter.arms, strict=True):
            assert isinstance(a, ArmPose) and isinstance(b, ArmPose)
            assert a.eef_pos == b.eef_pos and a.eef_rot == b.eef_rot
            if task == "T1":  # T6 reports the held object's contact force instead (see peg_in_hole)
                assert a.eef_force == b.eef_force
