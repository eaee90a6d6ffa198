"""Offline play data of the skill baselines (capevo.baselines.offline_data), collected in real robosuite episodes."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from capevo.baselines.am import DEMO_SEED_BASE
from capevo.baselines.base import HELD_OUT_SEED_BASE, MAX_CELL_SEED
from capevo.baselines.offline_data import (
    KINDS_RANDOM,
    KINDS_SCRIPTED,
    MAX_EPISODES,
    OFFLINE_SEED_BASE,
    collect,
    offline_data,
    offline_settings,
)
from capevo.errors import Conflict, Corrupt, ErrorCode, Invalid
from capevo.runtime.tasks import task_spec


def _settings(task: str = "T1", **kw: object) -> dict:
    base = {"episodes": 4, "seed": 5, "noise": 0.3, "phi": "task", "governance": True, "perturbations": True}
    base["horizon"] = 15
    base.update(kw)
    return offline_settings(task, **base)  # type: ignore[arg-type]


def _check_rows(data, task: str) -> None:
    spec = task_spec(task)
    n = data.env_steps
    assert len(data.obs) == len(data.action) == len(data.reward) == len(data.next_obs) == len(data.done) == n
    assert data.obs.dtype == data.action.dtype == data.next_obs.dtype == np.float32
    assert data.action.shape[1] == spec.action_layout.dim
    assert np.all(np.abs(data.action) <= 1.0)
    # invariant 1: episodes contiguous, in order, each ending with a done row, none longer than the horizon
    changes = np.flatnonzero(np.diff(data.episode)) + 1
    bounds = np.concatenate([[0], changes, [n]])
    assert list(data.episode[bounds[:-1]]) == list(range(data.episodes))
    for a, b in itertools.pairwise(bounds):
        assert data.done[b - 1] and not data.done[a : b - 1].any()
        assert b - a <= data.settings["horizon"]
        # consecutive rows chain: the next row's observation is this row's next observation
        assert np.array_equal(data.obs[a + 1 : b], data.next_obs[a : b - 1])


@pytest.mark.slow
def test_collects_reuses_and_refuses_other_settings(tmp_path: Path) -> None:
    settings = _settings()
    path = tmp_path / "offline.npz"
    data = offline_data(path, settings)
    assert not data.reused and path.exists()
    _check_rows(data, "T1")
    assert data.kinds == KINDS_SCRIPTED  # T1 has a reference: scripted, scripted, smooth, uniform
    assert f"{data.env_steps} env steps in 4 episodes" in data.describe()

    stamp = path.stat().st_mtime_ns
    again = offline_data(path, settings)  # invariant 3: a complete matching file is loaded, not recollected
    assert again.reused and path.stat().st_mtime_ns == stamp
    for name in ("obs", "action", "reward", "next_obs", "done", "episode"):
        assert np.array_equal(getattr(again, name), getattr(data, name))
    assert again.kinds == data.kinds and again.successes == data.successes

    with pytest.raises(Conflict) as err:
        offline_data(path, _settings(noise=0.1))
    assert err.value.code == ErrorCode.CONFLICT and "noise" in str(err.value)

    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(Corrupt) as err2:
        offline_data(bad, settings)
    assert err2.value.code == ErrorCode.CORRUPT


@pytest.mark.slow
def test_equal_settings_give_equal_data() -> None:
    settings = _settings(episodes=2, horizon=10)
    a, b = collect(settings), collect(settings)
    assert np.array_equal(a.obs, b.obs) and np.array_equal(a.action, b.action)
    assert np.array_equal(a.reward, b.reward)


@pytest.mark.slow
def test_a_task_without_a_reference_gets_random_play_of_its_action_dimension() -> None:
    data = collect(_settings("T6", episodes=2, horizon=10))
    _check_rows(data, "T6")
    assert data.kinds == KINDS_RANDOM
    assert data.action.shape[1] == 12
    # smooth play changes its action gradually, uniform play jumps
    smooth, uniform = (data.action[data.episode == j] for j in (0, 1))
    assert np.abs(np.diff(smooth, axis=0)).mean() < np.abs(np.diff(uniform, axis=0)).mean()


def test_offline_seeds_lie_between_demonstrations_and_held_out_seeds() -> None:
    # invariant 4
    assert DEMO_SEED_BASE + 1000 * MAX_CELL_SEED + 1000 <= OFFLINE_SEED_BASE
    assert OFFLINE_SEED_BASE + 1000 * MAX_CELL_SEED + MAX_EPISODES < HELD_OUT_SEED_BASE


@pytest.mark.parametrize(
    ("kw", "field"),
    [({"episodes": 0}, "options.offline_episodes"), ({"noise": -1.0}, "options.offline_noise"), ({"seed": -1}, "seed")],
)
def test_bad_settings_are_refused(kw: dict, field: str) -> None:
    with pytest.raises(Invalid) as err:
        _settings(**kw)
    assert err.value.code == ErrorCode.INVALID and err.value.details["field"] == field
