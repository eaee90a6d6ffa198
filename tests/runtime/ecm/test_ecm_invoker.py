"""The invoker: outcome records for every way an ECM can misbehave, budgets, recovery."""

from __future__ import annotations

import itertools
import json
import os
import time
from collections.abc import Mapping

import numpy as np
import pytest

from capevo.errors import ErrorCode, Invalid
from capevo.records import Interface, IOSpec, Kind, Origin
from capevo.runtime.ecm import (
    EcmInvoker,
    Fallback,
    LoadedEcm,
    Outcome,
    Retry,
    SafeAbort,
    Status,
    StepResult,
    load_code,
    make_recovery,
)
from capevo.runtime.sandbox import SkillStep

OBS = {"x": np.array([0.5], dtype=np.float32), "robot0_eef_pos": np.zeros(3)}
X_ONLY = Interface(inputs=(IOSpec(name="x", shape=(1,)),))
BOUNDED = Interface(
    inputs=(IOSpec(name="x", shape=(1,)),),
    outputs=(
        IOSpec(name="arm", shape=(6,), low=-1.0, high=1.0),
        IOSpec(name="gripper", shape=(1,), low=-1.0, high=1.0),
    ),
)

GOOD = "def act(obs, params):\n    return [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
SKILLS = {
    "good": GOOD,
    "raise": "def act(obs, params):\n    raise ValueError('bad gain')\n",
    "nan": "def act(obs, params):\n    return [float('nan')] + [0.0] * 6\n",
    "inf": "import math\ndef act(obs, params):\n    return [math.inf] + [0.0] * 6\n",
    "short": "def act(obs, params):\n    return [0.0, 0.0, 0.0]\n",
    "matrix": "def act(obs, params):\n    return [[0.0] * 7]\n",
    "text": "def act(obs, params):\n    return 'forward'\n",
    "none": "def act(obs, params):\n    return None\n",
    "done": GOOD + "def done(obs, params):\n    return obs['x'][0] > 0\n",
    "big": "def act(obs, params):\n    return [5.0, -5.0, 0.0, 0.0, 0.0, 0.0, 2.0]\n",
}
# A module-level counter is allowed; the action reports how often act ran.
COUNTER = "CALLS = [0]\ndef act(obs, params):\n    CALLS[0] += 1\n    return [float(CALLS[0])] + [0.0] * 5 + [-1.0]\n"
# Fails on every odd call: a transient fault that a retry fixes.
FLAKY = (
    "CALLS = [0]\n"
    "def act(obs, params):\n"
    "    CALLS[0] += 1\n"
    "    if CALLS[0] % 2 == 1:\n"
    "        raise RuntimeError('transient')\n"
    "    return [0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
)


def code(
    key_or_source: str,
    *,
    name: str = "skill",
    version: int = 1,
    interface: Interface = X_ONLY,
    origin: Origin = Origin.MANUAL,
) -> LoadedEcm:
    source = SKILLS.get(key_or_source, key_or_source)
    return load_code(source, name=name, version=version, origin=origin, interface=interface)


@pytest.mark.parametrize(
    ("key", "status", "error"),
    [
        ("good", Status.OK, None),
        ("raise", Status.EXCEPTION, "ValueError: bad gain"),
        ("nan", Status.NAN, "non-finite"),
        ("inf", Status.NAN, "non-finite"),
        ("short", Status.BAD_SHAPE, "shape (3,), expected (7,)"),
        ("matrix", Status.BAD_SHAPE, "shape (1, 7), expected (7,)"),
        ("text", Status.BAD_SHAPE, "act returned str"),
        ("none", Status.BAD_SHAPE, "act returned NoneType"),
        ("done", Status.TERMINATED, None),
    ],
)
def test_each_behaviour_gets_its_outcome_and_the_caller_survives(key: str, status: Status, error: str | None) -> None:
    inv = EcmInvoker(code(key, name=key, version=4))
    res = inv.step(OBS)
    assert res.status is status
    (outcome,) = res.attempts if status in (Status.OK, Status.TERMINATED) else res.attempts[:1]
    assert outcome.status is status and outcome.ecm == key and outcome.version == 4
    assert outcome.duration_s >= 0.0
    if error is None:
        assert outcome.error is None
    else:
        assert outcome.error is not None and error in outcome.error
    if status is Status.OK:
        assert res.action == (0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) and outcome.action == res.action
    elif status is Status.TERMINATED:
        assert res.action is None and res.done
    else:  # default recovery: hold still
        assert outcome.action is None
        assert res.aborted and res.recovery == "abort"
        assert res.action == (0.0,) * 7


def test_actions_are_clipped_to_declared_bounds_and_flagged() -> None:
    res = EcmInvoker(code("big", interface=BOUNDED)).step(OBS)
    assert res.status is Status.OK
    assert res.action == (1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert res.attempts[0].clipped
    unclipped = EcmInvoker(code("big", interface=BOUNDED), clip_to_bounds=False).step(OBS)
    assert unclipped.action == (5.0, -5.0, 0.0, 0.0, 0.0, 0.0, 2.0) and not unclipped.attempts[0].clipped


def test_in_process_overruns_are_timeouts_after_the_fact() -> None:
    ticks = itertools.count()
    inv = EcmInvoker(code("good"), timeout_s=0.5, clock=lambda: float(next(ticks)))  # every call "takes" 1 s
    res = inv.step(OBS)
    assert res.status is Status.TIMEOUT
    assert res.attempts[0].action is None
    assert "over the 0.5s limit; result discarded" in (res.attempts[0].error or "")
    assert res.aborted


def test_real_in_process_overrun_is_a_timeout() -> None:
    busy = "def act(obs, params):\n    s = 0\n    for i in range(300000):\n        s += i\n    return [0.0] * 7\n"
    res = EcmInvoker(code(busy), timeout_s=0.001).step(OBS)
    assert res.status is Status.TIMEOUT and res.attempts[0].duration_s > 0.001


def test_a_sandboxed_hang_is_a_timeout_and_the_caller_goes_on() -> None:
    hang = (
        "def act(obs, params):\n"
        "    if obs['x'][0] > 0:\n"
        "        while True:\n"
        "            pass\n"
        "    return [0.0] * 6 + [1.0]\n"
    )
    ecm = code(hang, origin=Origin.LLM)
    try:
        assert not ecm.in_process
        inv = EcmInvoker(ecm, timeout_s=0.3)
        t0 = time.monotonic()
        res = inv.step(OBS)
        assert time.monotonic() - t0 < 2.0
        assert res.status is Status.TIMEOUT and res.aborted
        assert "no reply within 0.3s" in (res.attempts[0].error or "")
        ok = inv.step({"x": np.array([-1.0], dtype=np.float32)})
        assert ok.status is Status.OK and ok.action == (0.0,) * 6 + (1.0,)
    finally:
        ecm.close()


def test_a_sandbox_crash_is_an_exception_outcome() -> None:
    bomb = "import numpy as np\ndef act(obs, params):\n    return list(np.ones(10 ** 10))\n"
    ecm = code(bomb, origin=Origin.HYBRID)
    try:
        res = EcmInvoker(ecm, timeout_s=5.0).step(OBS)
        assert res.status is Status.EXCEPTION
        assert "MemoryError" in (res.attempts[0].error or "")
    finally:
        ecm.close()


class _Exits:
    """A third-party runner that raises SystemExit (allowed by the Runner protocol)."""

    in_process = True

    def step(self, inputs: Mapping[str, np.ndarray], *, timeout_s: float) -> SkillStep:
        raise SystemExit(3)

    def close(self) -> None:
        pass


def test_even_system_exit_from_an_ecm_is_contained() -> None:
    ecm = LoadedEcm(name="exits", version=0, kind=Kind.NEURAL, origin=Origin.RL, interface=X_ONLY, runner=_Exits())
    res = EcmInvoker(ecm).step(OBS)
    assert res.status is Status.EXCEPTION and res.attempts[0].error == "SystemExit: 3"


# --- budget ----------------------------------------------------------------------------


def test_step_budget_stops_calls_and_reset_restores_it() -> None:
    inv = EcmInvoker(code(COUNTER), step_budget=3)
    assert [inv.step(OBS).action[0] for _ in range(3)] == [1.0, 2.0, 3.0]  # type: ignore[index]
    res = inv.step(OBS)
    assert res.status is Status.BUDGET_EXHAUSTED and res.action is None and res.done
    assert res.attempts[0].error == "step budget of 3 used up"
    assert inv.steps_used == 3
    inv.reset()
    assert inv.step(OBS).action[0] == 4.0  # type: ignore[index]  # not called while exhausted


# --- recovery --------------------------------------------------------------------------


def test_safe_abort_holds_still_with_the_gripper_unchanged() -> None:
    flaky = code(FLAKY)
    inv = EcmInvoker(flaky, recovery=SafeAbort(), default_gripper=-1.0)
    first = inv.step(OBS)  # call 1 fails before any action: gripper default
    assert first.aborted and first.action == (0.0,) * 6 + (-1.0,)
    second = inv.step(OBS)  # call 2 succeeds and closes the gripper
    assert second.status is Status.OK and second.action is not None and second.action[6] == 1.0
    third = inv.step(OBS)  # call 3 fails: hold with the gripper still closed
    assert third.aborted and third.status is Status.EXCEPTION
    assert third.action == (0.0,) * 6 + (1.0,)
    assert inv.safe_action() == third.action


def test_retry_recovers_a_transient_fault() -> None:
    inv = EcmInvoker(code(FLAKY), recovery=Retry(attempts=2))
    res = inv.step(OBS)
    assert res.status is Status.OK and res.recovery == "retry" and not res.aborted
    assert [a.status for a in res.attempts] == [Status.EXCEPTION, Status.OK]
    assert res.action == (0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def test_retry_then_fallback_then_abort_walks_the_chain() -> None:
    bad_prev = code("nan", name="skill", version=0)
    strategy = make_recovery("retry", attempts=2, then=make_recovery("fallback", alternatives=[bad_prev]))
    res = EcmInvoker(code("raise"), recovery=strategy).step(OBS)
    assert res.recovery == "retry>fallback>abort" and res.aborted
    assert res.status is Status.EXCEPTION
    assert [(a.version, a.status) for a in res.attempts] == [
        (1, Status.EXCEPTION),
        (1, Status.EXCEPTION),
        (1, Status.EXCEPTION),
        (0, Status.NAN),
    ]


@pytest.mark.parametrize("sticky", [True, False])
def test_fallback_to_the_previous_version(sticky: bool) -> None:
    broken = code("raise", name="reach", version=2)
    previous = code(COUNTER, name="reach", version=1)
    inv = EcmInvoker(broken, recovery=Fallback(alternatives=[previous], sticky=sticky))
    res = inv.step(OBS)
    assert res.status is Status.OK and res.recovery == "fallback"
    assert [(a.version, a.status) for a in res.attempts] == [(2, Status.EXCEPTION), (1, Status.OK)]
    nxt = inv.step(OBS)
    if sticky:
        assert inv.primary is previous
        assert [(a.version, a.status) for a in nxt.attempts] == [(1, Status.OK)] and nxt.recovery is None
        inv.reset()
        assert inv.primary is broken
    else:
        assert inv.primary is broken
        assert [a.version for a in nxt.attempts] == [2, 1]


def test_fallback_skips_the_primary_itself() -> None:
    primary = code("raise")
    res = EcmInvoker(primary, recovery=Fallback(alternatives=[primary])).step(OBS)
    assert len(res.attempts) == 1 and res.recovery == "fallback>abort"


def test_recovery_registry_lists_valid_names() -> None:
    with pytest.raises(Invalid) as info:
        make_recovery("pray")
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "unknown recovery strategy 'pray'; valid: abort, fallback, retry"
    with pytest.raises(Invalid, match=r"recovery strategy 'retry': .*unexpected keyword"):
        make_recovery("retry", tries=3)
    with pytest.raises(Invalid, match="attempts must be >= 1"):
        make_recovery("retry", attempts=0)
    with pytest.raises(Invalid, match="needs at least one alternative"):
        make_recovery("fallback", alternatives=[])


# --- wiring errors ---------------------------------------------------------------------


def test_wiring_errors_raise_invalid() -> None:
    prompt = LoadedEcm(name="plan", version=1, kind=Kind.PROMPT, origin=Origin.MANUAL, text="Plan the task.")
    with pytest.raises(Invalid, match="plan@1: prompt ECMs are not executable"):
        EcmInvoker(prompt)
    wide = Interface(outputs=(IOSpec(name="action", shape=(12,)),))
    with pytest.raises(Invalid, match="interface outputs total 12 values, but the task's action has 7"):
        EcmInvoker(code("good", interface=wide))
    with pytest.raises(Invalid, match="interface outputs total 12"):
        EcmInvoker(code("good"), recovery=Fallback(alternatives=[code("good", interface=wide)]))
    with pytest.raises(Invalid, match="timeout_s must be positive"):
        EcmInvoker(code("good"), timeout_s=0)
    with pytest.raises(Invalid, match="step_budget"):
        EcmInvoker(code("good"), step_budget=0)
    with pytest.raises(Invalid, match="input 'x' is missing"):
        EcmInvoker(code("good")).step({"y": np.zeros(1)})


def test_code_without_declared_inputs_sees_the_whole_observation() -> None:
    source = "def act(obs, params):\n    return [float(len(obs))] + [0.0] * 6\n"
    res = EcmInvoker(code(source, interface=Interface())).step({**OBS, "label": "not numeric"})
    assert res.action is not None and res.action[0] == 2.0


def test_outcome_records_round_trip_through_json() -> None:
    inv = EcmInvoker(code(FLAKY), recovery=Retry())
    for res in (inv.step(OBS), EcmInvoker(code("raise")).step(OBS)):
        wire = json.loads(json.dumps(res.to_dict()))
        assert StepResult.from_dict(wire) == res
        for a in res.attempts:
            assert Outcome.from_dict(a.to_dict()) == a


def test_sandbox_workers_of_closed_ecms_are_gone() -> None:
    with code("good", origin=Origin.LLM) as ecm:
        pid = ecm.runner.pid  # type: ignore[union-attr]
        assert EcmInvoker(ecm).step(OBS).status is Status.OK
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    ecm.close()  # idempotent
