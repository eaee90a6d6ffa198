"""Hand-made capability sets and decision contexts for the agent tests (no simulator)."""

from __future__ import annotations

from collections.abc import Mapping

from capevo.records import (
    ArtifactRef,
    Condition,
    Descriptor,
    EcmVersion,
    Interface,
    Kind,
    Origin,
    Predicate,
    Provenance,
    State,
)
from capevo.runtime.policy import DecisionContext, StepEnd
from capevo.runtime.tasks import task_spec


def version(name: str, descriptor: Descriptor, v: int = 1) -> EcmVersion:
    return EcmVersion(
        name=name,
        version=v,
        kind=Kind.CODE,
        state=State.ACTIVE,
        artifact=ArtifactRef(sha256="0" * 64, size=1, media_type="text/x-python"),
        descriptor=descriptor,
        interface=Interface(),
        parent=None,
        origin=Origin.MANUAL,
        provenance=Provenance(),
        gate_evidence=None,
        created_at=0.0,
        created_by="test",
    )


def task_capabilities(task: str) -> dict[str, EcmVersion]:
    """Version 1 of every ECM of ``task``, with the descriptor its task spec declares."""
    return {s.ecm: version(s.ecm, s.descriptor()) for s in task_spec(task).decomposition}


def pred(text: str, *conds: tuple[str, str, float]) -> Predicate:
    return Predicate(text=text, all=tuple(Condition(signal=s, op=o, value=v) for s, o, v in conds))


def step_version(
    name: str, description: str, done: tuple[str, str, float], when: tuple[str, str, float] | None = None
) -> EcmVersion:
    """Version 1 of ECM ``name``: done when ``done`` holds, applicable when ``when`` does (always if None)."""
    descriptor = Descriptor(
        description=description,
        applicability=pred("", when) if when else Predicate(),
        termination=pred(f"{description} done", done),
    )
    return version(name, descriptor)


def context(
    task: str,
    signals: Mapping[str, float],
    capabilities: Mapping[str, EcmVersion],
    *,
    prev: str | None = None,
    end: StepEnd = StepEnd.STARTED,
    attempts: Mapping[str, int] | None = None,
) -> DecisionContext:
    return DecisionContext(
        task=task,
        signals=dict(signals),
        previous_ecm=prev,
        previous_end=end,
        capabilities=capabilities,
        attempts=dict(attempts or {}),
    )


# T1 pick states, over the task's real signal names.
_PICK_BASE = {
    "eef_object_dist": 0.3,
    "eef_object_xy_dist": 0.25,
    "eef_object_dz": 0.15,
    "object_height_above_start": 0.0,
    "grasped": 0.0,
    "gripper_opening": 0.08,
    "success": 0.0,
}
PICK_FAR = dict(_PICK_BASE)
PICK_AT_CAN_OPEN = {**_PICK_BASE, "eef_object_dist": 0.005, "eef_object_xy_dist": 0.004, "eef_object_dz": 0.003}
PICK_GRASPED = {**PICK_AT_CAN_OPEN, "grasped": 1.0, "gripper_opening": 0.03}
PICK_LIFTED = {**PICK_GRASPED, "object_height_above_start": 0.08, "success": 1.0}
PICK_SLIPPED = {  # closed on nothing, can back on the table next to the fingers
    **_PICK_BASE,
    "eef_object_dist": 0.03,
    "eef_object_xy_dist": 0.01,
    "eef_object_dz": 0.026,
    "gripper_opening": 0.001,
}
PICK_DROPPED_OPEN = {**PICK_AT_CAN_OPEN, "object_height_above_start": 0.0}
