"""One forced observable refresh in dependency order (capevo.runtime.tasks.observables invariants
1-4), and that TaskEnv's per-step observations equal robosuite's two-pass refresh exactly."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest

from capevo.runtime.tasks import make_task
from capevo.runtime.tasks.observables import plan_observables


class _Observable:
    """Just what planning reads of a robosuite Observable: a name, flags and a sensor."""

    def __init__(self, name: str, reads: tuple[str, ...], *, active: bool = True) -> None:
        self.name, self._reads, self._active = name, reads, active

    def is_enabled(self) -> bool:
        return True

    def is_active(self) -> bool:
        return self._active

    def _sensor(self, cache: dict[str, Any]) -> float:
        return sum(cache[k] for k in self._reads if k in cache) + 1.0


class _Env:
    def __init__(self, *observables: _Observable) -> None:
        self._observables = {o.name: o for o in observables}
        self._obs_cache = {o.name: 1.0 for o in observables}


def test_readers_come_after_their_producers_ties_keep_order() -> None:
    # Invariants 1 and 2 on a hand-made graph: c reads a and the inactive d, which comes last.
    env = _Env(
        _Observable("c", ("a", "d")),
        _Observable("a", ()),
        _Observable("b", ()),
        _Observable("d", ("b",), active=False),
    )
    plan = plan_observables(env)
    assert plan is not None
    assert [o.name for o in plan.order] == ["a", "b", "d", "c"]
    assert [name for name, _ in plan.active] == ["c", "a", "b"]


def test_a_cycle_gives_no_plan() -> None:
    # Invariant 3.
    assert plan_observables(_Env(_Observable("a", ("b",)), _Observable("b", ("a",)))) is None


@pytest.fixture(scope="module", params=["T1", "T6"])
def env(request: pytest.FixtureRequest) -> Any:
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    e = make_task(request.param, horizon=40)
    yield e
    e.close()


@pytest.mark.slow
def test_robosuite_plan_orders_relative_poses_after_their_inputs(env: Any) -> None:
    env.reset(seed=1)
    rs = env.robosuite_env
    before = dict(rs._obs_cache)
    plan = plan_observables(rs)
    assert plan is not None
    # Invariant 4: planning leaves robosuite's cache alone.
    assert rs._obs_cache.keys() == before.keys()
    assert all(np.array_equal(rs._obs_cache[k], v) for k, v in before.items())
    # Invariant 2: robosuite's own observation keys, in its order, without the -state arrays.
    assert [n for n, _ in plan.active] == [k for k in rs._get_observations() if not k.endswith("-state")]
    order = [o.name for o in plan.order]
    if env.task_spec.id == "T1":
        assert order.index("Can_pos") < order.index("Can_to_robot0_eef_pos")
        assert order.index("Can_quat") < order.index("Can_to_robot0_eef_quat")
        assert order.index("world_pose_in_gripper") < order.index("Can_to_robot0_eef_pos")
    else:
        assert order.index("angle") < order.index("t") and order.index("hole_pos") < order.index("peg_to_hole")


@pytest.mark.slow
def test_step_observations_equal_the_two_pass_refresh(env: Any) -> None:
    # TaskEnv steps with one planned pass and no in-step sampling; recompute the old way.
    env.reset(seed=2)
    rng = np.random.default_rng(5)
    for _ in range(15):
        env.step(rng.uniform(-0.8, 0.8, env.action_space.shape))
        clean = env.clean_obs_dict
        twice = env._raw_observations()
        assert clean.keys() == {k for k in twice if not k.endswith("-state")}
        for k, v in clean.items():
            assert np.array_equal(v, np.asarray(twice[k], dtype=np.float32)), k
