"""JSON codec (capevo.runtime.traces.codec invariants 1-4), with property tests."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import jsonschema
import numpy as np
import pytest
from _trace_helpers import make_env_step, one_of_each, same_floats
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import Corrupt, ErrorCode, Invalid
from capevo.runtime.traces import codec
from capevo.runtime.traces.records import EcmInvocation, EnvStep, Intervention, Outcome

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
    data = codec.RecordEncoder().encode(s)
    d = strict_loads(data)
    assert EnvStep.from_dict(d) == EnvStep.from_dict(strict_loads(codec.encode_dict(s.to_dict()))) == s
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
            # 9 digits then float32: one of the two float32 neighbours of x.
            assert abs(y - x) <= float(np.spacing(np.float32(abs(x)))), (x, y)
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
    # Invariants 2 and 3 for the other fast paths: float32 vectors and float64 scalars exact.
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
    assert EcmInvocation.from_dict(strict_loads(codec.encode_dict(r.to_dict()))) == r
    i = Intervention(episode=0, step=1, constraint=name, original_action=inputs, result_action=output, reason=name)
    data = codec.encode(i)
    jsonschema.validate(strict_loads(data), Intervention.SCHEMA)
    assert codec.decode(Intervention.TOPIC, data) == i
    assert Intervention.from_dict(strict_loads(codec.encode_dict(i.to_dict()))) == i


@settings(max_examples=50, deadline=None)
@given(st.lists(f64_in_f32_range, max_size=20).map(tuple))
def test_float64_vectors_come_back_as_nearby_float32(values: tuple[float, ...]) -> None:
    r = Intervention(episode=0, step=0, constraint="c", original_action=values, result_action=None)
    back = codec.decode(Intervention.TOPIC, codec.encode(r))
    assert isinstance(back, Intervention)
    for x, y in zip(values, back.original_action, strict=True):
        assert float(np.float32(y)) == y
        assert abs(y - x) <= float(np.spacing(np.float32(abs(x))))


@pytest.mark.parametrize("record", one_of_each(), ids=lambda r: type(r).__name__)
def test_every_payload_validates_against_its_schema(record: Any) -> None:
    d = strict_loads(codec.encode(record))
    jsonschema.validate(d, type(record).SCHEMA, cls=jsonschema.Draft202012Validator)
    assert codec.decode(record.TOPIC, codec.encode(record)) == record


def test_env_step_values_beyond_float32_range_stay_finite() -> None:
    back = codec.decode(EnvStep.TOPIC, codec.encode(make_env_step(obs=(1e300, -1e39, 1.5), next_obs=())))
    assert isinstance(back, EnvStep)
    assert math.isclose(back.obs[0], 1e300, rel_tol=1e-8) and math.isclose(back.obs[1], -1e39, rel_tol=1e-8)
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


def test_obs_cache_is_one_attribute() -> None:
    # Invariant 4 under threads: the cached tuple and its float32 values are replaced together.
    enc = codec.RecordEncoder()
    s = make_env_step()
    enc.encode(s)
    cached_obs, cached_values = enc._last_next_obs
    assert cached_obs is s.next_obs and cached_values is not None
    assert cached_values.tolist() == list(s.next_obs)


def test_obs_cache_reuses_only_the_same_tuple() -> None:
    # Invariant 4: reuse by identity of a tuple; a mutated list or array is never served stale.
    enc = codec.RecordEncoder()
    a = make_env_step(0, 0)
    b = make_env_step(0, 1, obs=a.next_obs)
    enc.encode(a)
    encoded_b = enc.encode(b)
    assert encoded_b == codec.RecordEncoder().encode(b)  # the cached values are the right values
    assert codec.decode(EnvStep.TOPIC, encoded_b) == b

    for shared in ([1.0, 2.0], np.array([1.0, 2.0], dtype=np.float32)):
        enc = codec.RecordEncoder()
        enc.encode(make_env_step(0, 0, obs=(0.0, 0.0), next_obs=shared))  # type: ignore[arg-type]
        shared[0] = 99.0
        d = strict_loads(enc.encode(make_env_step(0, 1, obs=shared, next_obs=(5.0, 5.0))))  # type: ignore[arg-type]
        assert d["obs"] == [99.0, 2.0]


def test_float32_arrays_encode_like_their_tuples() -> None:
    # The runtime passes the env's float32 arrays: the same bytes as the tuple of their values.
    arr = np.asarray([0.1, -2.0, 3.5], dtype=np.float32)
    as_tuple = tuple(arr.tolist())
    s_np = make_env_step(obs=arr, next_obs=arr[::-1])
    s_t = make_env_step(obs=as_tuple, next_obs=as_tuple[::-1])
    assert codec.encode(s_np) == codec.encode(s_t)
    assert s_np == s_t and codec.decode(EnvStep.TOPIC, codec.encode(s_np)) == s_t
    assert codec.float32_array(arr) is arr  # no copy, no conversion
    r_np = EcmInvocation(episode=0, step=0, ecm="reach", version=1, input_state=arr, output=None, duration_s=0.5)
    r_t = dataclasses.replace(r_np, input_state=as_tuple)
    assert codec.encode(r_np) == codec.encode(r_t) and r_np == r_t and hash(r_np) == hash(r_t)


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


env_step_parts = st.fixed_dictionaries(
    {
        "obs": st.lists(f64_in_f32_range, max_size=50).map(tuple),
        "next_obs": st.lists(f64_in_f32_range, max_size=50).map(tuple),
        "action": st.lists(any_floats, max_size=12).map(tuple),
        "reward": any_floats,
        "key_state": st.dictionaries(names, st.lists(any_floats, max_size=6).map(tuple), max_size=3),
    }
)


@settings(max_examples=150, deadline=None)
@given(env_step_parts, st.booleans())
def test_fast_path_and_template_decode_alike(parts: dict[str, Any], as_arrays: bool) -> None:
    # Invariant 2: the one-call fast path and the template path decode to the same record
    # (vectors within one float32 ulp; non-finite values as NaN); arrays like tuples.
    if as_arrays:
        arrays = {k: np.asarray(parts[k], np.float32) for k in ("obs", "next_obs")}
        parts = {**parts, **arrays}
    s = make_env_step(**parts)
    enc = codec.RecordEncoder()
    fast = strict_loads(enc.encode(s))
    template = strict_loads(enc._env_step_template(s))
    assert ENV_STEP_VALIDATOR.is_valid(fast)
    a, b = EnvStep.from_dict(fast), EnvStep.from_dict(template)
    assert list(a.key_state) == list(b.key_state)
    pairs = [(a.obs, b.obs), (a.action, b.action), (a.next_obs, b.next_obs)]
    pairs += [(a.key_state[k], b.key_state[k]) for k in a.key_state]
    for x, y in pairs:
        assert same_floats(x, y, ulps=1), (x, y)
    assert same_floats((a.reward,), (b.reward,), ulps=0)


@settings(max_examples=100, deadline=None)
@given(
    st.lists(f64_in_f32_range, max_size=30).map(tuple),
    st.none() | st.lists(any_floats, max_size=12).map(tuple),
    any_floats,
    st.none() | st.text(max_size=20),
)
def test_invocation_fast_path_and_template_decode_alike(
    inputs: tuple[float, ...], output: tuple[float, ...] | None, duration: float, error: str | None
) -> None:
    r = EcmInvocation(
        episode=1, step=2, ecm="reach", version=3, input_state=inputs, output=output, duration_s=duration, error=error
    )
    enc = codec.RecordEncoder()
    fast = strict_loads(enc.encode(r))
    a = EcmInvocation.from_dict(fast)
    b = EcmInvocation.from_dict(strict_loads(enc._invocation_template(r)))
    assert a.error == b.error and a.outcome == b.outcome and same_floats((a.duration_s,), (b.duration_s,), ulps=0)
    assert same_floats(a.input_state, b.input_state, ulps=1)
    assert (a.output is None) == (b.output is None)
    if a.output is not None and b.output is not None:
        assert same_floats(a.output, b.output, ulps=1)


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


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(width=32), max_size=40))
def test_format_vector_names_each_float32_uniquely(values: list[float]) -> None:
    parsed = strict_loads(f"[{codec.format_vector(values)}]".encode())
    expected = [v if math.isfinite(v) else float("nan") for v in values]
    got = [float("nan") if v is None else float(np.float32(v)) for v in parsed]
    assert same_floats(got, expected)


# -- vector_json (the hot paths' vector printer) and invariant 5 ------------------------------


@settings(max_examples=300)
@given(st.lists(f32s, max_size=40))
def test_vector_json_names_each_float32_exactly(values: list[float]) -> None:
    text = codec.vector_json(tuple(values))
    parsed = strict_loads(text)
    assert [float(np.float32(v)) for v in parsed] == values


@settings(max_examples=300)
@given(st.lists(f64_in_f32_range, min_size=10, max_size=40))
def test_vector_json_rounds_float64_to_the_nearest_float32(values: list[float]) -> None:
    parsed = strict_loads(codec.vector_json(tuple(values)))
    assert [float(np.float32(v)) for v in parsed] == [float(np.float32(v)) for v in values]


@pytest.mark.parametrize("n", [3, 12])  # both sides of the short-vector cut-off
def test_vector_json_keeps_values_float32_cannot_hold(n: int) -> None:
    values = (1e300, float("nan"), -1e39, float("inf")) + (0.5,) * (n - 4 if n > 4 else 0)
    parsed = strict_loads(codec.vector_json(values[:n]))
    assert parsed[0] == 1e300 and parsed[1] is None and parsed[2] == -1e39
    if n > 3:
        assert parsed[3] is None


@pytest.mark.parametrize("n", [3, 12])
@pytest.mark.parametrize("bad", ["1.5", None, (1.0, 2.0), 1 + 2j])
def test_a_vector_component_that_is_not_a_real_number_fails_the_encoding(n: int, bad: Any) -> None:
    vector = (bad,) + (0.25,) * (n - 1)
    with pytest.raises(Invalid):
        codec.encode(make_env_step(next_obs=vector))


def test_a_name_that_is_not_utf8_fails_the_encoding() -> None:
    with pytest.raises(Invalid, match="EnvStep does not encode"):
        codec.encode(dataclasses.replace(make_env_step(), ecm="\ud800"))
