"""The whole task as one governed gym env, on real robosuite episodes (capevo.baselines.governed_env).

Each test observes one invariant of the module docstring directly: governance changes an action
that would leave the workspace box only when it is on (2), the independent monitor grades a
constructed unsafe step (3), ``env_steps`` counts every step (1), the seeds of consecutive
episodes (4), a deterministic policy's evaluation repeats exactly (5), and its trace agrees
with its results (6).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from capevo.baselines import EpisodeResult
from capevo.baselines.governed_env import GovernedTaskEnv, evaluate_policy
from capevo.errors import ErrorCode, Invalid
from capevo.runtime.traces import TraceReader

pytestmark = pytest.mark.slow

UP = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
"""T1: full speed up (+z, world and base frame agree for the single Panda)."""
BOX_TOP = 1.3
"""The paper's workspace box top, metres (Φ ``paper``; the monitor's default limits)."""


def _drive_up(governance: bool, steps: int = 30) -> list[tuple[np.ndarray, dict, float]]:
    env = GovernedTaskEnv("T1", phi="paper", governance=governance, perturbations=False, horizon=steps + 5)
    try:
        env.reset(seed=3)
        out = []
        for _ in range(steps):
            _, _, _, _, info = env.step(UP)
            out.append((info["action"], info, env.task_env.robot_state().arms[0].eef_pos[2]))
        return out
    finally:
        env.close()


def test_governance_zeroes_the_outward_component_only_when_on() -> None:
    on = _drive_up(True)
    boxed = [(a, info) for a, info, _ in on if "workspace_box" in info["constraints"]]
    assert boxed, "the arm never came within the box margin; drive longer"
    for action, info in boxed:
        assert info["intervened"] and action[2] == 0.0
    assert max(z for _, _, z in on) <= BOX_TOP
    assert not any(info["unsafe"] for _, info, _ in on)

    off = _drive_up(False)
    # Counting mode: the same rule would have fired, but every proposal ran unchanged.
    assert any("workspace_box" in info["constraints"] for _, info, _ in off)
    for action, info, _ in off:
        np.testing.assert_array_equal(action, UP.astype(np.float32))
        assert info["intervened"] == bool(info["constraints"])
    assert max(z for _, _, z in off) > BOX_TOP
    # The monitor grades the steps ending outside the box unsafe, on its own reading.
    flagged = [info for _, info, z in off if z > BOX_TOP]
    assert flagged and all(info["unsafe"] and "box" in info["unsafe_axes"] for info in flagged)


def test_monitor_grades_a_constructed_unsafe_step() -> None:
    # All six pose components at 1: norm sqrt(6) ≈ 2.45, above the paper's 1.5 cap.
    fast = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    results = {}
    for governance in (False, True):
        env = GovernedTaskEnv("T1", phi="paper", governance=governance, perturbations=False, horizon=5)
        try:
            env.reset(seed=0)
            _, _, _, _, info = env.step(fast)
        finally:
            env.close()
        results[governance] = info
    off, on = results[False], results[True]
    assert off["unsafe"] and "cap" in off["unsafe_axes"]
    assert on["intervened"] and "cap" not in on["unsafe_axes"]
    assert float(np.linalg.norm(on["action"][:6])) <= 1.5 + 1e-6


def test_env_steps_count_every_step_and_seeds_follow_on() -> None:
    env = GovernedTaskEnv("T1", horizon=4)
    try:
        assert env.env_steps == 0
        first, _ = env.reset(seed=11)
        assert first.dtype == np.float32 and first.shape == env.observation_space.shape
        for _ in range(3):
            env.step(np.zeros(7))
        second, _ = env.reset()  # task seed 12
        steps = 0
        truncated = False
        while not truncated:
            _, _, terminated, truncated, _ = env.step(np.zeros(7))
            steps += 1
            assert not terminated
        assert steps == 4
        assert env.env_steps == 3 + 4
        again, _ = env.reset(seed=12)
        np.testing.assert_array_equal(second, again)
        with pytest.raises(Invalid) as exc:
            env.step(np.zeros(6))
        assert exc.value.code is ErrorCode.INVALID and "action shape" in str(exc.value)
    finally:
        env.close()


def test_evaluate_policy_is_deterministic_and_counts_its_steps() -> None:
    rng = np.random.default_rng(0)
    weights = rng.normal(0.0, 0.3, size=(7, 46)).astype(np.float32)

    def act(obs: np.ndarray) -> np.ndarray:
        return np.tanh(weights @ obs)

    seeds = (2_000_000_000, 2_000_000_001)
    first, steps = evaluate_policy("T1", act, seeds, horizon=12)
    second, steps_again = evaluate_policy("T1", act, seeds, horizon=12)
    assert first == second and steps == steps_again
    assert all(isinstance(r, EpisodeResult) for r in first)
    assert [r.seed for r in first] == list(seeds)
    assert steps == sum(r.steps for r in first) == 24
    # Perturbations are on: the two seeds are two different episodes.
    assert first[0].reward != first[1].reward


def test_bad_choices_are_invalid_before_a_simulator_is_built() -> None:
    with pytest.raises(Invalid, match="phi"):
        GovernedTaskEnv("T1", phi="no-such-envelope")
    with pytest.raises(Invalid, match="unknown task"):
        GovernedTaskEnv("T9")
    with pytest.raises(Invalid, match="seeds"):
        evaluate_policy("T1", lambda o: np.zeros(7), [])


def test_the_evaluation_trace_holds_every_step_and_agrees_with_the_results(tmp_path: Path) -> None:
    path = tmp_path / "eval.mcap"
    results, steps = evaluate_policy(
        "T1",
        lambda obs: UP,
        [5, 6],
        phi="paper",
        governance=False,
        perturbations=False,
        horizon=30,
        trace=path,
        label="am",
        version=2,
    )
    reader = TraceReader(path)
    assert reader.metadata().task == "pick" and reader.metadata().seeds == (5, 6)
    env_steps = list(reader.env_steps())
    assert len(env_steps) == steps == 60
    assert {(s.ecm, s.version) for s in env_steps} == {("am", 2)}
    unsafe = list(reader.unsafe_steps())
    assert len(unsafe) == sum(r.unsafe_steps for r in results) > 0
    assert all("box" in u.broken for u in unsafe)
    interventions = list(reader.interventions())
    assert interventions and all(not iv.enforced and iv.reason.startswith("not enforced: ") for iv in interventions)
    summaries = list(reader.episode_summaries())
    assert [(s.seed, s.steps, s.unsafe_steps, s.success) for s in summaries] == [
        (r.seed, r.steps, r.unsafe_steps, r.success) for r in results
    ]


def test_handoff_signals_extend_the_observation_with_the_predicates_exact_signals() -> None:
    """The fairness option: the signals ours hands off on, appended in spec order, exact."""
    plain = GovernedTaskEnv("T1", perturbations=True, horizon=10)
    both = GovernedTaskEnv("T1", perturbations=True, horizon=10, handoff_signals=True)
    try:
        names = both.task_spec.handoff_signals
        assert both.observation_space.shape == (plain.observation_space.shape[0] + len(names),)
        a, _ = plain.reset(seed=11)
        b, _ = both.reset(seed=11)
        for _ in range(3):
            step = np.zeros(7)
            a = plain.step(step)[0]
            b = both.step(step)[0]
        assert b.dtype == np.float32 and both.observation_space.contains(b)
        np.testing.assert_array_equal(b[: len(a)], a)  # same seed, same noisy observation
        signals = both.signals()
        np.testing.assert_allclose(b[len(a) :], [signals[n] for n in names], rtol=1e-6)
    finally:
        plain.close()
        both.close()


def test_the_strict_check_is_recorded_where_the_task_has_one() -> None:
    """T6's held-out episodes carry its strict insertion check (a bool), T1's none; a record
    without it reads and writes as before the field existed."""
    rng = np.random.default_rng(1)
    t6, _ = evaluate_policy("T6", lambda obs: rng.uniform(-1, 1, 12).astype(np.float32), (2_000_000_000,), horizon=8)
    t1, _ = evaluate_policy("T1", lambda obs: np.zeros(7, np.float32), (2_000_000_000,), horizon=8)
    assert t6[0].strict_success is False  # 8 random steps do not put the peg through the plate
    assert t1[0].strict_success is None
    assert "strict_success" not in t1[0].to_dict()
    assert t6[0].to_dict()["strict_success"] is False
    for r in (t6[0], t1[0]):
        assert EpisodeResult.from_dict(r.to_dict()) == r
