"""The worker's wire formats and keys, without processes: parsers are total, records round-trip."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import CapevoError, Invalid, TooLarge
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.traces import COMPRESSIONS, DEFAULT_COMPRESSION
from capevo.runtime.worker import WorkerConfig
from capevo.runtime.worker_protocol import (
    MAX_EVAL_SEEDS,
    Adoption,
    EvaluateRequest,
    RuntimeKeys,
    decode_outcomes,
    encode_outcomes,
    validate_worker_id,
)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=200), json_values.map(lambda v: json.dumps(v).encode())))
def test_evaluate_request_parser_raises_only_capevo_errors(payload: bytes) -> None:
    try:
        request = EvaluateRequest.from_json(payload)
    except (Invalid, TooLarge):
        return
    # anything accepted is a well-formed request that survives its own encoding
    assert EvaluateRequest.from_json(request.to_json()) == request


@settings(max_examples=100, deadline=None)
@given(
    task=st.sampled_from(["T1", "pick", "T6", "peg_in_hole"]),
    versions=st.dictionaries(st.sampled_from(["pick.reach", "pick.lift", "x"]), st.integers(0, 10**6), max_size=3),
    seeds=st.lists(st.integers(0, 2**31), min_size=1, max_size=20),
)
def test_evaluate_request_round_trips(task: str, versions: dict[str, int], seeds: list[int]) -> None:
    request = EvaluateRequest.from_json(json.dumps({"task": task, "versions": versions, "seeds": seeds}).encode())
    assert request.task in ("pick", "peg_in_hole") and list(request.seeds) == seeds
    assert EvaluateRequest.from_json(request.to_json()) == request


def test_evaluate_request_errors_name_the_field() -> None:
    cases = [
        (b"not json", Invalid, "evaluate request is not JSON"),
        (b"[1]", Invalid, "evaluate request must be a JSON object"),
        (b'{"task": "T1", "seeds": [0], "colour": 1}', Invalid, "evaluate request: unknown field(s) colour"),
        (b'{"task": 1, "seeds": [0]}', Invalid, "evaluate request: task must be a string"),
        (b'{"task": "T9", "seeds": [0]}', Invalid, "unknown task 'T9'"),
        (b'{"task": "T1", "seeds": 3}', Invalid, "evaluate request: seeds must be a list of integers"),
        (b'{"task": "T1", "seeds": []}', Invalid, "seeds: give at least one seed"),
        (
            json.dumps({"task": "T1", "seeds": list(range(MAX_EVAL_SEEDS + 1))}).encode(),
            TooLarge,
            f"evaluate request has {MAX_EVAL_SEEDS + 1} seeds",
        ),
    ]
    for payload, cls, start in cases:
        with pytest.raises(cls) as err:
            EvaluateRequest.from_json(payload)
        assert err.value.message.startswith(start), err.value.message


def test_outcomes_round_trip_through_the_reply() -> None:
    outcomes = [
        EpisodeOutcome(
            seed=s,
            success=s % 2 == 0,
            reward=1.5 * s,
            steps=10 + s,
            duration_s=0.25,
            interventions=s,
            unsafe_steps=0,
            ecm_failures=1,
            capability_set={"pick.reach": 2},
            trace_path=None if s else "/t.mcap",
        )
        for s in range(3)
    ]
    assert decode_outcomes(encode_outcomes("w1", outcomes)) == ("w1", outcomes)
    with pytest.raises(CapevoError) as err:
        decode_outcomes(b'{"outcomes": [{"seed": 1}]}')
    assert err.value.message.startswith("malformed evaluate reply from a runtime worker")


def test_adoption_round_trips() -> None:
    a = Adoption(
        worker_id="w1",
        task="pick",
        revision=7,
        versions={"pick.reach": 1},
        pending={"pick.lift": 3},
        episodes=12,
        registry_connected=False,
        pid=42,
        started_at=1.5,
    )
    assert Adoption.from_dict(json.loads(json.dumps(a.to_dict()))) == a
    with pytest.raises(Invalid):
        Adoption.from_dict({"worker_id": "w1"})


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=70))
def test_worker_ids_are_key_chunks(worker_id: str) -> None:
    keys = RuntimeKeys("capevo")
    try:
        validate_worker_id(worker_id)
    except Invalid:
        assert (
            worker_id == "evaluate"
            or not 1 <= len(worker_id) <= 64
            or any(not (c.isascii() and (c.isalnum() or c in "_.-")) for c in worker_id)
        )
        return
    for key in (keys.alive(worker_id), keys.adopted(worker_id), keys.evaluate(worker_id)):
        assert keys.worker_of(key) == worker_id
        assert "*" not in key and "$" not in key and "//" not in key


def test_runtime_keys() -> None:
    keys = RuntimeKeys("lab/robot1")
    assert keys.adopted("w1") == "lab/robot1/runtime/w1/adopted"
    assert keys.evaluate_task("T1") == "lab/robot1/runtime/evaluate/pick"
    assert keys.adopted_all() == "lab/robot1/runtime/*/adopted"
    assert keys.worker_of(keys.evaluate_task("T1")) is None
    with pytest.raises(Invalid) as err:
        RuntimeKeys("bad/*")
    assert err.value.details["field"] == "namespace"


def test_the_cli_offers_every_trace_compression_the_writer_has() -> None:
    from capevo.cli.runtime import serve_cmd

    (option,) = [p for p in serve_cmd.params if p.name == "trace_compression"]
    assert list(option.type.choices) == list(COMPRESSIONS)  # type: ignore[attr-defined]
    assert option.default == DEFAULT_COMPRESSION


def test_worker_config_refuses_bad_settings() -> None:
    base = {"connect": ("tcp/127.0.0.1:7447",), "task": "T1"}
    for extra, message in (
        ({"connect": ()}, "a runtime worker needs the registry's endpoint (--connect)"),
        ({"episodes": 0}, "episodes must be >= 1, got 0"),
        ({"idle": True, "episodes": 3}, "give either --idle or --episodes, not both"),
        ({"worker_id": "a/b"}, "worker id 'a/b' must be 1-64 letters"),
        ({"recovery": "hope"}, "unknown recovery mode 'hope'"),
        ({"task": "T7"}, "unknown task 'T7'"),
        ({"trace_compression": "gzip"}, "unknown trace compression 'gzip'; valid: lz4, zstd, none"),
    ):
        with pytest.raises(Invalid) as err:
            WorkerConfig(**{**base, **extra})  # type: ignore[arg-type]
        assert err.value.message.startswith(message), err.value.message
