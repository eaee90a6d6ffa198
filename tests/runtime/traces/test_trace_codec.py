"""JSON codec (capevo.runtime.traces.codec invariants 1-4), with property tests."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import jsonschema
import numpy as np
import pytest
from _trace_helpers import make_env_step, one_of_each
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import Corrupt, ErrorCode, Invalid
from capevo.runtime.traces import codec
from capevo.runtime.traces.records import EcmInvocation, EnvStep, EpisodeSummary, Intervention, Outcome, PlanStep

ENV_STEP_VALIDATOR = jsonschema.Draft202012Validator(EnvStep.SCHEMA)


def strict_loads(data: bytes) -> Any:
    """json.loads that refuses NaN/Infinity tokens (invariant 1)."""

    def refuse(token: str) -> None:
        raise AssertionError(f"non-standard JSON token {token}")

    return json.loads(data, parse_constant=refuse)


f32s = st.floats(width=32, allow_nan=False, allow_infinity=False)
f64s = st.floats(allow_nan=False, allow_infinity=False)
# float64 values inside float32 range (at the very edge, 9-digit rounding may cross FLT_MAX).
f64_in_f32_range = st.floats(min_value=-3e38, max_value=3e38)
any_floats = st.floats(allow_nan=True, allow_infinity=True)
names = st.text(max_size=20)
ints = st.integers(min_value=0, max_value=2**53)


@st.composite
def env_steps(draw: st.DrawFn, values: st.SearchStrategy[float] = f32s) -> EnvStep:
    vec = st.lists(values, max_size=60).map(tuple)
    return EnvStep(
        episode=draw(ints),
        step=draw(ints),
        ecm=draw(names),
        version=draw(ints),
        obs=draw(vec),
        action=draw(st.lists(values, max_size=12).map(tuple)),
        reward=draw(values),
        next_obs=draw(vec),
        terminated=draw(st.booleans()),
        truncated=draw(st.booleans()),
        is_success=draw(st.booleans()),
        key_state=draw(st.dictionaries(names, st.lists(values, max_size=6).map(tuple), max_size=3)),
    )


@settings(max_examples=150, deadline=None)
@given(env_steps())
def test_env_step_float32_round_trips_exactly(s: EnvStep) -> None:
    # Invariants 2 and 3 on the hot path: float32 vectors come back bit-for-bit.
    data = codec.encode(s)
    d = strict_loads(data)
    assert EnvStep.from_dict(d) == EnvStep.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    assert ENV_STEP_VALIDATOR.is_valid(d)
    assert codec.decode(EnvStep.TOPIC, data) == s


@settings(max_examples=100, deadline=None)
@given(env_steps(values=f64_in_f32_range))
def test_env_step_float64_comes_back_as_float32(s: EnvStep) -> None:
    back = codec.decode(EnvStep.TOPIC, codec.encode(s))
    assert isinstance(back, EnvStep)
    for a, b in ((s.obs, back.obs), (s.action, back.action), (s.next_obs, back.next_obs)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert float(np.float32(y)) == y  # a float32 value
            assert y == float(np.float32(x)), (x, y)  # the float32 nearest to x
    assert back.reward == s.reward  # scalars are exact


@settings(max_examples=100, deadline=None)
@given(env_steps(values=any_floats))
def test_non_finite_values_become_null_and_decode_as_nan(s: EnvStep) -> None:
    # Invariant 1: strict JSON whatever the floats.
    data = codec.encode(s)
    d = strict_loads(data)
    assert ENV_STEP_VALIDATOR.is_valid(d)
    back = codec.decode(EnvStep.TOPIC, data)
    assert isinstance(back, EnvStep)
    for x, y in zip(s.obs, back.obs, strict=True):
        if not math.isfinite(x):
            assert math.isnan(y)
        elif abs(x) <= 3e38:
            assert abs(y - x) <= float(np.spacing(np.float32(abs(x))))
        else:
            assert math.isclose(x, y, rel_tol=1e-8)
    assert math.isnan(back.reward) if not math.isfinite(s.reward) else back.reward == s.reward


@settings(max_examples=80, deadline=None)
@given(
    st.lists(f32s, max_size=30).map(tuple),
    st.none() | st.lists(f32s, max_size=30).map(tuple),
    f64s,
    st.sampled_from(Outcome),
    st.none() | st.text(max_size=30),
    names,
)
def test_invocations_and_interventions_round_trip(
    inputs: tuple[float, ...],
    output: tuple[float, ...] | None,
    duration: float,
    outcome: Outcome,
    error: str | None,
    name: str,
) -> None:
    # Invariant 2 for the other vector records: float32 vectors and float64 scalars exact.
    r = EcmInvocation(
        episode=1,
        step=2,
        ecm=name,
        version=3,
        input_state=inputs,
        output=output,
        duration_s=duration,
        outcome=outcome,
        error=error,
    )
    data = codec.encode(r)
    d = strict_loads(data)
    jsonschema.validate(d, EcmInvocation.SCHEMA)
    assert codec.decode(EcmInvocation.TOPIC, data) == r == EcmInvocation.from_dict(d)
    i = Intervention(episode=0, step=1, constraint=name, original_action=inputs, result_action=output, reason=name)
    data = codec.encode(i)
    jsonschema.validate(strict_loads(data), Intervention.SCHEMA)
    assert codec.decode(Intervention.TOPIC, data) == i


@settings(max_examples=50, deadline=None)
@given(st.lists(f64_in_f32_range, max_size=20).map(tuple))
def test_float64_vectors_come_back_as_nearby_float32(values: tuple[float, ...]) -> None:
    r = Intervention(episode=0, step=0, constraint="c", original_action=values, result_action=None)
    back = codec.decode(Intervention.TOPIC, codec.encode(r))
    assert isinstance(back, Intervention)
    for x, y in zip(values, back.original_action, strict=True):
        assert y == float(np.float32(x))


@pytest.mark.parametrize("record", one_of_each(), ids=lambda r: type(r).__name__)
def test_every_payload_validates_against_its_schema(record: Any) -> None:
    d = strict_loads(codec.encode(record))
    jsonschema.validate(d, type(record).SCHEMA, cls=jsonschema.Draft202012Validator)
    assert codec.decode(record.TOPIC, codec.encode(record)) == record


def test_env_step_values_beyond_float32_range_stay_finite() -> None:
    back = codec.decode(EnvStep.TOPIC, codec.encode(make_env_step(obs=(1e300, -1e39, 1.5), next_obs=())))
    assert isinstance(back, EnvStep)
    assert back.obs[0] == 1e300 and back.obs[1] == -1e39
    assert back.obs[2] == 1.5


def test_nan_output_of_a_failed_invocation_is_strict_json() -> None:
    r = EcmInvocation(
        episode=0,
        step=0,
        ecm="reach",
        version=1,
        input_state=(float("inf"),),
        output=(float("nan"), 1.0),
        duration_s=0.01,
        outcome=Outcome.NAN,
        error="policy returned NaN",
    )
    d = strict_loads(codec.encode(r))
    assert d["output"] == [None, 1.0] and d["input_state"] == [None]
    back = codec.decode(EcmInvocation.TOPIC, codec.encode(r))
    assert isinstance(back, EcmInvocation) and back.output is not None
    assert math.isnan(back.output[0]) and back.output[1] == 1.0


def test_float32_arrays_encode_like_their_tuples() -> None:
    # Invariant 3. The runtime passes the env's float32 arrays: printed as float32 values, the
    # shortest text naming each; a strided array like a contiguous one.
    arr = np.asarray([0.1, -2.0, 3.5], dtype=np.float32)
    as_tuple = tuple(arr.tolist())
    s_np = make_env_step(obs=arr, next_obs=arr[::-1])
    s_t = make_env_step(obs=as_tuple, next_obs=as_tuple[::-1])
    assert strict_loads(codec.encode(s_np))["obs"] == [0.1, -2.0, 3.5]
    assert strict_loads(codec.encode(s_np))["next_obs"] == [3.5, -2.0, 0.1]
    assert codec.decode(EnvStep.TOPIC, codec.encode(s_np)) == codec.decode(EnvStep.TOPIC, codec.encode(s_t)) == s_t
    assert codec.vector(arr) is not None and codec.vector(arr).base is arr  # no copy, no conversion
    r_np = EcmInvocation(episode=0, step=0, ecm="reach", version=1, input_state=arr, output=None, duration_s=0.5)
    r_t = dataclasses.replace(r_np, input_state=as_tuple)
    back = codec.decode(EcmInvocation.TOPIC, codec.encode(r_np))
    assert back == codec.decode(EcmInvocation.TOPIC, codec.encode(r_t)) == r_np == r_t and hash(r_np) == hash(r_t)


def test_other_arrays_and_sequences_encode_like_tuples() -> None:
    # float64, int and strided arrays and lists take the conversion; they decode like tuples.
    base = np.asarray([0.1, -2.0, 3.5, 7.0], dtype=np.float64)
    for vector in (base, base.astype(np.float32)[::2], base.astype(np.int64), base.tolist()):
        values = tuple(float(v) for v in vector)
        s = make_env_step(obs=vector, next_obs=vector, action=vector)  # type: ignore[arg-type]
        back = codec.decode(EnvStep.TOPIC, codec.encode(s))
        want = codec.decode(EnvStep.TOPIC, codec.encode(make_env_step(obs=values, next_obs=values, action=values)))
        assert back == want


def test_short_float_tuples_are_printed_exactly() -> None:
    # The runtime's own float64 vectors (action, key state, output) are printed as they are.
    action = (0.1, -0.2, 1 / 3, 0.0, -0.0, 1e-300, 2.5e38)
    d = strict_loads(codec.encode(make_env_step(action=action, key_state={"p": (1 / 7, 2.0, 3.0)})))
    assert tuple(d["action"]) == action and d["key_state"]["p"] == [1 / 7, 2.0, 3.0]
    assert math.copysign(1.0, d["action"][4]) == -1.0


def test_wrong_field_types_are_invalid() -> None:
    with pytest.raises(Invalid) as exc:
        codec.encode(dataclasses.replace(make_env_step(), episode="zero"))  # type: ignore[arg-type]
    assert exc.value.code is ErrorCode.INVALID
    assert "EnvStep does not encode as JSON" in exc.value.message
    with pytest.raises(Invalid) as exc:
        codec.encode(make_env_step(obs=("a", "b")))  # type: ignore[arg-type]
    assert "EnvStep does not encode" in exc.value.message
    bad = EcmInvocation(
        episode=0,
        step=0,
        ecm="e",
        version=1,
        input_state=(object(),),
        output=None,
        duration_s=0.0,  # type: ignore[arg-type]
    )
    with pytest.raises(Invalid) as exc:
        codec.encode(bad)
    assert "EcmInvocation does not encode as JSON" in exc.value.message
    with pytest.raises(Invalid, match="EnvStep does not encode as JSON: TypeError: expected a str, got int"):
        codec.encode(dataclasses.replace(make_env_step(), ecm=3))  # type: ignore[arg-type]
    with pytest.raises(Invalid, match="PlanStep does not encode"):
        codec.encode(PlanStep(episode=0, step=None, ecm="a", version=1))  # type: ignore[arg-type]


def test_numpy_scalars_encode_as_their_python_values() -> None:
    # What the runtime may hand over: numpy ints, floats and bools where the schema says so.
    s = dataclasses.replace(
        make_env_step(),
        episode=np.int64(3),
        reward=np.float32(0.1),
        terminated=np.bool_(True),  # type: ignore[arg-type]
    )
    d = strict_loads(codec.encode(s))
    assert d["episode"] == 3 and d["reward"] == float(np.float32(0.1)) and d["terminated"] is True
    summary = EpisodeSummary(
        episode=0,
        seed=None,
        success=True,
        total_reward=float("nan"),
        steps=1,
        interventions=0,
        unsafe_steps=0,
        capability_set={"reach": 2},
        duration_s=1.0,
    )
    d = strict_loads(codec.encode(summary))
    assert d["seed"] is None and d["total_reward"] is None and d["revision"] is None


def test_decode_errors() -> None:
    with pytest.raises(Corrupt) as exc:
        codec.decode(EnvStep.TOPIC, b"{not json")
    assert exc.value.code is ErrorCode.CORRUPT
    assert "does not decode as EnvStep" in exc.value.message
    with pytest.raises(Corrupt) as exc:
        codec.decode(EnvStep.TOPIC, b'{"episode": 1}')
    assert "KeyError" in exc.value.message
    with pytest.raises(Invalid) as exc:
        codec.decode("/nope", b"{}")
    assert "unknown trace topic" in exc.value.message


# -- vectors (invariant 4) ---------------------------------------------------------------------


def test_values_float32_cannot_hold_are_kept() -> None:
    values = (1e300, float("nan"), -1e39, float("inf"), 0.5)
    parsed = strict_loads(codec.encode(make_env_step(action=values)))["action"]
    assert parsed == [1e300, None, -1e39, None, 0.5]


@pytest.mark.parametrize("bad", ["1.5", None, (1.0, 2.0), 1 + 2j])
def test_a_vector_component_that_is_not_a_real_number_fails_the_encoding(bad: Any) -> None:
    vector = (bad,) + (0.25,) * 11
    with pytest.raises(Invalid):
        codec.encode(make_env_step(next_obs=vector))
    with pytest.raises(Invalid):
        codec.encode(make_env_step(key_state={"p": vector}))


def test_a_name_that_is_not_utf8_fails_the_encoding() -> None:
    with pytest.raises(Invalid, match="EnvStep does not encode"):
        codec.encode(dataclasses.replace(make_env_step(), ecm="\ud800"))
