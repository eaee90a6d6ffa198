"""Input marshalling per the interface spec, and plan composition checks."""

from __future__ import annotations

import numpy as np
import pytest
from ecm_helpers import make_record
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from capevo.errors import ErrorCode, Invalid
from capevo.records import Interface, IOSpec
from capevo.runtime.ecm import check_composition, clip_to_bounds, flatten_inputs, marshal_inputs, output_size

SPECS = (IOSpec(name="eef_pos", shape=(3,)), IOSpec(name="gripper", shape=(2,), dtype="float64"))


def test_marshal_picks_declared_keys_in_order_with_declared_dtype() -> None:
    obs = {
        "gripper": [0.01, -0.01],
        "eef_pos": np.array([1.0, 2.0, 3.0]),
        "other": np.zeros(9),
    }
    out = marshal_inputs(obs, SPECS)
    assert list(out) == ["eef_pos", "gripper"]
    assert out["eef_pos"].dtype == np.float32 and out["gripper"].dtype == np.float64
    assert not out["eef_pos"].flags.writeable
    flat = flatten_inputs(out, SPECS)
    assert flat.dtype == np.float32
    np.testing.assert_allclose(flat, [1, 2, 3, 0.01, -0.01], rtol=1e-6)


def test_marshal_does_not_let_ecms_write_into_the_observation() -> None:
    raw = np.array([1.0, 2.0, 3.0], dtype=np.float32)
    out = marshal_inputs({"eef_pos": raw, "gripper": np.zeros(2)}, SPECS)
    with pytest.raises(ValueError, match="read-only"):
        out["eef_pos"][0] = 9.0
    assert raw[0] == 1.0 and raw.flags.writeable


@pytest.mark.parametrize(
    ("obs", "fragment"),
    [
        ({"gripper": np.zeros(2)}, "input 'eef_pos' is missing from the observation (keys: gripper)"),
        ({"eef_pos": np.zeros(4), "gripper": np.zeros(2)}, "input 'eef_pos' has shape (4,), expected (3,)"),
        ({"eef_pos": np.zeros((3, 1)), "gripper": np.zeros(2)}, "has shape (3, 1), expected (3,)"),
        ({"eef_pos": np.array(["a", "b", "c"]), "gripper": np.zeros(2)}, "has dtype <U1, expected numeric"),
        ({"eef_pos": [[1, 2], [3]], "gripper": np.zeros(2)}, "is not an array"),
        ({"eef_pos": [None, None, None], "gripper": np.zeros(2)}, "has dtype object"),
    ],
)
def test_marshal_errors_name_the_key_expected_and_actual(obs: dict, fragment: str) -> None:
    with pytest.raises(Invalid) as info:
        marshal_inputs(obs, SPECS, ecm="reach@2")
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message.startswith("reach@2: ")
    assert fragment in info.value.message


def test_marshal_rejects_non_mappings() -> None:
    with pytest.raises(Invalid, match="observation must be a dict"):
        marshal_inputs([1, 2, 3], SPECS)  # type: ignore[arg-type]


_spec = st.builds(
    IOSpec,
    name=st.sampled_from(["a", "b", "c", "d"]),
    shape=st.lists(st.integers(1, 3), min_size=1, max_size=2).map(tuple),
    dtype=st.sampled_from(["float32", "float64", "int32", "int64", "bool", "uint8"]),
)
_value = st.one_of(
    hnp.arrays(
        dtype=st.sampled_from([np.float32, np.float64, np.int64, np.bool_]),
        shape=hnp.array_shapes(min_dims=0, max_dims=2, max_side=3),
        elements={"allow_nan": False, "allow_infinity": False, "min_value": -100, "max_value": 100},
    ),
    st.lists(st.floats(-10, 10), max_size=4),
    st.text(max_size=3),
    st.none(),
    st.lists(st.lists(st.integers(0, 3), max_size=3), max_size=3),
)


@settings(max_examples=300, deadline=None)
@given(
    specs=st.lists(_spec, max_size=4, unique_by=lambda s: s.name),
    obs=st.dictionaries(st.sampled_from(["a", "b", "c", "d", "e"]), _value, max_size=5),
)
def test_marshal_returns_exact_arrays_or_raises_invalid(specs: list[IOSpec], obs: dict) -> None:
    try:
        out = marshal_inputs(obs, specs)
    except Invalid as exc:
        assert exc.message.startswith("ecm: input ")
        return
    assert list(out) == [s.name for s in specs]
    for s in specs:
        arr = out[s.name]
        assert arr.shape == s.shape and arr.dtype == np.dtype(s.dtype)
        np.testing.assert_array_equal(arr, np.asarray(obs[s.name]).astype(s.dtype))
    assert flatten_inputs(out, specs).shape == (sum(int(np.prod(s.shape)) for s in specs),)


def test_clip_to_bounds_per_output_slice() -> None:
    outputs = (
        IOSpec(name="arm", shape=(2,), low=-1.0, high=1.0),
        IOSpec(name="free", shape=(1,)),
        IOSpec(name="grip", shape=(1,), low=0.0),
    )
    assert output_size(outputs) == 4
    clipped, changed = clip_to_bounds(np.array([2.0, -0.5, 99.0, -3.0]), outputs)
    assert clipped.tolist() == [1.0, -0.5, 99.0, 0.0] and changed
    same, changed = clip_to_bounds(np.array([0.0, 0.0, 5.0, 1.0]), outputs)
    assert same.tolist() == [0.0, 0.0, 5.0, 1.0] and not changed


# --- composition ---------------------------------------------------------------------


def _ecm(name: str, inputs: tuple[IOSpec, ...] = (), outputs: tuple[IOSpec, ...] = (), version: int = 1):
    return make_record(name, name.encode(), version=version, interface=Interface(inputs=inputs, outputs=outputs))


POSE = IOSpec(name="pose", shape=(7,), low=-1.0, high=1.0)


def test_compatible_plans_pass() -> None:
    detect = _ecm("detect", outputs=(POSE, IOSpec(name="score", shape=(1,))))
    grasp = _ecm("grasp", inputs=(IOSpec(name="pose", shape=(7,), low=-2.0, high=2.0),), outputs=(POSE,))
    place = _ecm("place", inputs=(IOSpec(name="pose", shape=(7,)),))
    check_composition([detect, grasp, place])
    check_composition([])
    check_composition([place])


@pytest.mark.parametrize(
    ("consumer_input", "field", "expected", "got", "fragment"),
    [
        (IOSpec(name="goal", shape=(7,)), "missing", "goal", ["pose"], "input 'goal' of grasp@4: missing is not among"),
        (IOSpec(name="pose", shape=(6,)), "shape", [6], [7], "shape differs: expected [6], got [7] from detect@2"),
        (IOSpec(name="pose", shape=(7,), dtype="float64"), "dtype", "float64", "float32", "dtype differs"),
        (IOSpec(name="pose", shape=(7,), low=0.0), "low", 0.0, -1.0, "low is below the accepted range"),
        (IOSpec(name="pose", shape=(7,), high=0.5), "high", 0.5, 1.0, "high is above the accepted range"),
    ],
)
def test_incompatible_pairs_name_ecms_field_and_values(
    consumer_input: IOSpec, field: str, expected: object, got: object, fragment: str
) -> None:
    ok = _ecm("start", outputs=(POSE,))
    detect = _ecm("detect", inputs=(IOSpec(name="pose", shape=(7,)),), outputs=(POSE,), version=2)
    grasp = _ecm("grasp", inputs=(consumer_input,), version=4)
    with pytest.raises(Invalid) as info:
        check_composition([ok, detect, grasp])
    err = info.value
    assert err.code is ErrorCode.INVALID
    assert err.message.startswith("plan step 1: detect@2 ∘ grasp@4: ")
    assert fragment in err.message
    assert err.details == {
        "producer": "detect@2",
        "consumer": "grasp@4",
        "position": 1,
        "input": consumer_input.name,
        "field": field,
        "expected": expected,
        "got": got,
    }


def test_bounds_are_only_compared_when_both_sides_give_them() -> None:
    unbounded = _ecm("a", outputs=(IOSpec(name="pose", shape=(7,)),))
    strict = _ecm("b", inputs=(IOSpec(name="pose", shape=(7,), low=0.0, high=0.1),))
    check_composition([unbounded, strict])
