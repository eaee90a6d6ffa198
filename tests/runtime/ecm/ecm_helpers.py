"""Helpers for the ECM tests: registry records and a Pendulum interface."""

from __future__ import annotations

import hashlib

from capevo.records import (
    DEFAULT_MEDIA_TYPES,
    ArtifactRef,
    Descriptor,
    EcmVersion,
    Interface,
    IOSpec,
    Kind,
    Origin,
    Provenance,
    State,
)

PENDULUM_INTERFACE = Interface(
    inputs=(IOSpec(name="cos_sin", shape=(2,)), IOSpec(name="omega", shape=(1,))),
    outputs=(IOSpec(name="torque", shape=(1,), low=-2.0, high=2.0),),
)
"""Pendulum-v1's 3-dim observation split into two named inputs; its 1-dim torque action."""


def make_record(
    name: str,
    artifact: bytes,
    *,
    kind: Kind = Kind.CODE,
    version: int = 1,
    origin: Origin = Origin.MANUAL,
    interface: Interface | None = None,
) -> EcmVersion:
    """A registry record for ``artifact`` as a store would return it."""
    return EcmVersion(
        name=name,
        version=version,
        kind=kind,
        state=State.ACTIVE,
        artifact=ArtifactRef(
            sha256=hashlib.sha256(artifact).hexdigest(), size=len(artifact), media_type=DEFAULT_MEDIA_TYPES[kind]
        ),
        descriptor=Descriptor(description=f"{name} for tests"),
        interface=interface or Interface(),
        parent=None,
        origin=origin,
        provenance=Provenance(),
        gate_evidence=None,
        created_at=0.0,
        created_by="tests",
    )
