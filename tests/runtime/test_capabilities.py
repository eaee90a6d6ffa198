"""LoadedCapabilitySet and check_plan against a real LocalRegistry (no simulator needed).

Invariants of :mod:`capevo.runtime.capabilities`: one loaded version per plan ECM (1), swaps
only in begin_episode (2), failed swaps leave the set unchanged and registry outages keep
them pending (3), artifacts checked by sha256 (4), pinned versions never refreshed (5).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest
from runtime_support import ACTION, CAN, EEF, LIFT, PICK, publish, publish_pick, skill_spec

from capevo.errors import Corrupt, Invalid, NotFound
from capevo.records import Condition, Interface, IOSpec, Kind, Predicate
from capevo.registry.local import LocalRegistry
from capevo.runtime.artifact_cache import ArtifactCache
from capevo.runtime.capabilities import LoadedCapabilitySet, check_plan
from capevo.runtime.ecm import Fallback, Retry, SafeAbort

SHAPES = {"robot0_eef_pos": (3,), "Can_pos": (3,), "robot0_eef_quat": (4,)}


@pytest.fixture
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    with LocalRegistry(tmp_path / "registry", actor="tester") as reg:
        yield reg


def records(registry: LocalRegistry) -> list:
    return [registry.get_version(n) for n in PICK.ecm_names]


def test_loads_the_active_versions_of_the_plan(registry: LocalRegistry, tmp_path: Path) -> None:
    published = publish_pick(registry)
    cache = ArtifactCache(tmp_path / "cache")
    with LoadedCapabilitySet(registry, "T1", cache=cache, observation_shapes=SHAPES) as caps:
        assert caps.names == PICK.ecm_names
        assert caps.versions == {n: r.version for n, r in published.items()}
        assert caps.revision == registry.capability_set().revision
        assert dict(caps.records) == published
        assert all(caps.loaded(n).in_process for n in caps.names)
        assert caps.fallback("pick.reach") is None
    # every artifact went through the cache, under its sha256
    assert all(r.artifact.sha256 in cache for r in published.values())
    assert cache.stats["stored"] == 3


def test_missing_active_version_is_not_found(registry: LocalRegistry) -> None:
    publish(registry, "pick.reach", LIFT)
    publish(registry, "pick.grasp", LIFT)
    with pytest.raises(NotFound) as err:
        LoadedCapabilitySet(registry, "pick")
    assert err.value.code.value == "not_found"
    assert err.value.message.startswith("task 'pick' needs ECM 'pick.lift', which has no active version")


def test_pinned_ecm_outside_the_plan_is_invalid(registry: LocalRegistry) -> None:
    publish_pick(registry)
    with pytest.raises(Invalid) as err:
        LoadedCapabilitySet(registry, "pick", versions={"place.reach": 0})
    assert err.value.message == (
        "ECM(s) place.reach are not in the plan of task 'pick' (pick.reach, pick.grasp, pick.lift)"
    )


def test_unknown_recovery_mode_is_invalid(registry: LocalRegistry) -> None:
    publish_pick(registry)
    with pytest.raises(Invalid) as err:
        LoadedCapabilitySet(registry, "pick", recovery="pray")
    assert err.value.message == "unknown recovery mode 'pray'; valid: abort, retry, fallback, retry-fallback"


def test_artifact_not_matching_its_record_is_corrupt(registry: LocalRegistry, tmp_path: Path) -> None:
    published = publish_pick(registry)
    lift = published["pick.lift"]
    blob = registry.blobs.path_for(lift.artifact.sha256)
    blob.chmod(0o644)
    blob.write_bytes(b"def act(obs, params):\n    return [1.0] * 7\n")
    with pytest.raises(Corrupt) as err:
        LoadedCapabilitySet(registry, "pick")
    assert err.value.code.value == "corrupt"
    assert lift.artifact.sha256 in err.value.message


def test_corrupt_cache_entry_is_refetched_from_the_registry(registry: LocalRegistry, tmp_path: Path) -> None:
    published = publish_pick(registry)
    cache = ArtifactCache(tmp_path / "cache")
    LoadedCapabilitySet(registry, "pick", cache=cache).close()
    entry = cache.path_for(published["pick.lift"].artifact.sha256)
    entry.write_bytes(b"def act(obs, params):\n    return [1.0] * 7\n")  # tampered on disk
    with LoadedCapabilitySet(registry, "pick", cache=cache) as caps:
        assert caps.versions["pick.lift"] == published["pick.lift"].version
    assert cache.stats["corrupt"] == 1
    assert entry.read_bytes() == LIFT.encode()


def test_recovery_strategies_by_mode(registry: LocalRegistry) -> None:
    publish_pick(registry)
    publish(registry, "pick.lift", LIFT.replace('"speed": 1.0', '"speed": 0.5'))
    with LoadedCapabilitySet(registry, "pick", recovery="abort") as caps:
        assert isinstance(caps.make_recovery("pick.lift"), SafeAbort)
    with LoadedCapabilitySet(registry, "pick", recovery="retry-fallback") as caps:
        strategy = caps.make_recovery("pick.lift")
        assert isinstance(strategy, Retry) and isinstance(strategy.then, Fallback)
        assert [e.version for e in strategy.alternatives()] == [0]
        # no older version of reach: retry, then hold still
        reach = caps.make_recovery("pick.reach")
        assert isinstance(reach, Retry) and isinstance(reach.then, SafeAbort)


# --- hot swap ------------------------------------------------------------------------------


def test_swap_is_queued_then_applied_at_the_episode_boundary(registry: LocalRegistry) -> None:
    publish_pick(registry)
    with LoadedCapabilitySet(registry, "pick") as caps:
        before = caps.records
        new = publish(registry, "pick.lift", LIFT.replace('"speed": 1.0', '"speed": 0.5'))
        assert caps.refresh() == {"pick.lift": new.version}
        # queued, not applied
        assert caps.versions["pick.lift"] == 0 and caps.pending() == {"pick.lift": new.version}
        assert caps.records is before
        old = caps.loaded("pick.lift")
        (result,) = caps.begin_episode()
        assert (result.applied, result.from_version, result.to_version) == (True, 0, new.version)
        assert caps.versions["pick.lift"] == new.version and caps.pending() == {}
        assert caps.revision == registry.capability_set().revision
        # the replaced version is kept as the fallback
        assert caps.fallback("pick.lift") is old
        assert caps.begin_episode() == []


def test_swap_to_the_loaded_version_is_a_no_op(registry: LocalRegistry) -> None:
    publish_pick(registry)
    with LoadedCapabilitySet(registry, "pick") as caps:
        caps.queue_swap("pick.lift", 0)
        assert caps.begin_episode() == []


def test_pinned_versions_are_never_refreshed(registry: LocalRegistry) -> None:
    publish_pick(registry)
    publish(registry, "pick.lift", LIFT.replace('"speed": 1.0', '"speed": 0.5'))
    with LoadedCapabilitySet(registry, "pick", versions={"pick.lift": 0}) as caps:
        assert caps.versions["pick.lift"] == 0
        assert caps.refresh() == {}
        assert caps.pending() == {}


def test_swap_to_code_that_does_not_load_is_dropped_and_set_unchanged(registry: LocalRegistry) -> None:
    publish_pick(registry)
    broken = registry.publish("pick.lift", b"def act(obs, params:\n", skill_spec("pick.lift"))
    with LoadedCapabilitySet(registry, "pick") as caps:
        caps.queue_swap("pick.lift", broken.version)
        (result,) = caps.begin_episode()
        assert not result.applied and not result.pending
        assert result.error is not None and "invalid" in result.error
        assert caps.versions["pick.lift"] == 0 and caps.pending() == {}


def test_swap_that_breaks_composition_is_refused(registry: LocalRegistry) -> None:
    publish_pick(registry)
    bad_spec = dataclasses.replace(
        skill_spec("pick.lift"), interface=Interface(inputs=(EEF,), outputs=(IOSpec(name="action", shape=(6,)),))
    )
    bad = registry.publish("pick.lift", LIFT.encode(), bad_spec)
    with LoadedCapabilitySet(registry, "pick") as caps:
        caps.queue_swap("pick.lift", bad.version)
        (result,) = caps.begin_episode()
    assert not result.applied
    assert result.error == (
        f"[invalid] plan step 2 (pick.lift@{bad.version}): outputs total 6 values, but task 'pick' takes actions of 7"
    )


def test_swap_while_the_registry_is_away_stays_pending(registry: LocalRegistry, tmp_path: Path) -> None:
    publish_pick(registry)
    new = publish(registry, "pick.lift", LIFT.replace('"speed": 1.0', '"speed": 0.5'))
    other = LocalRegistry(registry.root, actor="runtime")
    caps = LoadedCapabilitySet(other, "pick", versions={"pick.lift": 0})
    try:
        caps.queue_swap("pick.lift", new.version, record=new)
        other.close()  # the registry goes away before the boundary
        (result,) = caps.begin_episode()
        assert not result.applied and result.pending
        assert result.error is not None and "unavailable" in result.error
        assert caps.pending() == {"pick.lift": new.version}
        assert caps.versions["pick.lift"] == 0
    finally:
        caps.close()


def test_queue_swap_refuses_ecms_outside_the_plan(registry: LocalRegistry) -> None:
    publish_pick(registry)
    with LoadedCapabilitySet(registry, "pick") as caps, pytest.raises(Invalid) as err:
        caps.queue_swap("place.reach", 1)
    assert (
        err.value.message
        == "cannot swap 'place.reach': not in the plan of task 'pick' (pick.reach, pick.grasp, pick.lift)"
    )


# --- check_plan ------------------------------------------------------------------------------


def with_interface(record, inputs: tuple[IOSpec, ...], outputs: tuple[IOSpec, ...] = ACTION):  # type: ignore[no-untyped-def]
    return dataclasses.replace(record, interface=Interface(inputs=inputs, outputs=outputs))


def test_check_plan_accepts_the_published_pick_plan(registry: LocalRegistry) -> None:
    publish_pick(registry)
    check_plan(PICK, records(registry), observation_shapes=SHAPES)
    check_plan(PICK, records(registry))  # names only


def test_check_plan_names_an_observation_shape_mismatch(registry: LocalRegistry) -> None:
    publish_pick(registry)
    plan = records(registry)
    plan[1] = with_interface(plan[1], (IOSpec(name="Can_pos", shape=(4,)),))
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan, observation_shapes=SHAPES)
    assert err.value.message == (
        "plan step 1 (pick.grasp@0): input 'Can_pos' has shape [4], but the task's observation 'Can_pos' has shape [3]"
    )
    assert err.value.details["field"] == "interface.inputs.Can_pos.shape"


def test_check_plan_first_ecm_cannot_consume_a_non_observation(registry: LocalRegistry) -> None:
    publish_pick(registry)
    plan = records(registry)
    plan[0] = with_interface(plan[0], (IOSpec(name="grip_target", shape=(3,)),))
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan, observation_shapes=SHAPES)
    assert err.value.message.startswith(
        "plan step 0 (pick.reach@0): input 'grip_target' is not an observation of task 'pick' and no ECM runs before"
    )


def test_check_plan_composes_outputs_into_the_next_inputs(registry: LocalRegistry) -> None:
    publish_pick(registry)
    plan = records(registry)
    grip = IOSpec(name="grip", shape=(1,), low=-1.0, high=1.0)
    split_action = (IOSpec(name="move", shape=(3,)), IOSpec(name="turn", shape=(3,)), grip)
    plan[0] = with_interface(plan[0], (EEF, CAN), split_action)
    # grasp consumes reach's last gripper command (c_0 ∘ c_1) besides observations
    plan[1] = with_interface(plan[1], (EEF, dataclasses.replace(grip, low=-2.0)))
    check_plan(PICK, plan, observation_shapes=SHAPES)
    plan[1] = with_interface(plan[1], (EEF, dataclasses.replace(grip, low=-0.5)))
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan, observation_shapes=SHAPES)
    assert err.value.details["field"] == "low"
    assert err.value.details["producer"] == "pick.reach@0" and err.value.details["consumer"] == "pick.grasp@0"
    assert err.value.message.endswith("(and it is not an observation of task 'pick')")
    plan[1] = with_interface(plan[1], (EEF, IOSpec(name="grip", shape=(2,))))
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan, observation_shapes=SHAPES)
    assert err.value.details["field"] == "shape"
    # the producer's outputs must still make one action of the task
    plan[0] = with_interface(plan[0], (EEF, CAN), (*ACTION, grip))
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan, observation_shapes=SHAPES)
    assert err.value.message == "plan step 0 (pick.reach@0): outputs total 8 values, but task 'pick' takes actions of 7"


def test_check_plan_refuses_unknown_signals_and_prompts(registry: LocalRegistry) -> None:
    publish_pick(registry)
    plan = records(registry)
    plan[2] = dataclasses.replace(
        plan[2],
        descriptor=dataclasses.replace(
            plan[2].descriptor, termination=Predicate(all=(Condition(signal="can_height", op=">", value=0.1),))
        ),
    )
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan)
    assert err.value.message.startswith(
        "plan step 2 (pick.lift@0): termination predicate uses signal(s) can_height, which task 'pick' does not expose"
    )
    plan = records(registry)
    plan[0] = dataclasses.replace(plan[0], kind=Kind.PROMPT)
    with pytest.raises(Invalid) as err:
        check_plan(PICK, plan)
    assert err.value.message == "plan step 0 (pick.reach@0): a prompt ECM cannot be executed step by step"
