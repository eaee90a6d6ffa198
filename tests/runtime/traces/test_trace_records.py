"""Records, schemas, topic registry and metadata (capevo.runtime.traces.records invariants 1-5)."""

from __future__ import annotations

import importlib.metadata
import json
import math

import jsonschema
import numpy as np
import pytest
from _trace_helpers import make_env_step, make_metadata, one_of_each

from capevo.errors import Conflict, Corrupt, ErrorCode, Invalid
from capevo.records import CapabilitySet
from capevo.runtime.traces import codec
from capevo.runtime.traces import records as rec
from capevo.runtime.traces.records import (
    EcmInvocation,
    EnvStep,
    EpisodeSummary,
    Intervention,
    Outcome,
    PlanStep,
    TraceMetadata,
    UnsafeStep,
    package_versions,
    record_type,
    register_topic,
    topics,
)

ALL_TYPES = (PlanStep, EcmInvocation, Intervention, EnvStep, UnsafeStep, EpisodeSummary)


@pytest.mark.parametrize("record", one_of_each(), ids=lambda r: f"{type(r).__name__}")
def test_round_trip_through_dict(record: object) -> None:
    # Invariant 1, and through real JSON text as well.
    cls = type(record)
    assert cls.from_dict(record.to_dict()) == record  # type: ignore[attr-defined]
    assert cls.from_dict(json.loads(json.dumps(record.to_dict()))) == record  # type: ignore[attr-defined]


@pytest.mark.parametrize("cls", ALL_TYPES, ids=lambda c: c.__name__)
def test_schema_is_a_valid_foxglove_json_schema(cls: type) -> None:
    schema = cls.SCHEMA
    jsonschema.Draft202012Validator.check_schema(schema)
    # Foxglove requires an object at the root.
    assert schema["type"] == "object"
    assert schema["title"] == cls.SCHEMA_NAME
    assert cls.TOPIC.startswith("/")


@pytest.mark.parametrize("record", one_of_each(), ids=lambda r: f"{type(r).__name__}")
def test_to_dict_matches_schema_exactly(record: object) -> None:
    # Invariant 2: validates, and keys == properties == required.
    schema = type(record).SCHEMA
    d = record.to_dict()  # type: ignore[attr-defined]
    jsonschema.validate(d, schema, cls=jsonschema.Draft202012Validator)
    assert list(d) == list(schema["properties"])
    assert set(schema["required"]) == set(schema["properties"])
    assert schema["additionalProperties"] is False


def test_schema_rejects_wrong_types() -> None:
    # The schemas are real constraints, not decoration.
    validator = jsonschema.Draft202012Validator(EnvStep.SCHEMA)
    good = make_env_step().to_dict()
    assert validator.is_valid(good)
    for key, bad in (("episode", -1), ("obs", ["x"]), ("terminated", "no"), ("extra", 1)):
        d = dict(good)
        d[key] = bad
        assert not validator.is_valid(d), key
    d = dict(good)
    del d["reward"]
    assert not validator.is_valid(d)
    inv = jsonschema.Draft202012Validator(EcmInvocation.SCHEMA)
    d = one_of_each()[1].to_dict()
    d["outcome"] = "exploded"
    assert not inv.is_valid(d)


def test_outcome_enum_is_the_schema_enum() -> None:
    assert EcmInvocation.SCHEMA["properties"]["outcome"]["enum"] == [o.value for o in Outcome]
    for value in ("ok", "timeout", "exception", "nan", "bad_shape", "budget_exhausted"):
        assert Outcome(value).value == value


def test_non_finite_floats_decode_as_nan() -> None:
    d = make_env_step().to_dict()
    d["reward"] = None
    d["obs"] = [1.0, None]
    s = EnvStep.from_dict(d)
    assert math.isnan(s.reward)
    assert s.obs[0] == 1.0 and math.isnan(s.obs[1])
    jsonschema.validate(d, EnvStep.SCHEMA)


def test_intervention_reject_has_no_result_action() -> None:
    reject = one_of_each()[4]
    assert isinstance(reject, Intervention) and reject.rejected
    assert reject.to_dict()["result_action"] is None
    assert not one_of_each()[3].rejected  # type: ignore[union-attr]


def test_topic_registry() -> None:
    # Invariant 3.
    assert topics() == (
        "/plan",
        "/ecm/invocation",
        "/governance/intervention",
        "/env/step",
        "/safety/unsafe",
        "/episode/summary",
    )
    for cls in ALL_TYPES:
        assert record_type(cls.TOPIC) is cls
    with pytest.raises(Invalid) as exc:
        record_type("/nope")
    assert exc.value.code is ErrorCode.INVALID
    assert "unknown trace topic '/nope'" in exc.value.message
    assert "/env/step" in exc.value.message


def test_topic_cannot_be_registered_twice() -> None:
    class Impostor:
        TOPIC = "/plan"

    with pytest.raises(Conflict) as exc:
        register_topic(Impostor)
    assert exc.value.code is ErrorCode.CONFLICT
    assert "already registered to PlanStep" in exc.value.message
    assert record_type("/plan") is PlanStep
    assert register_topic(PlanStep) is PlanStep  # re-registering the owner is harmless


def test_metadata_round_trip_through_mcap_strings() -> None:
    # Invariant 4.
    m = make_metadata(worker_id="worker-3")
    mc = m.to_mcap()
    assert set(mc) == {rec.RUN_METADATA, rec.PACKAGES_METADATA}
    for record in mc.values():
        assert all(isinstance(k, str) and isinstance(v, str) for k, v in record.items())
    assert TraceMetadata.from_mcap(mc) == m
    assert m.registry_revision == 4
    assert json.loads(mc[rec.RUN_METADATA]["capability_set"]) == {"grasp": 1, "reach": 2}


def test_metadata_collects_package_versions() -> None:
    m = make_metadata()
    assert set(m.package_versions) == set(rec.PACKAGES)
    assert m.package_versions["mcap"] == importlib.metadata.version("mcap")
    assert m.package_versions["zenoh"] == importlib.metadata.version("eclipse-zenoh")


def test_package_versions_marks_missing_packages() -> None:
    def lookup(dist: str) -> str:
        if dist == "ghost":
            raise importlib.metadata.PackageNotFoundError(dist)
        return "1.0"

    assert package_versions({"ghost": "ghost", "real": "real"}, lookup=lookup) == {
        "ghost": rec.NOT_INSTALLED,
        "real": "1.0",
    }


@pytest.mark.parametrize(
    ("field", "value", "text"),
    [
        ("run_id", "", "run_id must be a non-empty string"),
        ("task", 3, "task must be a non-empty string"),
        ("phi_hash", "", "phi_hash"),
        ("seeds", (1, "2"), "seeds must be integers"),
        ("capability_set", {"a": 1}, "capability_set must be a CapabilitySet"),
    ],
)
def test_metadata_rejects_bad_fields(field: str, value: object, text: str) -> None:
    kw: dict[str, object] = {
        "run_id": "r",
        "task": "t",
        "capability_set": CapabilitySet(revision=0, active={}),
        "phi_hash": "p",
        "agent_identity_hash": "a",
    }
    kw[field] = value
    with pytest.raises(Invalid) as exc:
        TraceMetadata(**kw)  # type: ignore[arg-type]
    assert exc.value.code is ErrorCode.INVALID
    assert text in exc.value.message


def test_metadata_from_foreign_file_is_corrupt() -> None:
    with pytest.raises(Corrupt) as exc:
        TraceMetadata.from_mcap({"other": {"k": "v"}})
    assert exc.value.code is ErrorCode.CORRUPT
    assert "not a capevo trace" in exc.value.message and "other" in exc.value.message
    broken = make_metadata().to_mcap()
    broken[rec.RUN_METADATA]["seeds"] = "[oops"
    with pytest.raises(Corrupt) as exc:
        TraceMetadata.from_mcap(broken)
    assert "does not parse" in exc.value.message


def test_intervention_enforced_round_trips_and_is_inferred_for_old_files() -> None:
    counted = Intervention(
        episode=0,
        step=1,
        constraint="workspace_box",
        original_action=(1.0, 0.0),
        result_action=(1.0, 0.0),
        reason=rec.NOT_ENFORCED_PREFIX + "eef would leave the box",
        enforced=False,
    )
    assert Intervention.from_dict(counted.to_dict()) == counted
    assert codec.decode(Intervention.TOPIC, codec.encode(counted)) == counted
    jsonschema.validate(counted.to_dict(), Intervention.SCHEMA)
    assert Intervention(episode=0, step=0, constraint="c", original_action=(), result_action=None).enforced
    # A file written before the field: counting mode is read off the reason's prefix.
    old = counted.to_dict()
    del old["enforced"]
    assert Intervention.from_dict(old).enforced is False
    old["reason"] = "eef would leave the box"
    assert Intervention.from_dict(old).enforced is True


def test_terminated_outcome_round_trips() -> None:
    done = EcmInvocation(
        episode=0,
        step=2,
        ecm="reach",
        version=1,
        input_state=(0.5,),
        output=None,
        duration_s=0.001,
        outcome=Outcome.TERMINATED,
    )
    assert codec.decode(EcmInvocation.TOPIC, codec.encode(done)) == done
    jsonschema.validate(done.to_dict(), EcmInvocation.SCHEMA)


def test_records_with_arrays_compare_and_hash_by_value() -> None:
    # Invariant 5: an array field equals the tuple of its values, both ways, and a changed value differs.
    obs = np.asarray([0.5, -1.25, 3.0], dtype=np.float32)
    with_array = make_env_step(obs=obs, next_obs=obs[::-1].copy())
    with_tuples = make_env_step(obs=(0.5, -1.25, 3.0), next_obs=(3.0, -1.25, 0.5))
    assert with_array == with_tuples and with_tuples == with_array
    assert with_array != make_env_step(obs=(0.5, -1.25, 3.5), next_obs=(3.0, -1.25, 0.5))
    assert with_array != PlanStep(episode=0, step=0, ecm="reach", version=2)
    call = EcmInvocation(episode=0, step=1, ecm="reach", version=2, input_state=obs, output=(0.1,), duration_s=0.0)
    same = EcmInvocation(
        episode=0, step=1, ecm="reach", version=2, input_state=(0.5, -1.25, 3.0), output=(0.1,), duration_s=0.0
    )
    assert call == same and hash(call) == hash(same) and len({call, same}) == 1
    with_nan = make_env_step(obs=np.asarray([np.nan, 1.0], dtype=np.float32))
    assert with_nan == with_nan  # reflexive, as a dataclass's equality is


def test_records_with_arrays_give_plain_json_dicts() -> None:
    # Invariants 1 and 2 with array fields: to_dict holds plain floats only (standard json
    # encodes it) and round trips to an equal record.
    obs = np.asarray([0.5, -1.25, 3.0], dtype=np.float32)
    s = make_env_step(obs=obs, next_obs=obs)
    d = s.to_dict()
    jsonschema.validate(d, EnvStep.SCHEMA)
    assert all(type(v) is float for v in d["obs"] + d["next_obs"])
    assert EnvStep.from_dict(json.loads(json.dumps(d))) == s
    call = EcmInvocation(episode=0, step=1, ecm="reach", version=2, input_state=obs, output=None, duration_s=0.0)
    assert EcmInvocation.from_dict(json.loads(json.dumps(call.to_dict()))) == call
