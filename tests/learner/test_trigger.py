"""The update trigger: pure rules (count, degradation) and the stateful wrapper.

Invariants of :mod:`capevo.learner.trigger`: no firing without new episodes (1), the count rule
(2), the degradation rule's evidence (3), the bounded stateful trigger deciding as the pure
function over the whole history (4).
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import ErrorCode, Invalid
from capevo.learner.trigger import TriggerConfig, UpdateTrigger, decide

histories = st.lists(st.booleans(), max_size=120)


def _config(min_new: int | None, window: int, margin: float | None) -> TriggerConfig | None:
    if min_new is None and margin is None:
        return None
    return TriggerConfig(min_new_episodes=min_new, window=window, degradation_margin=margin)


configs = st.builds(
    _config,
    st.one_of(st.none(), st.integers(1, 40)),
    st.integers(1, 25),
    st.one_of(st.none(), st.floats(0.01, 1.0)),
).filter(lambda c: c is not None)


@given(history=histories, config=configs)
def test_never_fires_without_new_episodes(history: list[bool], config: TriggerConfig) -> None:
    d = decide(history, len(history), config)
    assert not d.fire and d.reason == "" and d.new_episodes == 0


@given(history=histories, data=st.data(), min_new=st.integers(1, 40), window=st.integers(1, 25))
def test_count_rule_fires_exactly_at_the_threshold(
    history: list[bool], data: st.DataObject, min_new: int, window: int
) -> None:
    since = data.draw(st.integers(0, len(history)))
    config = TriggerConfig(min_new_episodes=min_new, window=window, degradation_margin=None)
    d = decide(history, since, config)
    assert d.fire == (len(history) - since >= min_new)
    assert d.reason == ("count" if d.fire else "")
    assert d.new_episodes == len(history) - since


@given(history=histories, data=st.data(), window=st.integers(1, 25), margin=st.floats(0.01, 1.0))
def test_degradation_fires_only_on_a_real_drop_over_full_windows(
    history: list[bool], data: st.DataObject, window: int, margin: float
) -> None:
    since = data.draw(st.integers(0, len(history)))
    config = TriggerConfig(min_new_episodes=None, window=window, degradation_margin=margin)
    d = decide(history, since, config)
    full = len(history) >= 2 * window
    new = len(history) - since
    if full:
        recent = sum(history[-window:]) / window
        reference = sum(history[-2 * window : -window]) / window
        assert d.recent_rate == pytest.approx(recent)
        assert d.reference_rate == pytest.approx(reference)
        expected = new >= window and reference - recent >= margin - 1e-12
    else:
        expected = False
        assert d.reference_rate is None
    assert d.fire == expected
    if d.fire:
        assert d.reason == "degradation"


@given(flag=st.booleans(), n=st.integers(0, 100), window=st.integers(1, 20), margin=st.floats(0.01, 1.0))
def test_a_constant_success_rate_never_degrades(flag: bool, n: int, window: int, margin: float) -> None:
    config = TriggerConfig(min_new_episodes=None, window=window, degradation_margin=margin)
    assert not decide([flag] * n, 0, config).fire


@settings(max_examples=150)
@given(
    config=configs,
    steps=st.lists(st.one_of(st.booleans(), st.just("update"), st.just("reset")), max_size=150),
)
def test_stateful_trigger_decides_like_the_pure_rule(config: TriggerConfig, steps: list[object]) -> None:
    trigger = UpdateTrigger(config)
    history: list[bool] = []
    since = 0
    for step in steps:
        if step == "update":
            trigger.mark_updated()
            since = len(history)
        elif step == "reset":
            trigger.reset()
            history, since = [], 0
        else:
            trigger.observe(bool(step))
            history.append(bool(step))
        assert trigger.check() == decide(history, since, config)
        assert trigger.new_episodes == len(history) - since
        assert len(trigger._tail) <= 2 * config.window


def test_degradation_example_and_one_update_per_drop() -> None:
    config = TriggerConfig(min_new_episodes=None, window=4, degradation_margin=0.5)
    trigger = UpdateTrigger(config)
    trigger.extend([True, True, True, True])
    assert not trigger.check().fire  # one window only
    trigger.extend([False, False, True, False])
    d = trigger.check()
    assert d.fire and d.reason == "degradation"
    assert (d.reference_rate, d.recent_rate) == (1.0, 0.25)
    trigger.mark_updated()
    trigger.extend([False, False, False])
    assert not trigger.check().fire  # fewer than a window of new evidence
    assert trigger.new_episodes == 3


@pytest.mark.parametrize(
    ("kwargs", "field", "text"),
    [
        ({"min_new_episodes": 0}, "min_new_episodes", "min_new_episodes must be a positive integer or None, got 0"),
        ({"window": 0}, "window", "window must be a positive integer, got 0"),
        ({"degradation_margin": 1.5}, "degradation_margin", "degradation_margin must be in (0, 1] or None, got 1.5"),
        (
            {"min_new_episodes": None, "degradation_margin": None},
            "min_new_episodes",
            "turn on at least one rule: min_new_episodes or degradation_margin",
        ),
    ],
)
def test_bad_configs_are_refused(kwargs: dict, field: str, text: str) -> None:
    with pytest.raises(Invalid) as info:
        TriggerConfig(**kwargs)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == text
    assert info.value.details["field"] == field


def test_since_beyond_the_history_is_refused() -> None:
    with pytest.raises(Invalid) as info:
        decide([True, False], 3, TriggerConfig())
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "since must be in [0, 2], got 3"
