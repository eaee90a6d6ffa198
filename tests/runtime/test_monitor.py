"""DegradationMonitor against a real LocalRegistry: versions promoted by the gate, live outcomes fed in.

Invariants of :mod:`capevo.runtime.monitor`: nothing before ``min_episodes`` (1),
``expected_active`` guards every rollback (2), non-active versions never count (3), one
rollback per watch (4), no reference -> not monitored (5).
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from runtime_support import REACH, FakeEvaluator, skill_spec
from scipy import stats as sps

from capevo.errors import ErrorCode, IllegalTransition, Invalid, Unavailable
from capevo.records import Action, State
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate import Gate, GateConfig, SeedPlan
from capevo.runtime.gate_stats import wilson_interval
from capevo.runtime.monitor import (
    DegradationMonitor,
    MonitorAction,
    MonitorConfig,
    binomial,
    make_signal,
    wilson_upper,
)

NAME = "pick.reach"
LIFT = "pick.lift"
SEEDS = SeedPlan().gate(10)
GATE_CFG = GateConfig(min_n=8, delta=0.3, max_slowdown=1.1)
MON_CFG = MonitorConfig(window=20, min_episodes=8, margin=0.1)


def live(version: int, success: bool, *, name: str = NAME, seed: int = 0, extra: dict | None = None) -> EpisodeOutcome:
    return EpisodeOutcome(
        seed=SeedPlan().live(1, offset=seed)[0],
        success=success,
        reward=1.0,
        steps=50,
        duration_s=1.0,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={name: version, **(extra or {})},
    )


def publish(registry: LocalRegistry, name: str = NAME, *, promote: bool = False, text: str = "") -> int:
    record = registry.publish(name, (REACH + text).encode(), skill_spec(name, inputs=()))
    if promote:
        registry.promote(name, record.version, reason="setup")
    return record.version


def gate_in(registry: LocalRegistry, name: str = NAME, *, active_rate_even: bool = True) -> tuple[int, int]:
    """v0 active (succeeds on even seeds: 5/10 at the gate), v1 gated and promoted (10/10)."""
    v0 = publish(registry, name, promote=True)
    v1 = publish(registry, name, text="# better")
    fake = FakeEvaluator({(name, v0): lambda s: (s % 2 == 0, 1.0, 50), (name, v1): lambda s: (True, 1.0, 50)})
    assert Gate(registry, fake, GATE_CFG).run(name, v1, task="T1", seeds=SEEDS).promoted
    return v0, v1


@pytest.fixture
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    reg = LocalRegistry(tmp_path / "registry", actor="tester")
    yield reg
    reg.close()


def test_a_degraded_version_is_rolled_back_with_the_numbers_in_the_audit_history(registry: LocalRegistry) -> None:
    monitor = DegradationMonitor(registry, config=MON_CFG)
    registry.add_listener(monitor)
    v0, v1 = gate_in(registry)
    (status,) = [s for s in monitor.status() if s.version == v1]
    assert status.state == "watching" and status.reference is not None
    assert status.reference.value == 0.5 and "v0's success at gate (5/10, replaced)" in status.reference.source

    for i in range(7):
        assert monitor.observe(live(v1, False, seed=i)) == []  # invariant 1: not before min_episodes
    (action,) = monitor.observe(live(v1, False, seed=7))

    assert action.rolled_back and action.version == v1 and action.to_version == v0
    assert (action.n, action.successes, action.live_rate) == (8, 0, 0.0)
    assert action.reference == 0.5 and action.threshold == pytest.approx(0.4)
    assert action.statistic == pytest.approx(wilson_interval(0, 8, alpha=0.05).high)
    assert action.statistic == pytest.approx(sps.binomtest(0, 8).proportion_ci(0.9, method="wilson").high)
    assert registry.get_version(NAME).version == v0
    assert registry.get_version(NAME, v1).state is State.SUPERSEDED
    last = registry.history(NAME)[-1]
    assert last.action is Action.ROLLBACK and last.actor == "monitor"
    assert (last.from_version, last.to_version) == (v1, v0)
    for fragment in (
        "roll back pick.reach v1",
        "live success 0/8 = 0.00",
        "Wilson upper bound 0.253",
        "threshold 0.400",
    ):
        assert fragment in last.reason, last.reason
    assert last.reason == action.reason
    # Invariant 4: later outcomes of the rolled-back version change nothing.
    assert monitor.observe_many([live(v1, False, seed=20 + i) for i in range(10)]) == []
    assert monitor.actions == [action]
    assert registry.verify().ok


def test_a_healthy_version_stays(registry: LocalRegistry) -> None:
    monitor = DegradationMonitor(registry, config=MON_CFG)
    _, v1 = gate_in(registry)  # not a listener: observe() finds the active version itself
    outcomes = [live(v1, i % 2 == 0, seed=i) for i in range(40)]  # 50% live: upper bound stays above 0.4
    assert monitor.observe_many(outcomes) == []
    assert registry.get_version(NAME).version == v1
    (status,) = monitor.status()
    assert (status.state, status.n, status.successes) == ("watching", 20, 10)


def test_the_window_slides_and_the_rollback_comes_when_scipy_says_so(registry: LocalRegistry) -> None:
    cfg = MonitorConfig(window=10, min_episodes=8, margin=0.1, reference="gate_rate")
    monitor = DegradationMonitor(registry, config=cfg)
    _, v1 = gate_in(registry)  # gate rate 1.0 -> threshold 0.9
    feed = [True] * 10 + [False] * 10
    window: list[bool] = []
    expected = None
    for i, ok in enumerate(feed):
        window = [*window, ok][-10:]
        upper = sps.binomtest(sum(window), len(window)).proportion_ci(0.9, method="wilson").high
        if len(window) >= 8 and upper < 0.9:
            expected = i
            break
    assert expected is not None and expected > 10
    fired_at = None
    for i, ok in enumerate(feed):
        if monitor.observe(live(v1, ok, seed=i)):
            fired_at = i
            break
    assert fired_at == expected


def test_outcomes_of_versions_that_are_not_active_never_count(registry: LocalRegistry) -> None:
    monitor = DegradationMonitor(registry, config=MON_CFG)
    _, v1 = gate_in(registry)
    v2 = publish(registry, text="# a candidate being evaluated")
    assert monitor.observe_many([live(v2, False, seed=i) for i in range(20)]) == []
    assert [(s.version, s.n) for s in monitor.status()] == []
    assert registry.get_version(NAME).version == v1


def test_a_version_without_gate_evidence_is_not_monitored_unless_a_fallback_is_set(tmp_path: Path) -> None:
    for fallback, expect in ((None, False), (0.9, True)):
        reg = LocalRegistry(tmp_path / f"r{fallback}", actor="tester")
        v0 = publish(reg, promote=True)
        v1 = publish(reg, promote=True, text="# promoted by hand")
        cfg = MonitorConfig(window=20, min_episodes=8, margin=0.1, fallback_reference=fallback)
        monitor = DegradationMonitor(reg, config=cfg)
        actions = monitor.observe_many([live(v1, False, seed=i) for i in range(10)])
        assert bool(actions) is expect
        assert monitor.status()[0].state == ("rolled_back" if expect else "unmonitored")
        assert reg.get_version(NAME).version == (v0 if expect else v1)
        reg.close()


def test_losing_a_race_reports_instead_of_rolling_back_the_wrong_version(registry: LocalRegistry) -> None:
    monitor = DegradationMonitor(registry, config=MON_CFG)
    registry.add_listener(monitor)
    _, v1 = gate_in(registry)
    v2 = publish(registry, text="# someone promotes this elsewhere")
    other = LocalRegistry(registry.root, actor="elsewhere")  # its mutations do not reach our listener
    other.promote(NAME, v2, expected_active=v1, reason="operator")
    other.close()
    # A stale runtime still reports v1 episodes.
    actions = monitor.observe_many([live(v1, False, seed=i) for i in range(8)])
    (action,) = actions
    assert not action.rolled_back and action.to_version is None
    assert action.error is not None and "expected active v1" in action.error and "[conflict]" in action.error
    assert registry.get_version(NAME).version == v2
    assert [s.state for s in monitor.status() if s.version == v1] == ["stopped"]


def test_nothing_to_roll_back_to_is_reported(registry: LocalRegistry) -> None:
    monitor = DegradationMonitor(registry, config=MonitorConfig(window=20, min_episodes=8, margin=0.0))
    v0 = publish(registry)
    fake = FakeEvaluator({(NAME, v0): lambda s: (True, 1.0, 50)})
    assert Gate(registry, fake, GATE_CFG).run(NAME, v0, task="T1", seeds=SEEDS).promoted  # first version
    (action,) = monitor.observe_many([live(v0, False, seed=i) for i in range(8)])
    assert not action.rolled_back and action.error is not None and "[not_found]" in action.error
    # First promotion: the reference is the version's own lower bound at the gate.
    assert action.reference == pytest.approx(wilson_interval(10, 10, alpha=0.05).low)
    assert registry.get_version(NAME).version == v0


def test_the_latest_change_takes_the_blame_unless_attribution_is_all(tmp_path: Path) -> None:
    for attribution, rolled in (("latest", {LIFT}), ("all", {NAME, LIFT})):
        reg = LocalRegistry(tmp_path / attribution, actor="tester")
        cfg = MonitorConfig(window=20, min_episodes=8, margin=0.1, attribution=attribution)
        monitor = DegradationMonitor(reg, config=cfg)
        reg.add_listener(monitor)
        _, reach = gate_in(reg, NAME)
        _, lift = gate_in(reg, LIFT)
        actions = monitor.observe_many([live(reach, False, seed=i, extra={LIFT: lift}) for i in range(8)])
        assert {a.name for a in actions if a.rolled_back} == rolled
        reg.close()


def test_signals_are_registered_and_match_scipy() -> None:
    assert make_signal("wilson_upper") is wilson_upper and make_signal("binomial") is binomial
    with pytest.raises(Invalid) as e:
        make_signal("cusum")
    assert e.value.code is ErrorCode.INVALID
    assert e.value.message == "unknown degradation signal 'cusum'; valid: binomial, wilson_upper"
    got = binomial(2, 12, 0.6, 0.05)
    assert got.statistic == pytest.approx(sps.binomtest(2, 12, 0.6, alternative="less").pvalue)
    assert got.fired
    assert not binomial(0, 12, 0.0, 0.05).fired


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"window": 0}, "window must be an integer >= 1"),
        ({"window": 5, "min_episodes": 6}, "min_episodes (6) cannot exceed window (5)"),
        ({"margin": 1.5}, "margin must be a number in [0, 1]"),
        ({"signal": "cusum"}, "unknown degradation signal 'cusum'"),
        ({"reference": "best"}, "unknown reference 'best'; valid: previous, gate_lower, gate_rate"),
        ({"attribution": "first"}, "unknown attribution 'first'; valid: latest, all"),
        ({"alpha": 0.0}, "alpha must be a number in (0, 0.5)"),
    ],
)
def test_bad_monitor_config_is_invalid(kwargs: dict, fragment: str) -> None:
    with pytest.raises(Invalid) as e:
        MonitorConfig(**kwargs)
    assert fragment in e.value.message


def test_watch_refuses_a_version_that_is_not_active(registry: LocalRegistry) -> None:
    monitor = DegradationMonitor(registry, config=MON_CFG)
    v0, v1 = gate_in(registry)
    assert monitor.watch(NAME).version == v1
    with pytest.raises(IllegalTransition) as e:
        monitor.watch(NAME, v0)
    assert e.value.code is ErrorCode.ILLEGAL_TRANSITION
    assert e.value.message == "pick.reach v0 is superseded; only the active version can be watched"


@given(st.lists(st.booleans(), min_size=1, max_size=30), st.integers(1, 15), st.integers(0, 15))
@settings(max_examples=25, deadline=None)
def test_never_rolls_back_before_min_episodes(feed: list[bool], min_episodes: int, extra: int) -> None:
    with tempfile.TemporaryDirectory() as d:
        reg = LocalRegistry(Path(d) / "registry", actor="tester")
        try:
            cfg = MonitorConfig(window=min_episodes + extra, min_episodes=min_episodes, margin=0.0)
            monitor = DegradationMonitor(reg, config=cfg)
            _, v1 = gate_in(reg)
            for i, ok in enumerate(feed):
                actions = monitor.observe(live(v1, ok, seed=i))
                if actions:
                    assert i + 1 >= min_episodes
                    assert len(actions) == 1 and actions[0].n >= min_episodes
                    break
        finally:
            reg.close()


# --- confirmation on the same seeds (invariant 6) -------------------------------------------


def replay_with(behaviours: dict[int, bool], calls: list[tuple[dict[str, int], tuple[int, ...]]]):
    """A replay that runs ``NAME`` at version v with success ``behaviours[v]`` on every seed (50 steps)."""

    def replay(versions, seeds):
        calls.append((dict(versions), tuple(seeds)))
        return [
            EpisodeOutcome(
                seed=int(s),
                success=behaviours[versions[NAME]],
                reward=1.0,
                steps=50,
                duration_s=0.1,
                interventions=0,
                unsafe_steps=0,
                ecm_failures=0,
                capability_set=dict(versions),
            )
            for s in seeds
        ]

    return replay


def screened(registry: LocalRegistry, replaced_succeeds: bool):
    """v1 promoted over v0, then 8 failed live episodes of v1 (the screen fires); v0 replays with
    ``replaced_succeeds`` on every seed. Returns (monitor, replay calls, v0, v1, window, action)."""
    calls: list = []
    replay = replay_with({0: replaced_succeeds, 1: False}, calls)
    monitor = DegradationMonitor(registry, config=MON_CFG, replay=replay)
    registry.add_listener(monitor)
    v0, v1 = gate_in(registry)
    window = [live(v1, False, seed=i) for i in range(8)]
    (action,) = monitor.observe_many(window)
    return monitor, calls, v0, v1, window, action


def test_a_drop_the_replaced_version_shows_on_the_same_seeds_is_not_rolled_back(registry: LocalRegistry) -> None:
    # Issue 19's T1 il run on seed plan 1: one hard block of live seeds, hard for both versions.
    monitor, calls, v0, v1, window, action = screened(registry, replaced_succeeds=False)

    assert not action.rolled_back and action.error is None and not action.confirmed
    assert action.statistic < action.threshold == pytest.approx(0.4)  # the unpaired screen fired
    assert action.replayed == {
        "version": v0,
        "n": 8,
        "successes": 0,
        "steps": 400,
        "statistic": pytest.approx(wilson_interval(0, 8, alpha=0.05).high),
        "threshold": pytest.approx(-0.1),
        "confirmed": False,
    }
    assert calls == [({NAME: v0}, tuple(o.seed for o in window))]
    assert "keep pick.reach v1" in action.reason and "v0 replayed on the same 8 seeds (0/8, replaced)" in action.reason
    assert registry.get_version(NAME).version == v1
    assert all(e.action is not Action.ROLLBACK for e in registry.history(NAME))
    (status,) = [s for s in monitor.status() if s.version == v1]
    assert (status.state, status.n) == ("watching", 0)  # the window starts again
    assert monitor.observe_many([live(v1, False, seed=10 + i) for i in range(7)]) == []  # invariant 1 again
    assert len(calls) == 1


def test_a_drop_confirmed_on_the_same_seeds_is_rolled_back(registry: LocalRegistry) -> None:
    _, calls, v0, _, window, action = screened(registry, replaced_succeeds=True)

    assert action.rolled_back and action.confirmed and action.to_version == v0
    assert action.replayed is not None and action.replayed["successes"] == 8 and action.replayed["confirmed"]
    assert action.replayed["threshold"] == pytest.approx(0.9)
    assert calls == [({NAME: v0}, tuple(o.seed for o in window))]
    last = registry.history(NAME)[-1]
    assert last.action is Action.ROLLBACK and "confirmed against v0 replayed on the same 8 seeds (8/8" in last.reason
    assert isinstance(action, MonitorAction) and action.to_dict()["replayed"]["version"] == v0


def test_the_replay_swaps_only_the_watched_ecm(tmp_path: Path) -> None:
    reg = LocalRegistry(tmp_path / "r", actor="tester")
    calls: list = []
    monitor = DegradationMonitor(reg, config=MON_CFG, replay=replay_with({0: False, 1: False}, calls))
    reg.add_listener(monitor)
    _, reach = gate_in(reg, NAME)
    lift0, lift = gate_in(reg, LIFT)
    (action,) = monitor.observe_many([live(reach, False, seed=i, extra={LIFT: lift}) for i in range(8)])
    assert action.name == LIFT and not action.rolled_back  # latest change screened, then kept
    assert [c[0] for c in calls] == [{NAME: reach, LIFT: lift0}]
    reg.close()


def test_a_first_promotion_is_judged_without_a_replay(registry: LocalRegistry) -> None:
    calls: list = []
    monitor = DegradationMonitor(
        registry, config=MonitorConfig(window=20, min_episodes=8, margin=0.0), replay=replay_with({}, calls)
    )
    v0 = publish(registry)
    fake = FakeEvaluator({(NAME, v0): lambda s: (True, 1.0, 50)})
    assert Gate(registry, fake, GATE_CFG).run(NAME, v0, task="T1", seeds=SEEDS).promoted
    (action,) = monitor.observe_many([live(v0, False, seed=i) for i in range(8)])
    assert action.replayed is None and action.confirmed and calls == []  # nothing it replaced


def test_a_failed_replay_keeps_the_window_and_asks_again(registry: LocalRegistry) -> None:
    calls: list = []
    good = replay_with({0: True, 1: False}, calls)

    def down(versions, seeds):
        raise Unavailable("no runtime worker")

    monitor = DegradationMonitor(registry, config=MON_CFG, replay=down)
    registry.add_listener(monitor)
    v0, v1 = gate_in(registry)
    assert monitor.observe_many([live(v1, False, seed=i) for i in range(7)]) == []
    with pytest.raises(Unavailable):
        monitor.observe(live(v1, False, seed=7))
    (status,) = [s for s in monitor.status() if s.version == v1]
    assert (status.state, status.n) == ("watching", 8)
    monitor.replay = good
    (action,) = monitor.observe(live(v1, False, seed=8))
    assert action.rolled_back and action.n == 9 and registry.get_version(NAME).version == v0


def test_a_replay_that_skips_a_seed_is_refused(registry: LocalRegistry) -> None:
    def short(versions, seeds):
        return replay_with({0: True}, [])(versions, seeds[1:])

    monitor = DegradationMonitor(registry, config=MON_CFG, replay=short)
    registry.add_listener(monitor)
    _, v1 = gate_in(registry)
    with pytest.raises(Invalid, match=r"replay of pick\.reach v0 returned seeds"):
        monitor.observe_many([live(v1, False, seed=i) for i in range(8)])
    assert registry.get_version(NAME).version == v1
